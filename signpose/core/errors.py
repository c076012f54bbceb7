"""The package's exception base. Imports nothing, so every layer may use it."""


class SignposeError(Exception):
    """An error the user can fix (bad input file, unwritable output).

    The CLI prints ``str(error)`` as one line and exits with code 2. The
    message names the file and says what to fix.
    """


class InputError(SignposeError):
    """An input file is missing, unreadable or malformed."""


class OutputError(SignposeError):
    """An output location cannot be written."""
