"""The run's private folder: where stage results are kept and products are staged.

Everything a run writes goes into ``OUT/.holefill-partial-<id>/`` first::

    .holefill-partial-<id>/
        work/tiles/<tile key>/     stage 1: per-tile statistic binaries (key: file name + input fingerprint)
        work/cells/<cell id>.npz   stage 2: merged statistics of a cell and its halo
        work/holes/<cell id>.npz   detection: part labels of a cell core
        work/holes/catalog.pkl     linking: the survey's hole catalog with causes
        work/fill/hole_<id>.npz    filling: one hole's heights, method codes, distances
        dsm/dsm_<cell id>.tif      the writer stage's rasters (also fill_mask/, fill_distance/,
                                   dsm_unfilled/)
        dsm.vrt, holes.gpkg, manifest.json, report.html

Names depend on what a result is made of (a cell's position on the absolute
lattice, a tile's path, size and modification time), never on the order in
which inputs were scanned, so a later stage, a resumed run or an incremental run
can find them. Products are moved into OUT only when the whole run has
succeeded; a failed run's folder is deleted.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from .errors import OutputError

#: Subfolders every task may write into; tasks never create parent folders.
WORK_FOLDERS = (
    "work/tiles",
    "work/cells",
    "work/holes",
    "work/fill",
    "dsm",
    "fill_mask",
    "fill_distance",
    "dsm_unfilled",
)


@dataclass(frozen=True)
class Staging:
    """The staging folder of one run inside its output folder."""

    out: Path
    root: Path

    @classmethod
    def create(cls, out: str | os.PathLike) -> Staging:
        """Make the run's private folder inside OUT (created if needed) and check it is writable."""
        out = Path(out)
        try:
            out.mkdir(parents=True, exist_ok=True)
            root = out / f".holefill-partial-{uuid.uuid4().hex[:10]}"
            root.mkdir()
            for sub in WORK_FOLDERS:
                (root / sub).mkdir(parents=True)
            probe = root / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as e:
            raise OutputError(f"{out}: output folder cannot be created or written: {e.strerror or e}") from None
        return cls(out, root)

    @property
    def work(self) -> Path:
        return self.root / "work"

    def tile_folder(self, path: str, fingerprint: str) -> Path:
        """Stage-1 results of one input file."""
        return self.work / "tiles" / f"{Path(path).stem}-{fingerprint}"

    def cell_statistics(self, cell_id: str) -> Path:
        return self.work / "cells" / f"cell_{cell_id}.npz"

    def cell_labels(self, cell_id: str) -> Path:
        return self.work / "holes" / f"labels_{cell_id}.npz"

    @property
    def hole_catalog(self) -> Path:
        return self.work / "holes" / "catalog.pkl"

    def hole_fill(self, hole_id: int) -> Path:
        return self.work / "fill" / f"hole_{hole_id}.npz"

    def raster_tile(self, product: str, cell_id: str) -> Path:
        """One cell's tile of a raster product (``dsm``, ``fill_mask``, ``fill_distance``, ``dsm_unfilled``)."""
        return self.root / product / f"{product}_{cell_id}.tif"

    def dsm_tile(self, cell_id: str) -> Path:
        return self.raster_tile("dsm", cell_id)

    def product(self, name: str) -> Path:
        return self.root / name

    def commit(self, products: tuple[str, ...], *, keep_work: bool, replaces: tuple[str, ...] = ()) -> None:
        """Move every product into OUT, replacing older ones, then delete the staging folder.

        ``replaces``: glob patterns of products an older run may have left in OUT that
        this run does not write again (e.g. the files of a sortie no longer planned);
        they are removed so that OUT never mixes two runs.
        """
        for pattern in replaces:
            for stale in self.out.glob(pattern):
                if stale.name not in products and stale.is_file():
                    stale.unlink()
        for name in products + (("work",) if keep_work else ()):
            source, target = self.root / name, self.out / name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            elif target.exists() or target.is_symlink():
                target.unlink()  # also a product an older run wrote and this one does not
            if source.exists() and not (source.is_dir() and not any(source.iterdir())):
                os.replace(source, target)
        shutil.rmtree(self.root, ignore_errors=True)

    def remove(self) -> None:
        """Delete a failed run's staging folder; a task still finishing may race the first try."""
        for _ in range(5):
            shutil.rmtree(self.root, ignore_errors=True)
            if not self.root.exists():
                return
            time.sleep(0.2)


def input_fingerprint(path: str, *parts: object) -> str:
    """A short stable key of an input file (path, size, modification time) and what it is read with."""
    try:
        stat = os.stat(path)
        identity: tuple[object, ...] = (os.path.abspath(path), stat.st_size, stat.st_mtime_ns)
    except OSError:
        identity = (os.path.abspath(path),)
    return hashlib.sha1(repr((identity, parts)).encode()).hexdigest()[:12]
