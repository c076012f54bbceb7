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


def one_line(text: object, limit: int = 400) -> str:
    """``text`` on one line (whitespace runs collapsed), cut to ``limit`` characters.

    Libraries' messages (gtsam's span a paragraph) must not break a one-line
    error or a CSV row.
    """
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."
