"""Python's cyclic garbage collector paused while a process imports holefill, and what the imports made frozen.

Importing the stages creates some hundreds of thousands of objects, and the collector,
triggered by allocations, walks them again and again while they are made: on the 2-core VM
(``perf record`` of a DSM-only run of 42 M points) 0.20 s of the client's CPU and 0.16 s of
the fork server's, both in the start, where the two import side by side and the workers wait
for the server. Paused over the imports and then frozen (:func:`gc.freeze`: the objects move to
a generation no collection visits), later collections walk only what the run itself makes.
In the fork server the freeze also keeps the workers it forks from writing the collector's
marks into the pages they share with it (each write a page copied).

Only a process that is holefill's own freezes (:func:`own_process`: the ``holefill`` script and
the fork server): a frozen object is never collected, so a program that calls holefill in its
own process, again and again, keeps its collector as it was, paused over the imports only.
Import-time objects live as long as the process in any case; a cycle of garbage made while
importing stays (a few kilobytes), the price the documentation of :func:`gc.freeze` names.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

_own_process = False


def own_process() -> None:
    """Mark this process as holefill's own (the ``holefill`` script, the fork server): its imports may be frozen."""
    global _own_process
    _own_process = True


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """Pause the collector over a block of imports; on leaving, freeze what exists (holefill's own
    process only) and collect as before."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if _own_process:
            gc.freeze()
        if was_enabled:
            gc.enable()


def pause() -> None:
    """Pause the collector (the fork server, before its preloads: :mod:`pipeline.fork_server_start`)."""
    gc.disable()


def freeze_imports() -> None:
    """Freeze every object made so far, then let the collector run again (the fork server, after its preloads)."""
    gc.freeze()
    gc.enable()
