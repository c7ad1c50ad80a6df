"""User-facing errors: the CLI prints them as one line and exits non-zero (no traceback)."""


class SlamError(Exception):
    """A known problem with the user's input or setup; the message says what to do."""


class InputError(SlamError):
    """A file or sequence cannot be read as given (names the file, and the line when known)."""
