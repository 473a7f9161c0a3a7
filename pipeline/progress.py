"""Progress bars on stderr and seconds per stage: what a run shows while it works and records after.

Apart from the engine (:mod:`pipeline.run`) so that it stays about graphs; no Dask here.
"""

from __future__ import annotations

import time
from typing import Any


class StageTimer:
    """Seconds per stage for the manifest, each measured from the end of the previous one: the
    wall time (``seconds``) and the CPU time of this process, the client (``cpu``); and, per
    Dask stage, its tasks and their compute seconds on the workers (``tasks``, set by the run)."""

    def __init__(self, started: float) -> None:
        self.seconds: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.tasks: dict[str, dict[str, float]] = {}
        self._last = started
        self._last_cpu = time.process_time()

    def lap(self, name: str) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._last  # a stage run again adds up
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu - self._last_cpu
        self._last, self._last_cpu = now, cpu


class ProgressBars:
    """rich progress bars on stderr: tasks done, points per second, time left."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._progress: Any = None
        self._points: dict[int, int] = {}
        self._started = time.perf_counter()

    def __enter__(self) -> ProgressBars:
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self._progress = Progress(
                TextColumn("{task.description:<24}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
            )
            self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)

    def add(self, description: str, *, total: int) -> int:
        """A new bar; returns its handle."""
        handle = len(self._points)
        self._points[handle] = 0
        if self._progress is not None:
            handle = self._progress.add_task(description, total=total, rate="")
            self._points[handle] = 0
        return handle

    def advance(self, handle: int, *, points: int = 0) -> None:
        self._points[handle] = self._points.get(handle, 0) + points
        if self._progress is not None:
            elapsed = max(time.perf_counter() - self._started, 1e-9)
            rate = f"{self._points[handle] / elapsed / 1e6:6.2f} M pts/s" if self._points[handle] else ""
            self._progress.update(handle, advance=1, rate=rate)
