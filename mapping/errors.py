"""Errors raised by the mapping core for inputs it cannot use."""


class InputError(ValueError):
    """An argument to a mapping function is invalid; the message says which and why."""
