"""Errors raised by the SLAM side for inputs it cannot use."""

from __future__ import annotations

import os
import stat
from pathlib import Path


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
