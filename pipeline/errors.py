"""Exception and warning hierarchy.

Every error a user can cause carries one message that names the file (or the
configuration key), the field and what is wrong. The CLI maps these classes to
exit codes in one place (``pipeline.cli.EXIT_CODES``).
"""

from __future__ import annotations


class HolefillError(Exception):
    """Root of all errors raised by holefill."""


class ConfigError(HolefillError, ValueError):
    """A configuration file or override is invalid (unknown key, wrong value)."""


class InputDataError(HolefillError, OSError):
    """An input file is missing, unreadable, corrupt or inconsistent."""

    def __init__(self, path: object, message: str) -> None:
        self.path = str(path)
        self.reason = message
        super().__init__(f"{self.path}: {message}")

    def __reduce__(self):  # keep the two-argument form across process boundaries
        return (type(self), (self.path, self.reason))


class CRSError(InputDataError):
    """A tile's coordinate reference system is missing, unreadable or inconsistent."""


class OutputError(HolefillError, OSError):
    """The output folder cannot be created or written."""


class HolefillWarning(UserWarning):
    """Root of holefill's warnings."""


class PointsOutsideHeaderWarning(HolefillWarning):
    """Some points lie outside the bounds their tile's header declares."""
