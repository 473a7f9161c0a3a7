"""The ``holefill`` group: logging, and holefill's exceptions as one line and an exit status.

Commands parse options, turn them into configuration overrides (validated once
by :func:`pipeline.config.load_config`), call one library function and let its
exceptions reach the group, which maps them to exit codes in one place
(:data:`EXIT_CODES`). Logging is configured here and nowhere else.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
from pathlib import Path
from typing import NoReturn

import click

from .. import __version__, interrupt
from ..errors import ClusterError, ConfigError, CRSError, HolefillError, InputDataError, OutputError, TaskError
from .messages import configure_logging, note

#: Exit status per error class (the first matching class wins).
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (ConfigError, 2),
    (CRSError, 3),
    (InputDataError, 3),
    (OutputError, 4),
    (ClusterError, 1),
    (HolefillError, 1),
)

#: Exit status of a run stopped by Ctrl-C or SIGTERM (what shells and schedulers expect).
EXIT_INTERRUPTED = 130
#: Exit status of a run that wrote its outputs but skipped tiles (``--on-error skip``), listed in the manifest.
EXIT_PARTIAL = 5


class _Group(click.Group):
    """Turn holefill's exceptions into one clear line on stderr and an exit status."""

    def invoke(self, ctx: click.Context):
        previous = interrupt.install()
        try:
            return super().invoke(ctx)
        except HolefillError as e:
            code = next(code for cls, code in EXIT_CODES if isinstance(e, cls))
            note(f"holefill: error: {e}", level="error", exit_status=code, error=type(e).__name__)
            if isinstance(e, TaskError):
                note("holefill: finished tasks are kept: run again with --resume to continue", level="error")
            ctx.exit(code)
        except KeyboardInterrupt:
            interrupt.acknowledge()
            note(
                "holefill: interrupted; finished tasks are kept: run again with --resume to continue",
                level="error",
                exit_status=EXIT_INTERRUPTED,
            )
            ctx.exit(EXIT_INTERRUPTED)
        finally:
            # the holefill command exits now, its outcome settled: a TERM or Ctrl-C while Python
            # shuts down (Dask's atexit clean-up) must not turn it into 143 or a traceback
            if _is_the_command():
                interrupt.restore({signum: signal.SIG_IGN for signum in previous})
            else:
                interrupt.restore(previous)


def _is_the_command() -> bool:
    """Whether this process is the ``holefill`` command (not a program or a test calling the CLI in-process)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return Path(sys.argv[0]).name == "holefill" or getattr(spec, "name", "") in (
        "pipeline.cli.__main__",
        "pipeline.__main__",
    )


@click.group(cls=_Group)
@click.version_option(__version__, prog_name="holefill")
@click.option("-v", "--verbose", count=True, help="More log output (repeatable).")
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable); -q: errors only.")
@click.option(
    "--log-format",
    type=click.Choice(["text", "json"]),
    default="text",
    envvar="HOLEFILL_LOG_FORMAT",
    show_default=True,
    help="json: every message and log record as one JSON object per line on stderr (for scheduled runs).",
)
def main(verbose: int, quiet: int, log_format: str) -> None:
    """Complete DSMs from airborne lidar surveys: find, explain and fill the holes."""
    configure_logging(verbose, quiet, log_format)


def console_main() -> NoReturn:
    """The ``holefill`` script: the group, then an exit that skips Python's teardown of its modules.

    After a run, Python's own shutdown (freeing the modules and heaps of numba, GDAL, pandas
    and distributed) took 0.2 to 1 s on the 2-core VM, up to a tenth of a DSM-only run of 40 M
    points. Everything a normal exit does for the outputs still happens, in its order: the
    threads that must finish are joined, the exit handlers run (logging's flush, Dask's
    clean-up), stdout and stderr are flushed; then the process leaves with its status. A
    program calling :data:`main` in-process keeps Python's ordinary exit.
    """
    from ..gc_pause import own_process

    own_process()  # the script's process is holefill's: what it imports is frozen (pipeline.gc_pause)
    try:
        main()  # click's standalone mode: always raises SystemExit
        status: object = 0
    except SystemExit as e:
        status = e.code
    if status is None:
        status = 0
    elif not isinstance(status, int):  # what Python prints and returns for sys.exit("text")
        print(status, file=sys.stderr)
        status = 1
    getattr(threading, "_shutdown", lambda: None)()  # what Python's exit does first: join the non-daemon threads
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (holefill ... | head): nothing more to say
            pass
    os._exit(status)
