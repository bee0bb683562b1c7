"""The bytes of a COLMAP sparse model: its text and binary files, parsed to columns and written from them.

The layout is COLMAP's (colmap.github.io/format.html, "Output Format"), little-endian binary:

* ``cameras``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` — binary: uint64 count, then per camera
  uint32 id, int32 model id, uint64 width, uint64 height, float64 params;
* ``images``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and
  ``X Y POINT3D_ID`` triples (``-1`` for none) — binary: uint64 count, then per image uint32 id,
  4 + 3 float64, uint32 camera id, the name NUL-terminated, uint64 point count and per point
  float64 x, y and uint64 point id (2⁶⁴ - 1 for none);
* ``points3D``: ``POINT3D_ID X Y Z R G B ERROR`` then ``IMAGE_ID POINT2D_IDX`` pairs — binary:
  uint64 count, then per point uint64 id, 3 float64, 3 uint8, float64 error, uint64 track length
  and per element uint32 image id, uint32 point index.

Columns travel as plain dicts of arrays between here and :mod:`kalmansfm.io.colmap`, which wraps
them in its records and checks how they refer to each other; here each file is checked on its
own: numbers, counts, truncation, camera models.  Every problem is an
:class:`~kalmansfm.InvalidInputError` naming the file (and the line of a text file).
"""

from __future__ import annotations

import itertools
import struct
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ._csv import where

#: Camera models kalmansfm reads and writes (no lens distortion), with their parameter counts.
SUPPORTED_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4}
#: COLMAP's camera model ids (camera_models.h), to name the model of a binary file.
MODEL_NAMES = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV",
               "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE",
               "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE", "EUCM", "EQUIRECTANGULAR")
#: The largest uint32 and uint64: COLMAP's "no camera / image / point" ids; valid ids lie below.
_NO_ID32 = 2**32 - 1
_NO_ID64 = 2**64 - 1

_POINT2D = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<u8")])
_POINT3D = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("length", "<u8")])
_TRACK = np.dtype([("image", "<u4"), ("index", "<u4")])


def unsupported_model(model: str) -> str:
    """The one message for a camera model kalmansfm does not read."""
    if model not in MODEL_NAMES:
        return f"unknown camera model {model!r} (COLMAP's models: {', '.join(MODEL_NAMES)})"
    return (f"camera model {model} has lens distortion, which kalmansfm does not model yet: only PINHOLE and "
            f"SIMPLE_PINHOLE cameras are read until lens distortion is supported (undistort the images first, "
            f"e.g. colmap image_undistorter)")


# --- text -------------------------------------------------------------------------------------


def _data_lines(text: str) -> list[tuple[int, str]]:
    """(1-based line, text) of the lines that are neither blank nor comments."""
    return [(n, line) for n, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]


def _numbers(file: Path, line: int, tokens: list[str], what: str, kind: type = float) -> np.ndarray:
    try:
        values = np.array(tokens, dtype=np.float64 if kind is float else np.int64)
    except (ValueError, OverflowError):
        raise InvalidInputError(f"{where(file, line)}: {what} must be {'numbers' if kind is float else 'integers'}; "
                                f"got {' '.join(tokens)!r}") from None
    if kind is float and not np.isfinite(values).all():
        raise InvalidInputError(f"{where(file, line)}: {what} must be finite; got {' '.join(tokens)!r}")
    return values


def _id(file: Path, line: int, token: str, what: str, limit: int) -> int:
    try:
        value = int(token)
    except ValueError:
        raise InvalidInputError(f"{where(file, line)}: {what} must be an integer; got {token!r}") from None
    if not 0 <= value < limit:
        raise InvalidInputError(f"{where(file, line)}: {what} must be in 0 … {limit - 1}; got {value}")
    return value


def parse_cameras_text(text: str, file: Path) -> dict:
    """Columns of a ``cameras.txt``."""
    ids, models, sizes, params = [], [], [], []
    for n, line in _data_lines(text):
        tokens = line.split()
        if len(tokens) < 4:
            raise InvalidInputError(f"{where(file, n)}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]; "
                                    f"got {line.strip()!r}")
        model = tokens[1]
        if model not in SUPPORTED_MODELS:
            raise InvalidInputError(f"{where(file, n)}: {unsupported_model(model)}")
        if len(tokens) != 4 + SUPPORTED_MODELS[model]:
            raise InvalidInputError(f"{where(file, n)}: a {model} camera has {SUPPORTED_MODELS[model]} parameters; "
                                    f"got {len(tokens) - 4}")
        ids.append(_id(file, n, tokens[0], "CAMERA_ID", _NO_ID32))
        size = [_id(file, n, t, "WIDTH and HEIGHT", 2**63) for t in tokens[2:4]]
        models.append(model)
        sizes.append(size)
        params.append(_pinhole(_numbers(file, n, tokens[4:], "the parameters")))
    return _cameras(ids, models, sizes, params)


