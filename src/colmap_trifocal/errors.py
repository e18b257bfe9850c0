"""User-facing errors.

Every problem caused by the user's input (a missing file, a database without
matches, a malformed prior, ...) is raised as :class:`CalibrationError`. The
command line prints its message as a single ``error: ...`` line and exits with
status 2; nothing else is caught there, so genuine bugs still show a traceback.
"""


class CalibrationError(RuntimeError):
    """An input problem explained in one line (no traceback for the user)."""
