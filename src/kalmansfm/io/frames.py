"""Frames in (a folder of images, a glob pattern, or a video file, as grey arrays) and frames out (PNG files of a run).

:func:`read_frames` checks what it can up front (the path exists, the folder holds
images, there are enough of them) and returns a :class:`FrameSource` that decodes
the frames lazily, one at a time, in natural order (``frame2`` before ``frame10``).
Decoding problems found later (a truncated file, a frame of another size) raise
:class:`~kalmansfm.errors.InvalidInputError` naming the file.
"""

from __future__ import annotations

import glob as globbing
import io
import os
import re
import shutil
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError
from ..tracking.grey import colour_to_grey
from ._csv import where
from .atomic import OutputDirectory
from .paths import native_path, path_problem

__all__ = [
    "IMAGE_EXTENSIONS",
    "FrameSource",
    "encode_png",
    "frame_name",
    "grey_uint8",
    "list_image_files",
    "natural_key",
    "quiet_decoders",
    "read_frames",
    "FRAMES_VIDEO",
    "MAX_COPIED_BITS_PER_PIXEL",
    "VIDEO_SUFFIXES",
    "MAX_PNG_FRAMES",
    "encode_jpeg",
    "encode_video",
    "is_frames_video",
    "stage_frames",
]

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff"})
MIN_FRAMES = 3


def natural_key(name: str) -> list[object]:
    """Sort key that orders embedded numbers by value: ``frame2`` < ``frame10``.

    Examples
    --------
    >>> sorted(["f10.png", "f2.png", "f1.png"], key=natural_key)
    ['f1.png', 'f2.png', 'f10.png']
    """
    return [(0, int(part), "") if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name) if part]


def _is_image_name(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS


def list_image_files(folder: str | os.PathLike[str]) -> list[Path]:
    """Image files directly inside ``folder`` (by extension, any case), in natural order.

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> for name in ["b10.PNG", "b2.png", "notes.txt"]:
    ...     _ = (d / name).write_bytes(b"")
    >>> [p.name for p in list_image_files(d)]
    ['b2.png', 'b10.PNG']
    """
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and _is_image_name(p)]
    return sorted(files, key=lambda p: natural_key(p.name))


@contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """Point file descriptor 2 at the null device for the block (main thread only).

    libpng and libtiff print some of their complaints ("libpng error: PNG input buffer
    is incomplete") with their own fprintf, past OpenCV's log level.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # another thread's output must not vanish with ours
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@contextmanager
def quiet_decoders() -> Iterator[None]:
    """Silence OpenCV's, FFmpeg's, libpng's and libtiff's own messages on stderr while decoding.

    A file they cannot decode is reported once, as our InvalidInputError naming the
    file; their native log lines ("PNG input buffer is incomplete", "moov atom not
    found") would otherwise reach the terminal as well.  OpenCV reads
    OPENCV_FFMPEG_LOGLEVEL once, when its FFmpeg backend first opens a file, so that
    one stays set for the process (-8 = AV_LOG_QUIET; a value the user set is kept).
    """
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with _native_stderr_silenced():
            yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


def grey_uint8(image: np.ndarray) -> np.ndarray:
    """A decoded image as (H, W) uint8 grey.

    Colour (BGR, BGRA) becomes grey by :func:`kalmansfm.tracking.grey.colour_to_grey`, the
    tracker's policy too; 16-bit values are divided by 257; floating-point images (such as
    32-bit TIFF) are taken to hold intensities in [0, 1] when no value exceeds 1 and in
    [0, 255] otherwise (NaN becomes 0).

    Examples
    --------
    >>> grey_uint8(np.array([[0.0, 0.5, 1.0]], np.float32)).tolist()
    [[0, 128, 255]]
    >>> grey_uint8(np.array([[0, 65535]], np.uint16)).tolist()
    [[0, 255]]
    """
    image = colour_to_grey(image)
    if image.dtype == np.uint8:
        return image
    if image.dtype.kind == "f":
        values = np.nan_to_num(image.astype(np.float64), nan=0.0, posinf=255.0, neginf=0.0)
        scale = 255.0 if values.max(initial=0.0) <= 1.0 else 1.0
        return np.clip(np.rint(values * scale), 0, 255).astype(np.uint8)
    return np.clip(np.rint(image.astype(np.float64) / 257.0), 0, 255).astype(np.uint8)


def decode_image_file(path: Path, *flags: int) -> np.ndarray | None:
    """The image in the file ``path`` decoded by OpenCV with the first of ``flags`` that succeeds (None if none does).

    The file is read by NumPy, not ``cv2.imread``, which crashes on names that are not UTF-8; the decoders'
    own messages are silenced (:func:`quiet_decoders`).  A file that cannot be read raises InvalidInputError.

    Examples
    --------
    >>> import tempfile
    >>> f = Path(tempfile.mkdtemp()) / "a.png"
    >>> _ = f.write_bytes(cv2.imencode(".png", np.full((2, 3), 7, np.uint8))[1].tobytes())
    >>> empty = f.with_name("empty.png"); _ = empty.write_bytes(b"")
    >>> decode_image_file(f, cv2.IMREAD_UNCHANGED).shape, decode_image_file(empty, cv2.IMREAD_UNCHANGED) is None
    ((2, 3), True)
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InvalidInputError(f"{where(path)}: cannot read the image ({exc.strerror or exc})") from None
    if not data.size:
        return None
    with quiet_decoders():
        for flag in flags:
            image = cv2.imdecode(data, flag)
            if image is not None:
                return image
    return None