def _pinhole(values: np.ndarray) -> np.ndarray:
    """fx, fy, cx, cy from PINHOLE's four or SIMPLE_PINHOLE's three parameters (f, cx, cy)."""
    return values if len(values) == 4 else np.array([values[0], values[0], values[1], values[2]])


def _cameras(ids: list, models: list, sizes: list, params: list) -> dict:
    return {"ids": np.array(ids, dtype=np.int64), "models": tuple(models),
            "sizes": np.array(sizes, dtype=np.int64).reshape(-1, 2), "params": np.array(params).reshape(-1, 4)}


def parse_images_text(text: str, file: Path) -> dict:
    """Columns of an ``images.txt``: after each image line, the next line (even a blank one) holds its points."""
    lines = text.splitlines()
    ids, cameras, names, poses, counts, blocks = [], [], [], [], [], []
    k = 0
    while k < len(lines):
        line = lines[k]
        k += 1
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        tokens = line.split(maxsplit=9)
        if len(tokens) < 10:
            raise InvalidInputError(f"{where(file, k)}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME; "
                                    f"got {line.strip()!r}")
        ids.append(_id(file, k, tokens[0], "IMAGE_ID", _NO_ID32))
        poses.append(_numbers(file, k, tokens[1:8], "QW QX QY QZ TX TY TZ"))
        cameras.append(_id(file, k, tokens[8], "CAMERA_ID", _NO_ID32))
        names.append(tokens[9].strip())
        points = lines[k].split() if k < len(lines) else []  # a last image may lack its (empty) points line
        k += 1
        if len(points) % 3:
            raise InvalidInputError(f"{where(file, k)}: the points of image {ids[-1]} must be X Y POINT3D_ID triples; "
                                    f"got {len(points)} numbers")
        values = (_numbers(file, k, points, "X Y POINT3D_ID") if points else np.zeros(0)).reshape(-1, 3)
        xy, point_ids = values[:, :2], values[:, 2]
        whole = (point_ids == np.round(point_ids)) & (point_ids >= -1) & (point_ids < 2**53)
        if not whole.all():
            raise InvalidInputError(f"{where(file, k)}: the points of image {ids[-1]} need a POINT3D_ID in 0 … 2⁵³ "
                                    f"(-1 for none); got {point_ids[np.argmin(whole)]:.17g}")
        counts.append(len(xy))
        blocks.append((xy, point_ids.astype(np.int64)))
    return _images(ids, cameras, names, poses, counts, blocks)


def _images(ids: list, cameras: list, names: list, poses: list, counts: list, blocks: list) -> dict:
    pose = np.array(poses, dtype=np.float64).reshape(-1, 7)
    return {"ids": np.array(ids, dtype=np.int64), "camera_ids": np.array(cameras, dtype=np.int64),
            "names": tuple(names), "quaternions": pose[:, :4], "translations": pose[:, 4:],
            "point_starts": np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64),
            "points2d": np.concatenate([b[0] for b in blocks]) if blocks else np.zeros((0, 2)),
            "point3d_ids": np.concatenate([b[1] for b in blocks]).astype(np.int64) if blocks else np.zeros(0, np.int64)}


