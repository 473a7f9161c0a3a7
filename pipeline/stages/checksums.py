"""The checksums, one task per input file: its size, time and SHA-256 for the manifest.

Submitted with stage 1, at a lower priority: a file is hashed after its decoding, which
the file is then cached for. A split COPC file is hashed once (by its top task's entry).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..io.checksums import input_record
from .bin_tiles import READ_TASKS, result_folder
from .stage import RunState, Stage


@dataclass(frozen=True)
class ChecksumTask:
    """Hash one input file."""

    path: str
    result_folder: str  # the file's stage-1 result folder: names the kept checksum


def checksum_tasks(state: RunState) -> list[ChecksumTask]:
    """One task per input file, in the order of the read tasks (once per file, also when a COPC file is split)."""
    return [ChecksumTask(task.path, result_folder(task)) for task in state[READ_TASKS] if task.role in ("whole", "top")]


def checksum_file(task: ChecksumTask) -> dict[str, object]:
    """The worker: the file's path, size, modification time and SHA-256 (:func:`pipeline.io.checksums.input_record`)."""
    return input_record(task.path)


def by_path(state: RunState, results: list[dict[str, Any]]) -> Mapping[str, dict[str, Any]]:
    """Gather: each file's record by its path."""
    return {str(record["path"]): record for record in results}


CHECKSUMS: Stage[ChecksumTask, Mapping[str, dict[str, Any]]] = Stage(
    name="checksums",
    recipes=checksum_tasks,
    worker=checksum_file,
    key=lambda task: f"sha256-{task.result_folder}",
    label=lambda task: f"tile {task.path} (checksum)",
    gather=by_path,
    bar="checksums",
    priority=lambda task: -1,  # after the decoding, which the file is then cached for
    streams=True,
    background=True,
)
