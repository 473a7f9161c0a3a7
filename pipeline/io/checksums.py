"""File checksums for the manifest: what a run read and what it wrote, verifiable later."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: Bytes read per step while hashing (the file is streamed, never held whole).
BLOCK_BYTES = 1 << 20


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, as ``sha256sum`` prints it."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(BLOCK_BYTES):
            digest.update(block)
    return digest.hexdigest()


def input_record(path: str) -> dict[str, object]:
    """Path, size, modification time and SHA-256 of one input file (the manifest's ``inputs``).

    Size and time are what a later run compares to find changed tiles (as ``make``
    and ``rsync`` do); the checksum is there to verify a delivery.
    """
    stat = os.stat(path)
    return {
        "path": path,
        "bytes": stat.st_size,
        "mtime": stat.st_mtime,
        "sha256": file_sha256(path),
    }


def output_records(root: Path, names: list[str]) -> list[dict[str, object]]:
    """Path (relative to ``root``), size and SHA-256 of every file under the given products."""
    records = []
    for name in names:
        product = root / name
        files = sorted(p for p in product.rglob("*") if p.is_file()) if product.is_dir() else [product]
        for file in files:
            if file.exists():
                rel = file.relative_to(root).as_posix()
                records.append({"path": rel, "bytes": file.stat().st_size, "sha256": file_sha256(file)})
    return records