def _decode_image(path: Path) -> np.ndarray:
    # unchanged: e.g. a 32-bit float TIFF, which only an unchanged read gives
    image = decode_image_file(path, cv2.IMREAD_GRAYSCALE, cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim not in (2, 3) or image.size == 0:
        raise InvalidInputError(f"{where(path)}: not a readable image (empty, truncated or not an image)")
    if image.ndim == 3 and image.shape[2] not in (3, 4):
        raise InvalidInputError(f"{where(path)}: {image.shape[2]} channels; an image must be grey, BGR or BGRA")
    return grey_uint8(image)


@dataclass(frozen=True)
class FrameSource:
    """Lazily decoded grey frames (uint8, (H, W)), iterable any number of times.

    Attributes
    ----------
    description : the input as the user gave it.
    files : the image files in order, or empty for a video.
    video : the video file, or None.
    count : number of frames when known in advance (exact for images; the
        container's claim for a video), else None.
    """

    description: str
    files: tuple[Path, ...] = ()
    video: Path | None = None
    count: int | None = None

    def __iter__(self) -> Iterator[np.ndarray]:
        if self.video is not None:
            yield from _video_frames(self.video)
            return
        shape = None
        for path in self.files:
            image = _decode_image(path)
            if shape is None:
                shape = image.shape
            elif image.shape != shape:
                raise InvalidInputError(
                    f"{where(path)}: {image.shape[1]}×{image.shape[0]}, but {self.files[0].name} is "
                    f"{shape[1]}×{shape[0]}; all frames must have the same size"
                )
            yield image

    @property
    def paths(self) -> tuple[Path, ...]:
        """The files the frames are read from: the images, or the video."""
        return self.files if self.video is None else (self.video,)

    def __len__(self) -> int:
        if self.count is None:
            raise TypeError("the number of frames of this video is not known in advance")
        return self.count


def _video_frames(path: Path) -> Iterator[np.ndarray]:
    name = native_path(path)
    if name is None:  # OpenCV crashes on a name that is not UTF-8; PyAV reads the open file
        yield from _video_frames_pyav(path)
        return
    with quiet_decoders():
        capture = cv2.VideoCapture(name)
    produced = 0
    try:
        if capture.isOpened():
            while True:
                ok, frame = capture.read()
                if not ok:
                    break
                produced += 1
                yield colour_to_grey(frame)
    finally:
        capture.release()
    if produced:
        return
    yield from _video_frames_pyav(path)


def _video_frames_pyav(path: Path) -> Iterator[np.ndarray]:
    try:
        import av
    except ImportError:
        raise InvalidInputError(f"{where(path)}: not a decodable video (OpenCV could not read it; PyAV is not installed)") from None
    # libav's own log lines would go straight to stderr; PANIC routes only fatal ones to Python logging
    previous_level = av.logging.get_level()
    av.logging.set_level(av.logging.PANIC)
    produced = 0
    try:
        with open(path, "rb") as handle, av.open(handle) as container:
            for frame in container.decode(video=0):
                produced += 1
                yield frame.to_ndarray(format="gray")
    except OSError as exc:
        raise InvalidInputError(f"{where(path)}: cannot read the video ({exc.strerror or exc})") from None
    except (av.error.FFmpegError, ValueError, IndexError) as exc:  # type: ignore[attr-defined]
        if not produced:
            raise InvalidInputError(f"{where(path)}: not a decodable video or image ({_decoder_reason(exc)})") from None
        raise InvalidInputError(
            f"{where(path)}: video decoding failed after frame {produced - 1} ({_decoder_reason(exc)})"
        ) from None
    finally:
        av.logging.set_level(previous_level)
    if not produced:
        raise InvalidInputError(f"{where(path)}: not a decodable video (no frames)")


def _decoder_reason(exc: Exception) -> str:
    """What the decoder said, in words: FFmpeg's message and its last log line, without the raw error number.

    Examples
    --------
    >>> _decoder_reason(ValueError("no video stream"))
    'no video stream'
    """
    message = getattr(exc, "strerror", None)
    if not isinstance(message, str) or not message:
        return str(exc)
    log = getattr(exc, "log", None)
    detail = log[2].strip() if isinstance(log, tuple) and len(log) == 3 and isinstance(log[2], str) else ""
    reason = f"FFmpeg: {message[:1].lower()}{message[1:]}"
    return f"{reason}; {detail}" if detail else reason


def _video_count(path: Path) -> int | None:
    name = native_path(path)
    if name is None:
        return None
    with quiet_decoders():
        capture = cv2.VideoCapture(name)
    try:
        if not capture.isOpened():
            return None
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        return count if count > 0 else None
    finally:
        capture.release()


def read_frames(source: str | os.PathLike[str], min_frames: int = MIN_FRAMES) -> FrameSource:
    """Frames from a folder of images, a glob pattern or a video file.

    Parameters
    ----------
    source : folder (image files taken by extension — png, jpg, jpeg, pgm, ppm,
        bmp, tif, tiff, any case — other files ignored; natural order), glob
        pattern (e.g. ``"shots/img_*.png"``), or video file (OpenCV, else PyAV).
    min_frames : fewer frames than this is an error (checked here for images).

    Returns
    -------
    FrameSource
        Iterating yields (H, W) uint8 grey frames; colour is converted to grey, other
        depths as :func:`grey_uint8` says.

    Raises
    ------
    InvalidInputError
        Missing path, no images, a file that is not an image or video; a named pipe, a
        device or a symbolic link loop is named as what it is (it is never opened).
    NotEnoughDataError
        Fewer than ``min_frames`` images.

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> for k in range(3):
    ...     _ = cv2.imwrite(str(d / f"f{k}.png"), np.full((4, 6, 3), 10 * k, np.uint8))
    >>> frames = read_frames(d)
    >>> frames.count, [int(f[0, 0]) for f in frames], next(iter(frames)).shape
    (3, [0, 10, 20], (4, 6))
    """
    text = os.fspath(source)
    path = Path(text)
    problem = path_problem(path)
    if problem is not None:
        raise InvalidInputError(f"input {text} is {problem} (expected a folder of images, a glob or a video)")
    if path.is_dir():
        files = list_image_files(path)
        if not files:
            raise InvalidInputError(
                f"folder {path} holds no image files (looked for {', '.join(sorted(IMAGE_EXTENSIONS))})"
            )
        description = str(path)
    elif path.is_file():
        if _is_image_name(path):
            raise NotEnoughDataError(f"{where(path)}: a single image; tracking needs at least {min_frames} frames")
        # A video: check that something can decode it before promising frames.
        first = next(iter(_video_frames(path)), None)
        if first is None:
            raise InvalidInputError(f"{where(path)}: not a decodable video")
        return FrameSource(description=str(path), video=path, count=_video_count(path))
    elif any(ch in text for ch in "*?["):
        files = sorted(
            (Path(p) for p in globbing.glob(text) if Path(p).is_file() and _is_image_name(Path(p))),
            key=lambda p: natural_key(str(p)),
        )
        if not files:
            raise InvalidInputError(f"the pattern {text!r} matches no image files")
        description = text
    else:
        raise InvalidInputError(f"input {text} does not exist (expected a folder of images, a glob or a video)")
    if len(files) < min_frames:
        raise NotEnoughDataError(f"{description} holds {len(files)} image(s); tracking needs at least {min_frames} frames")
    return FrameSource(description=description, files=tuple(files), count=len(files))


def frame_name(index: int, n_frames: int) -> str:
    """File name of frame ``index`` in a sequence of ``n_frames`` (at least three digits).

    Examples
    --------
    >>> frame_name(7, 30), frame_name(7, 5000)
    ('frame_007.png', 'frame_0007.png')
    """
    digits = max(3, len(str(max(n_frames - 1, 0))))
    return f"frame_{index:0{digits}d}.png"


def encode_png(image: np.ndarray) -> bytes:
    """A grey or BGR image as PNG bytes (values outside 0-255 are clipped)."""
    if image.dtype != np.uint8:
        image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 grey or BGR image
        raise RuntimeError("could not encode a frame as PNG")
    return png.tobytes()


def encode_jpeg(image: np.ndarray, quality: int = 85) -> bytes:
    """A grey or BGR uint8 image as JPEG bytes (for pictures shown, not kept: the report's player)."""
    ok, data = cv2.imencode(".jpg", np.asarray(image, dtype=np.uint8), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 grey or BGR image
        raise RuntimeError("could not encode a frame as JPEG")
    return data.tobytes()


#: A sequence of at most this many frames is kept as PNG files (lossless); a longer one as one video.
MAX_PNG_FRAMES = 120
#: The video a long sequence's frames are encoded into.
FRAMES_VIDEO = "frames.mp4"
#: A long clip read from one compressed video file is kept as a copy of that file, ``frames`` plus its suffix,
#: when the file holds at most this many bits per pixel of each frame (compressed video holds a few hundredths;
#: raw or motion-JPEG video several, which is re-encoded instead).
MAX_COPIED_BITS_PER_PIXEL = 0.5
#: The file suffixes of videos (a run's frames video is ``frames`` with one of them).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".flv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")


def is_frames_video(name: str) -> bool:
    """Whether ``name`` (in a run folder) is the video that holds the run's frames.

    Examples
    --------
    >>> is_frames_video("frames.mp4"), is_frames_video("frames.flv"), is_frames_video("frames/frame_001.png")
    (True, True, False)
    """
    path = Path(name)
    return path.stem == "frames" and path.parent == Path(".") and path.suffix.lower() in VIDEO_SUFFIXES


def stage_frames(out: OutputDirectory, frames: list[np.ndarray], folder: str = "",
                 source: Path | None = None) -> list[str]:
    """Stage ``frames`` for the run's report; returns the names written.

    Up to :data:`MAX_PNG_FRAMES` frames are ``folder/frame_NNN.png`` files, exactly as they were
    tracked.  A longer sequence is kept as one video: when ``source`` is the compressed video file
    the frames are all the frames of, a copy of it (``frames`` with its suffix: the same frames
    bit for bit, no time spent encoding); otherwise one H.264 video, :data:`FRAMES_VIDEO` (quality
    18, about one grey level of error, a twentieth of the PNGs' size), so that a long clip's run
    folder stays the size of its results.
    """
    if len(frames) > MAX_PNG_FRAMES:
        if source is not None and _copyable(source, frames):
            name = "frames" + source.suffix.lower()
            shutil.copyfile(source, out.file(name))
            return [name]
        out.write_bytes(FRAMES_VIDEO, encode_video(frames))
        return [FRAMES_VIDEO]
    names = [f"{folder}{frame_name(f, len(frames))}" for f in range(len(frames))]
    for name, frame in zip(names, frames):
        out.write_bytes(name, encode_png(np.asarray(frame)))
    return names


def _copyable(source: Path, frames: list[np.ndarray]) -> bool:
    """A compressed video file, small for its frames (:data:`MAX_COPIED_BITS_PER_PIXEL`)."""
    if source.suffix.lower() not in VIDEO_SUFFIXES or not source.is_file():
        return False
    height, width = np.asarray(frames[0]).shape[:2]  # the frames of one video share a size
    return 8 * source.stat().st_size <= MAX_COPIED_BITS_PER_PIXEL * len(frames) * height * width


def encode_video(frames: list[np.ndarray], fps: int = 25) -> bytes:
    """The bytes of an H.264 MP4 of ``frames`` (grey or BGR uint8, one size; odd sizes padded by a pixel).

    Examples
    --------
    >>> data = encode_video([np.full((16, 16), 10 * k, np.uint8) for k in range(3)])
    >>> data[4:8]
    b'ftyp'
    """
    import av

    first = np.asarray(frames[0])
    height, width = first.shape[:2]
    padded = (width + width % 2, height + height % 2)  # yuv420p needs even sizes
    buffer = io.BytesIO()
    with av.open(buffer, "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = padded
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}
        for frame in frames:
            image = np.asarray(frame)
            image = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            if (image.shape[1], image.shape[0]) != padded:
                image = cv2.copyMakeBorder(image, 0, padded[1] - image.shape[0], 0, padded[0] - image.shape[1],
                                           cv2.BORDER_REPLICATE)
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="gray")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return buffer.getvalue()
