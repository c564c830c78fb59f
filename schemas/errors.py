"""The one error type for every wire message and file format that fails validation."""


class FormatError(ValueError):
    """A file or message does not match its contract.

    The message is one sentence that names the file or message, the field, what was found and what was
    expected, so a user can fix the input without reading code.
    """
