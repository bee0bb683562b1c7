"""Frozen records to JSON and back: the one conversion every file that holds a record uses.

:func:`to_json` turns a frozen dataclass (nested records, tuples, NumPy arrays and
scalars, enums, the tracker's settings with its motion model) into plain JSON values;
:func:`from_json` rebuilds the record from them, checking every field against the
record's type hints and naming the file and the field when something does not fit.
Dicts appear only here, at the file boundary.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

import numpy as np

from ..errors import InvalidInputError
from ..estimation.models import LinearGaussianModel

__all__ = ["to_json", "from_json"]

T = TypeVar("T")

_MODEL_MATRICES = ("F", "H", "Q", "R", "P0")


def to_json(value: Any) -> Any:
    """Plain JSON values (dict, list, str, int, float, bool, None) for ``value``.

    Non-finite floats become None (JSON has no NaN).

    Examples
    --------
    >>> from kalmansfm.tracking.settings import TrackerSettings
    >>> data = to_json(TrackerSettings(window=9))
    >>> data["window"], data["model"]["R"]
    (9, [[4.0, 0.0], [0.0, 4.0]])
    """
    if isinstance(value, LinearGaussianModel):
        return {name: to_json(getattr(value, name)) for name in _MODEL_MATRICES}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.name.lower()
    if isinstance(value, np.ndarray):
        return to_json(value.tolist())
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def _fail(where: str, message: str) -> InvalidInputError:
    return InvalidInputError(f"{where}: {message}")


def _model_from_json(data: Any, where: str) -> LinearGaussianModel:
    if not isinstance(data, dict) or set(data) != set(_MODEL_MATRICES):
        raise _fail(where, f"expected an object with the matrices {', '.join(_MODEL_MATRICES)}")
    try:
        matrices = {name: np.asarray(data[name], dtype=np.float64) for name in _MODEL_MATRICES}
    except (TypeError, ValueError):
        raise _fail(where, "the model matrices must be numeric") from None
    for name, matrix in matrices.items():
        if matrix.ndim != 2 or not np.isfinite(matrix).all():
            raise _fail(f"{where}.{name}", f"must be a finite matrix; got shape {matrix.shape}")
    return LinearGaussianModel(**matrices)


def _convert(hint: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, where)
            except InvalidInputError as exc:
                errors.append(str(exc))
        raise InvalidInputError(errors[0] if len(errors) == 1 else f"{where}: {value!r} fits none of its types")
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, list):
            raise _fail(where, f"expected a list; got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{k}]") for k, v in enumerate(value))
        if len(args) != len(value):
            raise _fail(where, f"expected {len(args)} values; got {len(value)}")
        return tuple(_convert(a, v, f"{where}[{k}]") for k, (a, v) in enumerate(zip(args, value)))
    if hint is LinearGaussianModel:
        return _model_from_json(value, where)
    if dataclasses.is_dataclass(hint):
        return from_json(hint, value, where)
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        try:
            return hint[str(value).upper()]
        except KeyError:
            raise _fail(where, f"unknown value {value!r}; expected one of {[m.name.lower() for m in hint]}") from None
    if hint is bool:
        if not isinstance(value, bool):
            raise _fail(where, f"expected true or false; got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(where, f"expected an integer; got {value!r}")
        return value
    if hint is float:
        if value is None:  # a non-finite number is written as null
            return math.nan
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(where, f"expected a number; got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise _fail(where, f"expected a string; got {value!r}")
        return value
    if hint is Any:
        return value
    raise TypeError(f"no JSON conversion for the type {hint!r} of {where}")  # a record the schema does not support


def from_json(cls: type[T], data: Any, where: str) -> T:
    """The record ``cls`` rebuilt from JSON ``data``; ``where`` (file and field) heads every error.

    Fields with a default may be absent; unknown fields are refused.

    Raises
    ------
    InvalidInputError
        A missing or unknown field, or a value of the wrong type, named by its path.

    Examples
    --------
    >>> from kalmansfm.tracking.settings import TrackerSettings
    >>> from_json(TrackerSettings, {"window": 9, "score": "ncc"}, "summary.json: settings").score
    'ncc'
    >>> from_json(TrackerSettings, {"windw": 9}, "summary.json: settings")
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: summary.json: settings: unknown field(s) windw
    """
    if not isinstance(data, dict):
        raise _fail(where, f"expected an object; got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise _fail(where, f"unknown field(s) {', '.join(unknown)}")
    values = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise _fail(where, f"missing field {name!r}")
            continue
        values[name] = _convert(hints[name], data[name], f"{where}.{name}")
    try:
        return cls(**values)
    except InvalidInputError as exc:
        raise _fail(where, str(exc)) from None
