"""Validation of arguments at the public boundary (shapes, finiteness, definiteness, counts), shared by every layer."""

from __future__ import annotations

import os
from enum import IntEnum

import numpy as np

from .errors import InvalidInputError


def as_float_array(name: str, value: object, *, dtype: type = np.float64) -> np.ndarray:
    """Convert ``value`` to a float array or raise an error that names the argument."""
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be numeric; could not convert it ({exc})") from None
    return array


def check_shape(name: str, array: np.ndarray, expected: tuple[int | None, ...], meaning: str) -> None:
    """Raise unless ``array.shape`` matches ``expected`` (``None`` matches any length)."""
    ok = array.ndim == len(expected) and all(e is None or e == s for e, s in zip(expected, array.shape))
    if not ok:
        shown = "(" + ", ".join("?" if e is None else str(e) for e in expected) + ")"
        raise InvalidInputError(f"{name} must have shape {shown} {meaning}; got {array.shape}")


def check_finite(name: str, array: np.ndarray) -> None:
    """Raise if ``array`` holds NaN or infinity."""
    if not np.all(np.isfinite(array)):
        bad = np.argwhere(~np.isfinite(array))[0]
        raise InvalidInputError(f"{name} must be finite; entry {tuple(int(i) for i in bad)} is {array[tuple(bad)]}")


def check_covariance(name: str, cov: np.ndarray, *, allow_singular: bool = False) -> None:
    """Raise unless every matrix in ``cov`` (``(..., n, n)``) is symmetric positive (semi-)definite."""
    check_finite(name, cov)
    scale = np.maximum(np.abs(cov).max(axis=(-2, -1), keepdims=True), np.finfo(cov.dtype).tiny)
    asym = np.abs(cov - np.swapaxes(cov, -1, -2)) / scale
    if np.any(asym > 1e-8):
        raise InvalidInputError(f"{name} must be symmetric; max relative asymmetry {asym.max():.3g}")
    eig_min = np.linalg.eigvalsh(cov)[..., 0]
    limit = -1e-12 * scale[..., 0, 0] if allow_singular else 0.0
    bad = eig_min < limit if allow_singular else eig_min <= 0.0
    if np.any(bad):
        where = np.argwhere(np.atleast_1d(bad))[0]
        which = f" (matrix {tuple(int(i) for i in where)})" if np.ndim(bad) else ""
        kind = "positive semi-definite" if allow_singular else "positive definite"
        raise InvalidInputError(
            f"{name} must be {kind}{which}; smallest eigenvalue {np.atleast_1d(eig_min)[tuple(where)]:.6g}"
        )


def check_positive(name: str, value: object, unit: str = "") -> float:
    """Return ``value`` as a float or raise unless it is a finite number > 0 (bools refused).

    ``unit`` (e.g. ``"pixels"``) is shown in the message.
    """
    shown = f" ({unit})" if unit else ""
    if isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(f"{name} must be a number{shown}; got {value!r}")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number{shown}; got {value!r}") from None
    if not np.isfinite(number) or number <= 0:
        raise InvalidInputError(f"{name} must be finite and > 0{shown}; got {number}")
    return number


def check_choice(name: str, value: object, choices: tuple[str, ...]) -> None:
    """Raise unless ``value`` is one of ``choices``: ``NAME must be one of a, b, c; got 'x'``.

    Examples
    --------
    >>> check_choice("method", "batch", ("recursive", "batch"))
    >>> check_choice("method", "ekf", ("recursive", "batch"))
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: method must be one of recursive, batch; got 'ekf'
    """
    if value not in choices:
        raise InvalidInputError(f"{name} must be one of {', '.join(choices)}; got {value!r}")


def check_count(name: str, value: object, minimum: int, error: type[Exception] = InvalidInputError) -> int:
    """Return ``value`` as an int or raise ``error`` unless it is an integer >= ``minimum`` (bools refused)."""
    integral = isinstance(value, (int, np.integer)) or (isinstance(value, (float, np.floating)) and float(value).is_integer())
    if isinstance(value, bool) or not integral or value < minimum:  # type: ignore[operator]
        wanted = "a non-negative integer" if minimum == 0 else f"an integer >= {minimum}"
        raise error(f"{name} must be {wanted}; got {value!r}")
    return int(value)  # type: ignore[arg-type]


class LabelledEnum(IntEnum):
    """A status code that files store as its integer value or as its lower-case name (its *label*)."""

    @property
    def label(self) -> str:
        """The word files use for this code: the member's name in lower case."""
        return self.name.lower()

    @classmethod
    def from_label(cls, label: str) -> LabelledEnum:
        """The member named ``label`` (as :attr:`label` writes it); raises ``KeyError`` otherwise."""
        if label != label.lower():
            raise KeyError(label)
        return cls[label.upper()]


def physical_memory() -> int | None:
    """The machine's memory in bytes, where the system says (POSIX), else None."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def size_in_words(n_bytes: float) -> str:
    """A memory size in words (binary units).

    Examples
    --------
    >>> size_in_words(6.7 * 2**30), size_in_words(161e12)
    ('6.7 GB', '146 TB')
    """
    for unit, size in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20)):
        if n_bytes >= size:
            return f"{n_bytes / size:.2g} {unit}" if n_bytes < 10 * size else f"{n_bytes / size:.0f} {unit}"
    return f"{n_bytes / 2**10:.0f} KB"


def check_fits_in_memory(needed: float, what: str, advice: str) -> None:
    """Refuse, before allocating, work that needs more than this machine's memory (no check where it is unknown).

    ``what`` says what needs the memory, ``advice`` what to do instead; both go into one line.

    Examples
    --------
    >>> check_fits_in_memory(1e6, "a small array", "use less")
    >>> check_fits_in_memory(1e30, "x of 1e29 floats", "use fewer")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: x of 1e29 floats would need about ... of memory, more than this machine's ...; use fewer
    """
    available = physical_memory()
    if available is not None and needed > available:
        raise InvalidInputError(f"{what} would need about {size_in_words(needed)} of memory, more than this "
                                f"machine's {size_in_words(available)}; {advice}")