def parse_points_text(text: str, file: Path) -> dict:
    """Columns of a ``points3D.txt``: each line split once, every token converted in one go, then sliced."""
    data = _data_lines(text)
    tokens = [line.split() for _, line in data]
    lengths = np.fromiter(map(len, tokens), dtype=np.int64, count=len(tokens))
    bad = (lengths < 8) | ((lengths - 8) % 2 == 1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidInputError(f"{where(file, data[i][0])}: expected POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID, "
                                f"POINT2D_IDX) pairs; got {len(tokens[i])} fields")
    try:
        values = np.array(list(itertools.chain.from_iterable(tokens)), dtype=np.float64)
    except ValueError:
        _first_bad_point_line(file, data, tokens)
        raise  # pragma: no cover - the scan above always finds the line
    first = np.cumsum(lengths) - lengths  # where each line's tokens start
    heads = values[first[:, None] + np.arange(8)].reshape(-1, 8)
    in_track = np.ones(len(values), dtype=bool)
    in_track[(first[:, None] + np.arange(8)).ravel()] = False
    track = values[in_track].reshape(-1, 2)
    ids, xyz, rgb, errors = heads[:, 0], heads[:, 1:4], heads[:, 4:7], heads[:, 7]
    whole = (ids == np.round(ids)) & (ids >= 0) & (ids < 2**53)
    for test, what in ((whole, "POINT3D_ID must be an integer in 0 … 2⁵³"),
                       (np.isfinite(xyz).all(axis=1) & ~np.isnan(errors), "X Y Z must be finite and ERROR a number"),
                       (((rgb >= 0) & (rgb <= 255) & (rgb == np.round(rgb))).all(axis=1), "R G B must be integers in "
                                                                                          "0 … 255")):
        if not test.all():
            i = int(np.argmin(test))
            raise InvalidInputError(f"{where(file, data[i][0])}: {what}; got {' '.join(tokens[i][:8])!r}")
    starts = np.concatenate([[0], np.cumsum((lengths - 8) // 2)]).astype(np.int64)
    outside = ~((track >= 0) & (track < _NO_ID32) & (track == np.round(track))).all(axis=1)
    if outside.any():
        i = int(np.searchsorted(starts, np.argmax(outside), side="right") - 1)
        raise InvalidInputError(f"{where(file, data[i][0])}: IMAGE_ID and POINT2D_IDX must be integers in 0 … "
                                f"{_NO_ID32 - 1}")
    return {"ids": ids.astype(np.int64), "xyz": xyz.copy(), "colours": rgb.astype(np.uint8), "errors": errors.copy(),
            "track_starts": starts, "track_image_ids": track[:, 0].astype(np.int64),
            "track_point2d": track[:, 1].astype(np.int64)}


def _first_bad_point_line(file: Path, data: list[tuple[int, str]], tokens: list[list[str]]) -> None:
    for (n, _), t in zip(data, tokens):
        bad = next((v for v in t if not _is_number(v)), None)
        if bad is not None:
            raise InvalidInputError(f"{where(file, n)}: every field must be a number; got {bad!r}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def cameras_text(cameras: dict) -> str:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras['ids'])}"]
    for cid, model, (w, h), p in zip(cameras["ids"].tolist(), cameras["models"], cameras["sizes"].tolist(),
                                     cameras["params"].tolist()):
        values = p if model == "PINHOLE" else [p[0], p[2], p[3]]
        lines.append(f"{cid} {model} {w} {h} " + " ".join(map(repr, values)))
    return "\n".join(lines) + "\n"


def images_text(images: dict) -> str:
    n = len(images["ids"])
    total = int(images["point_starts"][-1])
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {n}, mean observations per image: {total / n if n else 0:g}"]
    starts = images["point_starts"].tolist()
    # every number turned into text once, then joined per image
    xy = images["points2d"]
    triples = [f"{x} {y} {p}" for x, y, p in zip(map(repr, xy[:, 0].tolist()), map(repr, xy[:, 1].tolist()),
                                                   images["point3d_ids"].tolist())]
    poses = np.concatenate([images["quaternions"], images["translations"]], axis=1).tolist()
    for i, (iid, cid, name) in enumerate(zip(images["ids"].tolist(), images["camera_ids"].tolist(), images["names"])):
        lines.append(f"{iid} {' '.join(map(repr, poses[i]))} {cid} {name}")
        lines.append(" ".join(triples[starts[i]:starts[i + 1]]))
    return "\n".join(lines) + "\n"


def points_text(points: dict) -> str:
    n = len(points["ids"])
    starts = points["track_starts"].tolist()
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {n}, mean track length: {starts[-1] / n if n else 0:g}"]
    pairs = [f"{a} {b}" for a, b in zip(points["track_image_ids"].tolist(), points["track_point2d"].tolist())]
    xyz = points["xyz"].tolist()
    rgb = points["colours"].tolist()
    for k, (pid, err) in enumerate(zip(points["ids"].tolist(), map(repr, points["errors"].tolist()))):
        x, y, z = map(repr, xyz[k])
        r, g, b = rgb[k]
        lines.append(f"{pid} {x} {y} {z} {r} {g} {b} {err} {' '.join(pairs[starts[k]:starts[k + 1]])}".rstrip())
    return "\n".join(lines) + "\n"


# --- binary -----------------------------------------------------------------------------------


class _Reader:
    """Sequential little-endian reads from a file's bytes; running past the end is a truncated file."""

    def __init__(self, data: bytes, file: Path) -> None:
        self.data, self.file, self.pos = data, file, 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            self.truncated(what)
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        end = self.pos + count * dtype.itemsize
        if count < 0 or end > len(self.data):
            self.truncated(what)
        out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos = end
        return out

    def count(self, what: str, smallest_record: int) -> int:
        (n,) = self.take("<Q", f"the number of {what}")
        if n * smallest_record > len(self.data) - self.pos:
            raise InvalidInputError(f"{where(self.file)}: truncated or corrupt COLMAP binary file: it says {n} {what}, "
                                    f"more than its {len(self.data)} bytes can hold")
        return n

    def truncated(self, what: str) -> None:
        raise InvalidInputError(f"{where(self.file)}: truncated or corrupt COLMAP binary file: {what} runs past its "
                                f"end ({len(self.data)} bytes)")

    def end(self) -> None:
        if self.pos != len(self.data):
            raise InvalidInputError(f"{where(self.file)}: corrupt COLMAP binary file: {len(self.data) - self.pos} "
                                    f"bytes after the last record")


def parse_cameras_binary(data: bytes, file: Path) -> dict:
    """Columns of a ``cameras.bin``."""
    read = _Reader(data, file)
    ids, models, sizes, params = [], [], [], []
    for k in range(read.count("cameras", 24)):
        cid, model_id, width, height = read.take("<IiQQ", f"camera {k + 1}")
        model = MODEL_NAMES[model_id] if 0 <= model_id < len(MODEL_NAMES) else f"id {model_id}"
        if model not in SUPPORTED_MODELS:
            raise InvalidInputError(f"{where(file)}: camera {cid}: {unsupported_model(model)}")
        values = np.array(read.take(f"<{SUPPORTED_MODELS[model]}d", f"camera {cid}'s parameters"))
        if not np.isfinite(values).all() or width >= 2**63 or height >= 2**63:
            raise InvalidInputError(f"{where(file)}: camera {cid}: corrupt size {width}x{height} or parameters "
                                    f"{values.tolist()}")
        ids.append(cid)
        models.append(model)
        sizes.append([width, height])
        params.append(_pinhole(values))
    read.end()
    return _cameras(ids, models, sizes, params)


def parse_images_binary(data: bytes, file: Path) -> dict:
    """Columns of an ``images.bin`` (each image's points read as one array)."""
    read = _Reader(data, file)
    ids, cameras, names, poses, counts, blocks = [], [], [], [], [], []
    for k in range(read.count("images", 73)):
        iid, *pose, cid = read.take("<I7dI", f"image {k + 1}")
        end = data.find(b"\0", read.pos)
        if end < 0:
            read.truncated(f"the name of image {iid}")
        try:
            names.append(data[read.pos:end].decode("utf-8"))
        except UnicodeDecodeError:
            raise InvalidInputError(f"{where(file)}: image {iid}: its name is not UTF-8 text") from None
        read.pos = end + 1
        (n,) = read.take("<Q", f"the point count of image {iid}")
        points = read.array(_POINT2D, n, f"the points of image {iid}")
        point_ids = points["id"].astype(np.int64)  # 2⁶⁴ - 1, no point, wraps to -1
        if (point_ids < -1).any():
            raise InvalidInputError(f"{where(file)}: image {iid}: corrupt POINT3D_ID {points['id'].max()}")
        ids.append(iid)
        cameras.append(cid)
        poses.append(pose)
        counts.append(n)
        blocks.append((np.stack([points["x"], points["y"]], axis=1), point_ids))
    read.end()
    if poses and not np.isfinite(np.array(poses)).all():
        raise InvalidInputError(f"{where(file)}: image {ids[int(np.argmin(np.isfinite(poses).all(axis=1)))]}: "
                                f"its pose is not finite")
    if blocks and not all(np.isfinite(b[0]).all() for b in blocks):
        raise InvalidInputError(f"{where(file)}: an image's 2-D points are not finite")
    return _images(ids, cameras, names, poses, counts, blocks)


def parse_points_binary(data: bytes, file: Path) -> dict:
    """Columns of a ``points3D.bin``: one pass finds where each point starts, then every field is gathered at once."""
    read = _Reader(data, file)
    n = read.count("points", _POINT3D.itemsize)
    offsets = np.empty(n, dtype=np.int64)
    lengths = np.empty(n, dtype=np.int64)
    pos, size, length_at = read.pos, len(data), _POINT3D.fields["length"][1]
    for k in range(n):  # a point's length field says where the next one starts: this chain is sequential
        if pos + _POINT3D.itemsize > size:
            read.truncated(f"point {k + 1} of {n}")
        (length,) = struct.unpack_from("<Q", data, pos + length_at)
        offsets[k], lengths[k] = pos, min(length, size)
        pos += _POINT3D.itemsize + 8 * lengths[k]
    if pos > size:
        read.truncated(f"the track of point {n}")
    if pos != size:
        raise InvalidInputError(f"{where(file)}: corrupt COLMAP binary file: {size - pos} bytes after the last point")
    raw = np.frombuffer(data, dtype=np.uint8)
    heads = raw[offsets[:, None] + np.arange(_POINT3D.itemsize)].copy().view(_POINT3D).ravel()
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    element = np.arange(starts[-1]) - np.repeat(starts[:-1], lengths)  # index within its track
    first_byte = np.repeat(offsets + _POINT3D.itemsize, lengths) + 8 * element
    track = raw[first_byte[:, None] + np.arange(8)].copy().view(_TRACK).ravel()
    if (heads["id"] >= 2**63).any() or not np.isfinite(heads["xyz"]).all() or np.isnan(heads["error"]).any():
        k = int(np.argmax((heads["id"] >= 2**63) | ~np.isfinite(heads["xyz"]).all(axis=1) | np.isnan(heads["error"])))
        raise InvalidInputError(f"{where(file)}: point {k + 1} of {n}: corrupt id, coordinates or error")
    return {"ids": heads["id"].astype(np.int64), "xyz": heads["xyz"].astype(np.float64),
            "colours": heads["rgb"].astype(np.uint8), "errors": heads["error"].astype(np.float64),
            "track_starts": starts, "track_image_ids": track["image"].astype(np.int64),
            "track_point2d": track["index"].astype(np.int64)}


def cameras_binary(cameras: dict) -> bytes:
    out = [struct.pack("<Q", len(cameras["ids"]))]
    for cid, model, (w, h), p in zip(cameras["ids"].tolist(), cameras["models"], cameras["sizes"].tolist(),
                                     cameras["params"].tolist()):
        values = p if model == "PINHOLE" else [p[0], p[2], p[3]]
        out.append(struct.pack(f"<IiQQ{len(values)}d", cid, MODEL_NAMES.index(model), w, h, *values))
    return b"".join(out)


def images_binary(images: dict) -> bytes:
    out = [struct.pack("<Q", len(images["ids"]))]
    starts = images["point_starts"]
    points = np.empty(int(starts[-1]), dtype=_POINT2D)
    points["x"], points["y"] = images["points2d"][:, 0], images["points2d"][:, 1]
    points["id"] = images["point3d_ids"].astype(np.uint64)  # -1 wraps to 2⁶⁴ - 1, COLMAP's "none"
    for i, (iid, cid, name) in enumerate(zip(images["ids"].tolist(), images["camera_ids"].tolist(), images["names"])):
        out.append(struct.pack("<I7dI", iid, *images["quaternions"][i], *images["translations"][i], cid))
        out.append(name.encode("utf-8") + b"\0")
        out.append(struct.pack("<Q", starts[i + 1] - starts[i]))
        out.append(points[starts[i]:starts[i + 1]].tobytes())
    return b"".join(out)


def points_binary(points: dict) -> bytes:
    """``points3D.bin`` built in one buffer: each point's head and track element scattered to its offset."""
    n = len(points["ids"])
    lengths = np.diff(points["track_starts"])
    sizes = _POINT3D.itemsize + 8 * lengths
    offsets = 8 + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    raw = np.empty(8 + int(sizes.sum()), dtype=np.uint8)
    raw[:8] = np.frombuffer(struct.pack("<Q", n), dtype=np.uint8)
    heads = np.empty(n, dtype=_POINT3D)
    heads["id"], heads["xyz"], heads["rgb"] = points["ids"], points["xyz"], points["colours"]
    heads["error"], heads["length"] = points["errors"], lengths
    raw[offsets[:, None] + np.arange(_POINT3D.itemsize)] = heads.view(np.uint8).reshape(n, _POINT3D.itemsize)
    track = np.empty(int(points["track_starts"][-1]), dtype=_TRACK)
    track["image"], track["index"] = points["track_image_ids"], points["track_point2d"]
    element = np.arange(len(track)) - np.repeat(points["track_starts"][:-1], lengths)
    first_byte = np.repeat(offsets + _POINT3D.itemsize, lengths) + 8 * element
    raw[first_byte[:, None] + np.arange(8)] = track.view(np.uint8).reshape(-1, 8)
    return raw.tobytes()
