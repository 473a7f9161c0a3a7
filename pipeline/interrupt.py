"""How a run stops on SIGTERM or Ctrl-C (SIGINT): exactly one outcome, whatever the timing.

A scheduler stops a job with SIGTERM (``timeout``, ``scancel``, ``sbatch --signal``,
systemd, Kubernetes), often twice (``scancel`` signals every process of the job,
and the batch script passes its own TERM on). The rule:

- a TERM before the result is committed (the products moved into OUT, the manifest
  last) stops the run: ``KeyboardInterrupt`` in the main thread, finished tasks kept,
  the lock released, exit 130;
- a TERM once the commit has begun is ignored: the run completes, exit 0;
- a second TERM while the first is being handled is ignored, so it cannot cut the
  clean-up short (a stale ``OUT/.holefill.lock`` was left by one ``scancel`` in three);
- Ctrl-C is answered the same way (where the process does not ignore SIGINT: a run
  started in the background of a shell does), so that a Ctrl-C swallowed like the TERM
  below is not lost either, and a second one cannot cut the clean-up short;
- a TERM that comes while a garbage-collection callback runs is not raised there: Python
  would only print it, and the callback would be cut short half-way (distributed's
  ``GCDiagnosis`` then fails an assertion at the next full collection, with a traceback
  above the run's one line). It is raised :data:`DEFERRED_S` later, outside the callback;
- a TERM whose ``KeyboardInterrupt`` was swallowed all the same (raised inside a
  finalizer, where Python only prints it) is raised again, every
  :data:`RERAISE_AFTER_S` seconds, until the run answers it (:func:`acknowledge`); Python's
  print of the swallowed one ("Exception ignored in ...", a traceback) is left out
  (:func:`_unraisable`): the user gets the run's one line.

The state is per process (a signal handler's is), kept in :data:`STATE`.
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

#: Seconds after which a TERM the run has not answered is raised again.
RERAISE_AFTER_S = 2.0

#: Seconds after which a TERM that came during a garbage-collection callback is sent again.
DEFERRED_S = 0.02


@dataclass
class _State:
    requested: bool = False  # a TERM arrived
    acknowledged: bool = False  # the run is stopping (its handler caught the KeyboardInterrupt)
    committed: bool = False  # the commit began: later TERMs are ignored
    signum: int = signal.SIGTERM  # the signal that asked for the stop (the watchdog sends it again)
    watchdog: threading.Thread | None = None
    deferred: threading.Event = field(default_factory=threading.Event)  # a TERM waits outside a gc callback
    epoch: int = 0  # counts installs: a watchdog of an earlier run stops

    def reset(self) -> None:
        self.requested = self.acknowledged = self.committed = False
        self.watchdog = None
        self.deferred = threading.Event()
        self.signum = signal.SIGTERM
        self.epoch += 1


STATE = _State()


def on_terminate(signum: int, frame: Any) -> None:
    """The SIGTERM and SIGINT handler: raise ``KeyboardInterrupt`` while a stop is pending and not yet answered."""
    if STATE.committed or STATE.acknowledged:
        return
    if not STATE.requested:
        STATE.requested = True
        STATE.signum = signum
        STATE.watchdog = threading.Thread(
            target=_reraise_until_answered, args=(STATE.epoch, STATE.deferred), name="holefill-term", daemon=True
        )
        STATE.watchdog.start()
    if _inside_gc_callback(frame):
        STATE.deferred.set()  # the watchdog sends it again in a moment
        return
    raise KeyboardInterrupt


def _inside_gc_callback(frame: Any) -> bool:
    """Whether the main thread is running one of ``gc.callbacks`` (or what it calls)."""
    codes = {getattr(getattr(callback, "__func__", callback), "__code__", None) for callback in gc.callbacks}
    codes.discard(None)
    while frame is not None:
        if frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


def _reraise_until_answered(epoch: int, deferred: threading.Event) -> None:
    while True:
        if deferred.wait(RERAISE_AFTER_S):
            deferred.clear()
            time.sleep(DEFERRED_S)  # the callback has returned by then, or defers again
        if STATE.acknowledged or STATE.committed or STATE.epoch != epoch:
            return
        if signal.getsignal(STATE.signum) is not on_terminate:
            return  # the handler is gone (the command ended): never kill the process
        os.kill(os.getpid(), STATE.signum)  # the handler runs again in the main thread


#: The report of unraisable exceptions that :func:`_unraisable` hands the others to.
_previous_unraisable = sys.unraisablehook


def install() -> dict[int, Any]:
    """Make SIGTERM and SIGINT stop the run (main thread only); returns the handlers it replaces, by signal.

    SIGINT is left alone where the process ignores it (started in a shell's background:
    the shell's way of keeping a terminal's Ctrl-C from it).
    """
    STATE.reset()
    if sys.unraisablehook is not _unraisable:
        global _previous_unraisable
        _previous_unraisable = sys.unraisablehook
        sys.unraisablehook = _unraisable
    previous: dict[int, Any] = {signal.SIGTERM: signal.signal(signal.SIGTERM, on_terminate)}
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, on_terminate)
    return previous


def restore(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install` replaced."""
    for signum, handler in previous.items():
        signal.signal(signum, handler)


def _unraisable(unraisable: Any) -> None:
    """Python's report of an exception it cannot raise, less a stop's (TERM or Ctrl-C): that one is raised again.

    A stop's ``KeyboardInterrupt`` raised inside a callback Python runs between bytecodes (a
    garbage-collection callback, distributed's among them) cannot leave it; Python prints it
    with a traceback and goes on, and the watchdog raises it again where the run answers it.
    Frequent while the client imports (allocations run the collector): one ``scancel`` in a
    few dozen printed a traceback above the run's one line.
    """
    if STATE.requested and unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
        return
    _previous_unraisable(unraisable)


def acknowledge() -> None:
    """The run caught the interrupt and is stopping: later TERMs must not cut its clean-up short."""
    STATE.acknowledged = True


def begin_commit() -> None:
    """Called before the products move into OUT: a pending TERM stops the run now, later ones are ignored."""
    if STATE.requested and not STATE.acknowledged:
        raise KeyboardInterrupt
    STATE.committed = True


def settled() -> bool:
    """Whether this process's run has an outcome (committed or stopping): a TERM now changes nothing."""
    return STATE.committed or STATE.acknowledged


__all__ = [
    "DEFERRED_S",
    "RERAISE_AFTER_S",
    "STATE",
    "acknowledge",
    "begin_commit",
    "install",
    "on_terminate",
    "restore",
    "settled",
]
