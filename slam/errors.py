"""Errors raised by the SLAM side for inputs it cannot use."""


class LogFormatError(ValueError):
    """A dataset or log cannot be read or is not of the expected kind; the message says which file and why."""
