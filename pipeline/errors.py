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


class ClusterError(HolefillError):
    """The Dask scheduler cannot be reached or the cluster cannot start."""


class OutputError(HolefillError, OSError):
    """The output folder cannot be created or written."""


class DiskFullError(OutputError):
    """The output folder's file system filled up during the run; finished tasks are kept for ``--resume``."""


class HolefillWarning(UserWarning):
    """Root of holefill's warnings."""


class PointsOutsideHeaderWarning(HolefillWarning):
    """Some points lie outside the bounds their tile's header declares."""


class TaskError(HolefillError):
    """A task failed on a worker for a reason holefill does not foresee; the message names the task."""

    def __init__(self, task: str, cause: BaseException) -> None:
        self.task = task
        self.cause = f"{type(cause).__name__}: {cause}".strip().splitlines()[0] if str(cause) else type(cause).__name__
        super().__init__(f"{task}: {self.cause}")

    def __reduce__(self):
        return (_rebuild_task_error, (self.task, self.cause))


def _rebuild_task_error(task: str, cause: str) -> TaskError:
    error = TaskError.__new__(TaskError)
    error.task, error.cause = task, cause
    HolefillError.__init__(error, f"{task}: {cause}")
    return error
