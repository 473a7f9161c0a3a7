"""Pure kernels stay pure: no I/O library is imported by them (scikit-image's rule, made a test)."""

from __future__ import annotations

import subprocess
import sys

import pytest

KERNELS = ["pipeline.grid", "pipeline.rasterize", "pipeline.config"]
IO_LIBRARIES = ["laspy", "rasterio", "pyogrio", "geopandas", "distributed", "dask"]


@pytest.mark.parametrize("module", KERNELS)
def test_kernel_modules_import_no_io_or_dask(module):
    code = (
        f"import sys, {module}; "
        f"bad = [m for m in {IO_LIBRARIES!r} if m in sys.modules]; "
        "print(','.join(bad))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"{module} imports {loaded}"


def test_only_run_module_imports_dask():
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "pipeline"
    offenders = [
        p.name
        for p in root.rglob("*.py")
        if p.name != "run.py" and ("import distributed" in p.read_text() or "from distributed" in p.read_text() or "import dask" in p.read_text())
    ]
    assert offenders == []
