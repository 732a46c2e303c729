"""Argument checks shared by the public functions.

Every failure is a ``ValueError`` whose message starts with the argument's name and
says what was expected, e.g. ``"V: expected shape (N, 2) with N >= 4, got (3, 2)"``.
"""

from __future__ import annotations

import contextlib
import numbers
from collections.abc import Mapping

import numpy as np


def float_array(x, name: str, shape: tuple, *, finite: bool = True) -> np.ndarray:
    """``x`` as a float64 array of ``shape``; ``None`` in ``shape`` matches any length.

    Parameters
    ----------
    x : array_like
    name : str
        The argument's name, used in the error message.
    shape : tuple of int or None
        Expected shape, e.g. ``(None, 3)``.
    finite : bool
        Refuse NaN and inf.
    """
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a numeric array of shape {_fmt(shape)}") from exc
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        raise ValueError(f"{name}: expected shape {_fmt(shape)}, got {tuple(a.shape)}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return a


def positive(x, name: str, shape: tuple = ()) -> np.ndarray:
    """``x`` as a float64 array of ``shape`` whose entries are all > 0."""
    a = float_array(x, name, shape)
    if not np.all(a > 0):
        raise ValueError(f"{name}: expected values > 0, got {a.tolist()}")
    return a


def integer(x, name: str, *, minimum=None, maximum=None, optional: bool = False):
    """``x`` as an int: a Python int, never a bool, in ``[minimum, maximum]`` (either bound
    may be left out); ``None`` too when ``optional``.

    The message says ``a positive integer`` for ``minimum=1`` alone, else ``an integer >=
    minimum`` or ``an integer in [minimum, maximum]``, after ``None or`` when ``optional``.
    """
    if x is None and optional:
        return None
    ok = isinstance(x, int) and not isinstance(x, bool)
    if not ok or (minimum is not None and x < minimum) or (maximum is not None and x > maximum):
        if maximum is not None:
            expected = f"an integer in [{minimum}, {maximum}]"
        elif minimum == 1:
            expected = "a positive integer"
        else:
            expected = "an integer" + ("" if minimum is None else f" >= {minimum}")
        raise ValueError(f"{name}: expected {'None or ' * optional}{expected}, got {x!r}")
    return x


def seconds(x, name: str, *, optional: bool = False) -> float | None:
    """``x`` as float seconds > 0 (a real number, not a bool; ``inf``: no cap); ``None``
    too when ``optional``."""
    if x is None and optional:
        return None
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not x > 0:
        raise ValueError(f"{name}: expected {'None or ' * optional}seconds > 0, got {x!r}")
    return float(x)


def choice(x, name: str, choices):
    """``x`` when it is one of ``choices`` (an iterable of str, e.g. a tuple of method
    names or a dict's keys, named in the message in the order given).

    Examples
    --------
    >>> choice("box", "input_form", ("box", "simplex"))
    'box'
    >>> choice("cube", "input_form", ("box", "simplex"))
    Traceback (most recent call last):
    ...
    ValueError: input_form: expected one of box, simplex, got 'cube'
    """
    choices = tuple(choices)
    if x not in choices:
        raise ValueError(f"{name}: expected one of {', '.join(map(str, choices))}, got {x!r}")
    return x


@contextlib.contextmanager
def named(names: Mapping[str, str], prefix: str = ""):
    """Within the block, a check's ``ValueError`` in the caller's words: ``'key: …'`` is
    raised again as ``'{prefix}{names[key]}: …'`` (a key missing from ``names`` keeps its
    name), for an object whose checks name its own fields where the caller's argument
    has another name."""
    try:
        yield
    except ValueError as exc:
        key, colon, rest = str(exc).partition(": ")
        if not colon:
            raise
        raise ValueError(f"{prefix}{names.get(key, key)}: {rest}") from exc


def intrinsics(K, name: str = "K") -> np.ndarray:
    """OpenCV pinhole intrinsics (3, 3): ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, fx, fy > 0.

    OpenCV's projection and PnP have no skew term, so a non-zero skew is refused.
    """
    K = float_array(K, name, (3, 3))
    pattern = np.array([[K[0, 0], 0, K[0, 2]], [0, K[1, 1], K[1, 2]], [0, 0, 1]])
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.array_equal(K, pattern):
        raise ValueError(
            f"{name}: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
            f"got {K.tolist()}"
        )
    return K


def rotation(R, name: str = "R") -> np.ndarray:
    """A rotation matrix (3, 3): orthonormal with determinant +1 (to 1e-6)."""
    R = float_array(R, name, (3, 3))
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{name}: expected a rotation matrix (orthonormal, det +1)")
    return R


def _fmt(shape: tuple) -> str:
    inner = ", ".join("N" if s is None else str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"
