"""The run's private folder: where stage results are kept and products are staged.

Everything a run writes goes into ``OUT/.holefill-partial-<id>/`` first::

    .holefill-partial-<id>/
        work/tiles/<tile key>/     stage 1: per-tile statistic binaries (key: file name + input fingerprint)
        work/cells/<cell id>.npz   stage 2: merged statistics of a cell and its halo
        work/holes/<cell id>.npz   detection: part labels of a cell core
        work/holes/catalog.npz     linking: the survey's hole catalog with causes
        work/fill/fill_<cell id>.npz  filling: the holes a cell owns: ids, heights, method codes, distances
        dsm/dsm_<cell id>.tif      the writer stage's rasters (also fill_mask/, fill_distance/,
                                   dsm_unfilled/)
        points/<tile stem>.laz     repaired point clouds (output.points)
        dsm.vrt, holes.gpkg, manifest.json, report.html

Names depend on what a result is made of (a cell's position on the absolute
lattice, a tile's path, size and modification time), never on the order in
which inputs were scanned, so a later stage, a resumed run or an incremental run
can find them.

**Complete or absent.** Products are moved into OUT only when the whole run has
succeeded, ``manifest.json`` last: the old manifest is removed before any product
is replaced, so ``OUT/manifest.json`` exists exactly when OUT holds one complete
result (its ``"complete": true`` says so too). A failed run's folder is deleted.

**One run at a time.** ``OUT/.holefill.lock`` (pid and host) refuses a second run
into the same folder; the holder touches it every 30 s, so a lock whose process is
gone (same host) or that has been silent for 5 minutes (any host) is taken over.

**Interrupted runs.** A run stopped by Ctrl-C or SIGTERM keeps its folder, and
every finished task has left its result under ``work/done/``; ``--resume`` picks
the folder of the same inputs and configuration (``run.json``) and reruns only
what is missing. Other partial folders are reported and removed.

**Incremental runs.** ``--incremental`` keeps ``work/`` in OUT after a run, and the
next run of the same configuration adopts from it the results of tasks whose key
it plans again (:meth:`Staging.adopt`): the keys of stage 1 and 2 name what a
result is made of (a tile's path, size and time and the lattice; a cell and the
keys of its tiles), so an unchanged tile is not decoded again and a cell none of
whose tiles changed is not merged again. Adopted files are hard links (copies
across file systems); every kept file is replaced, never rewritten in place, so
the previous result in OUT stays whole until this run commits.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import shutil
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import OutputError
from .io.intermediate import internal_name, load_object, save_object

logger = logging.getLogger(__name__)

#: Subfolders every task may write into; tasks never create parent folders.
WORK_FOLDERS = (
    "work/tiles",
    "work/cells",
    "work/holes",
    "work/fill",
    "work/done",
    "dsm",
    "fill_mask",
    "fill_distance",
    "dsm_unfilled",
    "points",
)


@dataclass(frozen=True)
class Staging:
    """The staging folder of one run inside its output folder."""

    out: Path
    root: Path
    resumed: bool = False
    reuse_from: Path | None = None  # OUT/work of the previous run, for an incremental run

    @classmethod
    def create(
        cls, out: str | os.PathLike, *, run_key: str = "", resume: bool = False, incremental: bool = False
    ) -> Staging:
        """Lock OUT, make (or, with ``resume``, find) the run's private folder and check it is writable.

        ``run_key`` identifies the inputs and configuration; only a partial folder of
        the same key is resumed. Partial folders of other, interrupted runs are removed.
        ``incremental``: results kept in ``OUT/work`` by the previous run may be
        adopted (the caller has checked that OUT holds a result of the same configuration).
        """
        out = Path(out)
        try:
            out.mkdir(parents=True, exist_ok=True)
            _lock(out)
        except OSError as e:
            raise OutputError(f"{out}: output folder cannot be created or written: {e.strerror or e}") from None
        try:
            root = _partial_to_resume(out, run_key) if resume else None
            _remove_stale_partials(out, keep=root)
            resumed = root is not None
            if root is None:
                root = out / f"{PARTIAL_PREFIX}{uuid.uuid4().hex[:10]}"
                root.mkdir()
            for sub in WORK_FOLDERS:
                (root / sub).mkdir(parents=True, exist_ok=True)
            (root / RUN_FILE).write_text(json.dumps({"run_key": run_key, "pid": os.getpid()}))
        except OSError as e:
            _unlock(out)
            raise OutputError(f"{out}: output folder cannot be created or written: {e.strerror or e}") from None
        except BaseException:  # a TERM while the folder is being set up must not leave the lock
            _unlock(out)
            raise
        previous_work = out / "work"
        reuse_from = previous_work if incremental and (previous_work / "done").is_dir() else None
        return cls(out, root, resumed, reuse_from)

    @property
    def work(self) -> Path:
        return self.root / "work"

    def tile_folder(self, path: str, fingerprint: str) -> Path:
        """Stage-1 results of one input file (named after it, shortened: :func:`internal_name`)."""
        return self.work / "tiles" / internal_name(f"{Path(path).stem}-{fingerprint}")

    def cell_statistics(self, cell_id: str) -> Path:
        return self.work / "cells" / f"cell_{cell_id}.npz"

    def cell_labels(self, cell_id: str) -> Path:
        return self.work / "holes" / f"labels_{cell_id}.npz"

    @property
    def hole_catalog(self) -> Path:
        return self.work / "holes" / "catalog.npz"

    def cell_fill(self, cell_id: str) -> Path:
        """The filled holes a cell owns (their first pixel lies in its core)."""
        return self.work / "fill" / f"fill_{cell_id}.npz"

    def task_result(self, key: str) -> Path:
        """Where a finished task keeps its (small) result, for a resumed run."""
        return self.work / "done" / f"{internal_name(key)}.npz"

    def kept(self, key: str) -> tuple[Any, str] | None:
        """The kept result of task ``key`` and where it came from (``resumed`` or ``reused``), if any.

        An interrupted run's own results come first (``--resume``); then, in an
        incremental run, the previous run's (:meth:`adopt`).
        """
        if self.resumed and (value := kept_result(self.task_result(key))) is not None:
            return value, "resumed"
        if (
            self.reuse_from is not None
            and self.adopt(key)
            and (value := kept_result(self.task_result(key))) is not None
        ):
            return value, "reused"
        return None

    def adopt(self, key: str) -> bool:
        """Link the previous run's result of task ``key`` and the files it names into this run.

        Only stage-1 (``rasterize-<tile folder>``, the file's checksum in it) and stage-2
        (``merge-<digest>-<cell id>``) results are adopted: their keys
        say everything they are made of. Returns whether the result (and its files)
        is now here.
        """
        assert self.reuse_from is not None
        kind = key.split("-", 1)[0]
        if kind == "rasterize":
            data = [Path("tiles") / key.removeprefix("rasterize-")]
        elif kind == "merge":
            data = [Path("cells") / f"cell_{key.split('-', 2)[2]}.npz"]
        else:
            return False
        sources = [self.reuse_from / "done" / f"{key}.npz", *(self.reuse_from / d for d in data)]
        if not all(s.exists() for s in sources):
            return False
        targets = [self.task_result(key), *(self.work / d for d in data)]
        try:
            for source, target in zip(sources, targets):
                _link_tree(source, target)
        except OSError:
            for target in targets:  # nothing half-adopted: the task runs and writes its own files
                shutil.rmtree(target, ignore_errors=True) if target.is_dir() else target.unlink(missing_ok=True)
            return False
        return True

    def raster_tile(self, product: str, cell_id: str) -> Path:
        """One cell's tile of a raster product (``dsm``, ``fill_mask``, ``fill_distance``, ``dsm_unfilled``)."""
        return self.root / product / f"{product}_{cell_id}.tif"

    def points_file(self, name: str) -> Path:
        """One repaired point cloud (``output.points``): ``points/<name>.laz``."""
        return self.root / "points" / f"{name}.laz"

    def dsm_tile(self, cell_id: str) -> Path:
        return self.raster_tile("dsm", cell_id)

    def product(self, name: str) -> Path:
        return self.root / name

    def commit(self, products: tuple[str, ...], *, keep_work: bool, replaces: tuple[str, ...] = ()) -> None:
        """Move every product into OUT, ``manifest.json`` last, then delete the staging folder.

        The old manifest goes first, so a commit cut short leaves no manifest: OUT is
        then visibly incomplete. ``replaces``: glob patterns of products an older run
        may have left in OUT that this run does not write again (e.g. the files of a
        sortie no longer planned); they are removed so that OUT never mixes two runs.

        The commit is journaled (``commit.json`` in the staging folder: the products, which
        of them this run wrote, ``keep_work``), so a commit cut short by SIGKILL or a lost
        node is finished by ``--resume`` (:meth:`finish_commit`). Ctrl-C and SIGTERM are held
        until it is done: a commit is renames, and once it starts the result is complete.
        """
        journal = {
            "products": list(products),
            "written": [name for name in (*products, "work") if _has_content(self.root / name)],
            "keep_work": keep_work,
            "replaces": list(replaces),
        }
        with deferred_interrupts() as interrupted:
            tmp = self.root / f"{COMMIT_FILE}.tmp"
            tmp.write_text(json.dumps(journal))
            os.replace(tmp, self.root / COMMIT_FILE)
            self._apply_commit(journal)
        if interrupted:
            logger.warning("interrupted while the result was being moved into place; the result is complete")

    def start_again(self, footprint: Any) -> None:
        """A plan that changed after stage 1: the work so far is removed and the density that
        changed it kept (a resumed run plans from it at once, :meth:`kept_footprint`)."""
        for sub in WORK_FOLDERS:
            shutil.rmtree(self.root / sub, ignore_errors=True)
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        save_object(self.root / FOOTPRINT_FILE, footprint)

    def kept_footprint(self) -> Any | None:
        """The density an interrupted run counted in stage 1 before it started again, if any."""
        from .survey.blocks import FootprintDensity

        found = kept_result(self.root / FOOTPRINT_FILE) if self.resumed else None
        return found if isinstance(found, FootprintDensity) else None

    @property
    def commit_pending(self) -> bool:
        """Whether an interrupted run of this folder had begun its commit (``--resume`` finishes it)."""
        return (self.root / COMMIT_FILE).is_file()

    def finish_commit(self) -> None:
        """Finish the commit an interrupted run began (its journal says what it moves)."""
        journal = _read_json(self.root / COMMIT_FILE)
        if not isinstance(journal.get("products"), list) or not isinstance(journal.get("written"), list):
            raise OutputError(f"{self.root / COMMIT_FILE}: the commit journal cannot be read; run without --resume")
        safe = [n for n in journal["products"] + journal["written"] if isinstance(n, str) and _plain_name(n)]
        if len(safe) != len(journal["products"]) + len(journal["written"]):
            raise OutputError(f"{self.root / COMMIT_FILE}: the commit journal names a path outside the folder")
        with deferred_interrupts() as interrupted:
            self._apply_commit(journal)
        if interrupted:
            logger.warning("interrupted while the result was being moved into place; the result is complete")

    def _apply_commit(self, journal: dict[str, Any]) -> None:
        """Move what is still staged into OUT (idempotent: a product already moved stays)."""
        products, written = tuple(journal["products"]), set(journal["written"])
        keep_work = bool(journal.get("keep_work"))
        manifest = MANIFEST if MANIFEST in products else None
        if manifest is not None:
            (self.out / manifest).unlink(missing_ok=True)
        for pattern in journal.get("replaces", ()):
            for stale in self.out.glob(pattern):
                if stale.name not in products and stale.is_file():
                    stale.unlink()
        ordered = [name for name in products if name != manifest] + ([manifest] if manifest else [])
        for name in ordered + (["work"] if keep_work else []):
            source, target = self.root / name, self.out / name
            staged = _has_content(source)
            if not staged and name in written:
                continue  # moved into place before the interruption
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            elif target.exists() or target.is_symlink():
                target.unlink()  # also a product an older run wrote and this one does not
            if staged:
                os.replace(source, target)
        shutil.rmtree(self.root, ignore_errors=True)
        _unlock(self.out)

    def remove(self) -> None:
        """Delete a failed run's staging folder; a task still finishing may race the first try."""
        for _ in range(5):
            shutil.rmtree(self.root, ignore_errors=True)
            if not self.root.exists():
                break
            time.sleep(0.2)
        _unlock(self.out)

    def keep_for_resume(self) -> None:
        """An interrupted run: keep the folder (finished tasks' results) for ``--resume``; unlock."""
        _unlock(self.out)


def _has_content(path: Path) -> bool:
    """A staged product: a file, or a folder that is not empty."""
    return path.exists() and not (path.is_dir() and not any(path.iterdir()))


def _plain_name(name: str) -> bool:
    return name not in ("", ".", "..") and "/" not in name and "\\" not in name


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[list[int]]:
    """Hold Ctrl-C and SIGTERM until the block is done; the list says which arrived.

    Only in the main thread (where Python runs signal handlers); a signal the process
    ignores (a run started in the background of a shell) stays ignored.
    """
    arrived: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield arrived
        return
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, lambda s, _frame: arrived.append(s))
    try:
        yield arrived
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _link_tree(source: Path, target: Path) -> None:
    """Hard-link a file, or every file of a folder, to ``target`` (copy across file systems)."""
    if source.is_dir():
        shutil.copytree(source, target, copy_function=_link_or_copy, dirs_exist_ok=True)
    else:
        _link_or_copy(str(source), str(target))


