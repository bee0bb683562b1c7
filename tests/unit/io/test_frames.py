"""Frames reader: natural order, ignored files, grey conversion, and every kind of bad input."""

import os

import cv2
import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.io.frames import read_frames


def write_frames(folder, names, size=(8, 6)):
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), np.full((size[1], size[0], 3), k * 10, np.uint8))


def test_natural_order_any_case_extensions_and_other_files_ignored(tmp_path):
    write_frames(tmp_path, ["frame2.png", "frame10.PNG", "frame1.jpg", "frame3.TIF"])
    (tmp_path / "notes.txt").write_text("not a frame")
    (tmp_path / "sub.png").mkdir()
    frames = read_frames(tmp_path)
    assert [p.name for p in frames.files] == ["frame1.jpg", "frame2.png", "frame3.TIF", "frame10.PNG"]
    images = list(frames)
    assert frames.count == 4 and all(im.ndim == 2 and im.dtype == np.uint8 for im in images)
    # written as 0, 10, 20, 30 in the order frame2, frame10, frame1, frame3 (jpg is lossy)
    assert [int(round(im.mean())) for im in images] == pytest.approx([20, 0, 30, 10], abs=2)


def test_glob(tmp_path):
    write_frames(tmp_path, ["a_1.png", "a_2.png", "a_10.png", "b_1.png"])
    frames = read_frames(str(tmp_path / "a_*.png"))
    assert [p.name for p in frames.files] == ["a_1.png", "a_2.png", "a_10.png"]
    with pytest.raises(InvalidInputError, match="matches no image"):
        read_frames(str(tmp_path / "c_*.png"))


def test_missing_empty_and_too_short(tmp_path):
    with pytest.raises(InvalidInputError, match="does not exist"):
        read_frames(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    with pytest.raises(InvalidInputError, match="no image files"):
        read_frames(tmp_path / "empty")
    write_frames(tmp_path / "two", ["1.png", "2.png"])
    with pytest.raises(NotEnoughDataError, match="at least 3"):
        read_frames(tmp_path / "two")


def test_bad_files_are_named(tmp_path):
    write_frames(tmp_path / "fake", ["1.png", "2.png", "3.png"])
    (tmp_path / "fake" / "2.png").write_text("this is text")
    with pytest.raises(InvalidInputError, match=r"2\.png: not a readable image"):
        list(read_frames(tmp_path / "fake"))

    write_frames(tmp_path / "cut", ["1.png", "2.png", "3.png"], size=(64, 48))
    data = (tmp_path / "cut" / "3.png").read_bytes()
    (tmp_path / "cut" / "3.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(InvalidInputError, match=r"3\.png"):
        list(read_frames(tmp_path / "cut"))

    write_frames(tmp_path / "sizes", ["1.png", "2.png"])
    write_frames(tmp_path / "other", ["3.png"], size=(9, 6))
    (tmp_path / "other" / "3.png").rename(tmp_path / "sizes" / "3.png")
    with pytest.raises(InvalidInputError, match=r"3\.png: 9×6, but 1\.png is 8×6"):
        list(read_frames(tmp_path / "sizes"))


def test_video_and_undecodable_video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for k in range(5):
        writer.write(np.full((24, 32, 3), 40 * k, np.uint8))
    writer.release()
    frames = read_frames(path)
    images = list(frames)
    assert len(images) == 5 and images[0].shape == (24, 32)
    bogus = tmp_path / "clip.mp4"
    bogus.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(InvalidInputError, match="clip.mp4"):
        read_frames(bogus)


@pytest.mark.parametrize("with_pyav", [True, False])
def test_undecodable_video_message_is_the_same_with_or_without_pyav(tmp_path, monkeypatch, with_pyav):
    import sys

    if not with_pyav:
        monkeypatch.setitem(sys.modules, "av", None)  # makes `import av` raise ImportError
    bogus = tmp_path / "broken.mp4"
    bogus.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(InvalidInputError, match=r"broken\.mp4: not a decodable video"):
        list(read_frames(bogus))


def test_float32_tiff_that_opencv_reads_is_a_frame(tmp_path):
    """Issue 20: 32-bit float TIFFs were refused as 'not an image' although OpenCV reads them."""
    ramp = np.linspace(0.0, 1.0, 8 * 6, dtype=np.float32).reshape(6, 8)
    for k in range(3):
        assert cv2.imwrite(str(tmp_path / f"f{k}.tiff"), ramp * (k + 1) / 3)
    assert cv2.imdecode(np.fromfile(tmp_path / "f0.tiff", np.uint8), cv2.IMREAD_GRAYSCALE) is None
    frames = list(read_frames(tmp_path))
    assert all(f.dtype == np.uint8 and f.shape == (6, 8) for f in frames)
    # [0, 1] intensities scaled by 255
    np.testing.assert_array_equal(frames[2], np.rint(ramp * 255).astype(np.uint8))
    np.testing.assert_array_equal(frames[0], np.rint(ramp / 3 * 255).astype(np.uint8))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
def test_a_pipe_a_device_or_a_link_loop_is_named_as_what_it_is_and_never_opened(tmp_path):
    os.mkfifo(tmp_path / "clip.avi")  # nobody writes into it: opening it would wait for ever
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    cases = [(tmp_path / "clip.avi", r"is a named pipe \(FIFO\), not a file"), ("/dev/zero", "is a character device"),
             (tmp_path / "loop", "is a symbolic link loop"), (tmp_path / "gone", "is a broken symbolic link")]
    for path, words in cases:
        with pytest.raises(InvalidInputError, match=words):
            read_frames(path)
    write_frames(tmp_path / "frames", ["1.png", "2.png", "3.png"])
    os.mkfifo(tmp_path / "frames" / "4.png")  # a pipe among the frames is not a frame
    assert [p.name for p in read_frames(tmp_path / "frames").files] == ["1.png", "2.png", "3.png"]


def test_names_that_are_not_utf8_are_read_without_handing_them_to_opencv(tmp_path):
    """OpenCV crashes (SIGSEGV) on a path that is not UTF-8 text; frames and videos are read from Python."""
    write_frames(tmp_path / "frames", ["1.png", "2.png", "3.png"])  # cv2.imwrite too crashes on such a name
    folder = (tmp_path / "frames").rename(tmp_path / os.fsdecode(b"frames\xff"))
    assert [int(f.mean()) for f in read_frames(folder)] == [0, 10, 20]
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for k in range(5):
        writer.write(np.full((24, 32, 3), 40 * k, np.uint8))
    writer.release()
    video = path.rename(tmp_path / os.fsdecode(b"clip\xff.avi"))
    images = list(read_frames(video))
    assert len(images) == 5 and [int(round(im.mean() / 40)) for im in images] == [0, 1, 2, 3, 4]
