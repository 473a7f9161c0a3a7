"""What a run may replace in its output folder: only holefill's own result of the same survey.

A run moves its products into ``--out`` at the end, replacing the folders and files of
the same names (:meth:`pipeline.staging.Staging.commit`). So before any work it checks
that nothing there belongs to someone else:

- a folder holefill writes (``dsm/``, ``points/``, ...) holding a file it does not
  write (``dsm/notes.txt``) would lose it: refused;
- a non-empty folder that holds no holefill result (no ``manifest.json``) and names
  that holefill does not write (someone's files): refused;
- a result of another configuration (its manifest's ``config_key``), or of another
  survey (none of its inputs is an input of this run): refused.

``--overwrite`` accepts all three (files at the top level that holefill does not
write are left alone even then). Every refusal is an :class:`OutputError` (exit 4).
"""

from __future__ import annotations

import fnmatch
import json
from collections.abc import Iterable
from pathlib import Path

from .errors import OutputError
from .staging import LOCK_FILE, MANIFEST, PARTIAL_PREFIX

#: Folders holefill writes into OUT, and the names of the files it writes there.
#: (GIS and point tools add side files to products: statistics, overviews, spatial indices.)
SIDE_FILES = ("*.aux.xml", "*.ovr", "*.lax")
PRODUCT_FOLDERS = {
    "dsm": ("dsm_*.tif", *SIDE_FILES),
    "fill_mask": ("fill_mask_*.tif", *SIDE_FILES),
    "fill_distance": ("fill_distance_*.tif", *SIDE_FILES),
    "dsm_unfilled": ("dsm_unfilled_*.tif", *SIDE_FILES),
    "points": ("*.laz", *SIDE_FILES),
    "work": ("*",),  # kept results (--incremental, output.keep_intermediate)
}
#: Files holefill writes at the top of OUT.
PRODUCT_FILES = (
    "*.vrt",
    "holes.gpkg",
    "holes.gpkg-*",  # SQLite's journal while a GIS has it open
    *SIDE_FILES,
    MANIFEST,
    "report.html",
    "flightplan*.gpkg",
    "flightplan*.plan",
    "flightplan*.waypoints",
    "flightplan*.kmz",
    "flightplan*.kml",
    LOCK_FILE,
    f"{PARTIAL_PREFIX}*",
)

OVERWRITE_HINT = "use --overwrite to replace it, or another --out"


def check_before_run(out: Path, config_key: str, *, overwrite: bool) -> None:
    """Refuse an output folder whose files holefill would delete or mix with its own (see the module)."""
    if overwrite or not out.is_dir():
        return
    foreign = _foreign_in_product_folders(out)
    if foreign is not None:
        raise OutputError(
            f"{out}: {foreign.relative_to(out)} is not a holefill product and would be deleted with its folder; "
            "move it away, or use --overwrite"
        )
    manifest = _manifest(out)
    if manifest is None:
        others = [p.name for p in out.iterdir() if not _is_product_name(p.name)]
        if others:
            raise OutputError(
                f"{out}: is not empty and holds no holefill result ({', '.join(sorted(others)[:3])}"
                f"{', ...' if len(others) > 3 else ''}); {OVERWRITE_HINT}"
            )
        return
    previous = manifest.get("config_key")
    if previous is not None and previous != config_key:
        raise OutputError(f"{out}: holds the result of another configuration (manifest.json); {OVERWRITE_HINT}")


def check_same_survey(out: Path, inputs: Iterable[str], *, overwrite: bool) -> None:
    """Refuse a result none of whose inputs is an input of this run: another survey's (after the scan)."""
    manifest = None if overwrite else _manifest(out)
    if manifest is None or not manifest.get("complete"):
        return
    previous = {
        str(Path(i["path"]).resolve()) for i in manifest.get("inputs", []) if isinstance(i, dict) and "path" in i
    }
    if previous and not previous & {str(Path(p).resolve()) for p in inputs}:
        raise OutputError(
            f"{out}: holds the result of another survey (none of its {len(previous):,} inputs is an input of this "
            f"run); {OVERWRITE_HINT}"
        )


def _manifest(out: Path) -> dict | None:
    try:
        manifest = json.loads((out / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _is_product_name(name: str) -> bool:
    return name in PRODUCT_FOLDERS or any(fnmatch.fnmatchcase(name, pattern) for pattern in PRODUCT_FILES)


def _foreign_in_product_folders(out: Path) -> Path | None:
    """The first file in a folder holefill replaces whole that holefill does not write there."""
    for name, patterns in PRODUCT_FOLDERS.items():
        folder = out / name
        if not folder.is_dir() or folder.is_symlink():
            continue
        for path in folder.iterdir() if name != "work" else ():
            if not (path.is_file() and any(fnmatch.fnmatchcase(path.name, p) for p in patterns)):
                return path
    return None
