"""Errors raised by the SLAM side for inputs it cannot use."""

from __future__ import annotations

import math
import operator
import os
import stat
from pathlib import Path

import numpy as np

# an argument of a library call (a model's parameter, a filter's step, a scoring input) that cannot be used: the
# numerics layers' one error for it (a ValueError), which the command line says in one line
from mapping.errors import InputError


class LogFormatError(ValueError):
    """A dataset or log cannot be read or is not of the expected kind; the message says which file and why."""


def refuse_special_file(path: Path, what: str) -> None:
    """Raise LogFormatError when ``path`` exists but is no regular file: a FIFO (reading it waits for a writer),
    a device such as /dev/zero (it never ends), a folder. A missing path is left to the reader, which says what it
    needed."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "a device or socket"
        raise LogFormatError(f"{path}: is {kind}, not a regular file; give the path of the {what}")


def finite_array(name: str, value: object, shape: tuple[int | None, ...], hint: str = "") -> np.ndarray:
    """``value`` as a float64 array of ``shape`` (None: any length) whose every element is finite; InputError
    naming ``name`` (and the first bad row, with ``hint`` appended) otherwise. O(N), vectorised."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be real numbers of shape {_shape_text(shape)}, got {value!r:.80}") from None
    if array.ndim != len(shape) or any(want is not None and got != want for got, want in zip(array.shape, shape)):
        raise InputError(f"{name} must have shape {_shape_text(shape)}, got {array.shape}{hint}")
    bad = ~np.isfinite(array)
    if bad.any():
        where = np.argwhere(bad)[0]
        at = f" at index {tuple(int(i) for i in where)}" if array.ndim else ""
        raise InputError(f"{name} must be finite, got {array[tuple(where)]}{at}{hint}")
    return array


def check_within(name: str, value: object, limits: tuple[float, float], unit: str = "") -> None:
    """InputError unless every element of ``value`` is finite and within ``limits`` (low, high), both included, in
    ``unit`` (an infinite limit: no bound that side); the message gives the first value outside. O(N), vectorised."""
    array = np.asarray(value, dtype=np.float64)
    low, high = limits
    bad = ~(np.isfinite(array) & (array >= low) & (array <= high))
    if bad.any():
        first = array.ravel()[int(np.flatnonzero(bad.ravel())[0])]
        units = f" {unit}" if unit else ""
        if math.isinf(low) and math.isinf(high):
            wanted = "finite"
        elif math.isinf(high):
            wanted = f"finite and >= {low:g}{units}"
        elif math.isinf(low):
            wanted = f"finite and <= {high:g}{units}"
        else:
            wanted = f"finite and within [{low:g}, {high:g}]{units}"
        raise InputError(f"{name} must be {wanted}, got {first:g}")


def check_count(name: str, value: object, least: int = 1) -> None:
    """InputError unless ``value`` is an integer (Python or numpy; not a float) >= ``least``."""
    try:
        ok = operator.index(value) >= least  # type: ignore[arg-type]
    except TypeError:
        ok = False
    if not ok:
        raise InputError(f"{name} must be a whole number >= {least}, got {value!r}")


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if n is None else str(n) for n in shape) + ("," if len(shape) == 1 else "") + ")"
