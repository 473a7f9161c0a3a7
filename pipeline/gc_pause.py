"""Python's cyclic garbage collector paused while a process imports holefill, and what the imports made frozen.

Importing the stages creates some hundreds of thousands of objects, and the collector,
triggered by allocations, walks them again and again while they are made: on the 2-core VM
(``perf record`` of a DSM-only run of 42 M points) 0.20 s of the client's CPU and 0.16 s of
the fork server's, both in the start, where the two import side by side and the workers wait
for the server. Paused over the imports and then frozen (:func:`gc.freeze`: the objects move to
a generation no collection visits), later collections walk only what the run itself makes.
In the fork server the freeze also keeps the workers it forks from writing the collector's
marks into the pages they share with it (each write a page copied).

Import-time objects live as long as the process in any case; a cycle of garbage made while
importing stays (a few kilobytes), the price the documentation of :func:`gc.freeze` names.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """Pause the collector over a block of imports; on leaving, freeze what exists and collect as before."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        freeze_imports(enable=was_enabled)


def pause() -> None:
    """Pause the collector (the fork server, before its preloads: :mod:`pipeline.fork_server_start`)."""
    gc.disable()


def freeze_imports(*, enable: bool = True) -> None:
    """Freeze every object made so far, then let the collector run again (where ``enable``)."""
    gc.freeze()
    if enable:
        gc.enable()