def _link_or_copy(source: str, target: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(target)
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def run_and_keep(function: Callable[..., Any], result_path: str, *args: Any) -> Any:
    """Run a task and keep its result under ``result_path`` (what a resumed run reads back)."""
    result = function(*args)
    save_object(result_path, result)
    return result


def kept_result(path: Path) -> Any | None:
    """A finished task's kept result, or None when there is none (or it is unreadable)."""
    if not path.exists():
        return None
    try:
        return load_object(path)
    except (OSError, ValueError) as e:  # another version, or content this holefill did not write: recompute
        logger.warning("%s: not used, the task runs again (%s)", path.name, e)
        return None


PARTIAL_PREFIX = ".holefill-partial-"
#: In a partial folder: the footprint density that made an interrupted run plan again.
FOOTPRINT_FILE = "footprint.npz"

RUN_FILE = "run.json"
COMMIT_FILE = "commit.json"
LOCK_FILE = ".holefill.lock"
MANIFEST = "manifest.json"


def _lock(out: Path) -> None:
    """Take ``OUT/.holefill.lock``, or refuse when a live run holds it."""
    lock = out / LOCK_FILE
    me = {"pid": os.getpid(), "host": socket.gethostname()}
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = _read_json(lock)
            dead = holder.get("host") == me["host"] and not _alive(int(holder.get("pid", 0)))
            if dead or _silent_for(lock) > LOCK_STALE_S:
                # its run died without cleaning up (here, or on a node that stopped beating): take over
                lock.unlink(missing_ok=True)
                continue
            raise OutputError(
                f"{out}: another holefill run (pid {holder.get('pid', '?')} on {holder.get('host', '?')}) is writing "
                f"into this folder; wait for it, or remove {lock} if that run is gone"
            ) from None
        with os.fdopen(fd, "w") as fh:
            json.dump(me, fh)
        _Heartbeat(lock).start()
        return
    raise OutputError(f"{out}: cannot take the lock {lock}")


#: A run touches its lock this often; a lock silent for ``LOCK_STALE_S`` belongs to a dead run,
#: whatever host it came from (a requeued SLURM job, a new Kubernetes pod).
LOCK_BEAT_S = 30.0
LOCK_STALE_S = 300.0


class _Heartbeat(threading.Thread):
    """Touches the lock while this process holds it."""

    def __init__(self, lock: Path) -> None:
        super().__init__(name="holefill-lock", daemon=True)
        self.lock = lock

    def run(self) -> None:
        while True:
            time.sleep(LOCK_BEAT_S)
            if _read_json(self.lock).get("pid") != os.getpid():
                return  # released (or taken over)
            with contextlib.suppress(OSError):
                os.utime(self.lock)


def _silent_for(lock: Path) -> float:
    try:
        return time.time() - lock.stat().st_mtime
    except OSError:
        return 0.0


def _unlock(out: Path) -> None:
    lock = out / LOCK_FILE
    if _read_json(lock).get("pid") == os.getpid():
        lock.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _partial_to_resume(out: Path, run_key: str) -> Path | None:
    """The newest partial folder of the same inputs and configuration."""
    candidates = [p for p in out.glob(f"{PARTIAL_PREFIX}*") if _read_json(p / RUN_FILE).get("run_key") == run_key]
    return max(candidates, key=lambda p: p.stat().st_mtime) if candidates else None


def _remove_stale_partials(out: Path, *, keep: Path | None) -> None:
    for partial in out.glob(f"{PARTIAL_PREFIX}*"):
        if partial == keep or not partial.is_dir():
            continue
        size = sum(f.stat().st_size for f in partial.rglob("*") if f.is_file())
        logger.warning("removing %s, left by an interrupted run (%.1f MB)", partial, size / 1e6)
        shutil.rmtree(partial, ignore_errors=True)


#: A failed write with less free space than this on the output's file system is a full disk
#: (numpy and GDAL do not always say ENOSPC: ``tofile`` reports "N requested and 0 written").
DISK_FULL_FREE_BYTES = 4 << 20


def disk_full(error: OSError, folder: Path) -> bool:
    """Whether ``error`` (from writing under ``folder``) means its file system is full."""
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    try:
        return shutil.disk_usage(folder).free < DISK_FULL_FREE_BYTES
    except OSError:
        return False


def input_fingerprint(path: str, *parts: object) -> str:
    """A short stable key of an input file (path, size, times, inode) and what it is read with.

    The change time and inode are part of it: a file rewritten with the same size and
    a restored modification time (``touch -r``, ``rsync -t``) has another change time,
    which no program can set, so its old decoding and checksum are not reused.
    """
    try:
        stat = os.stat(path)
        identity: tuple[object, ...] = (
            os.path.abspath(path), stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino
        )  # fmt: skip
    except OSError:
        identity = (os.path.abspath(path),)
    return hashlib.sha1(repr((identity, parts)).encode()).hexdigest()[:12]
