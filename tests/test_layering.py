"""Pure kernels stay pure: no I/O library is imported by them (scikit-image's rule, made a test)."""

from __future__ import annotations

import subprocess
import sys

import pytest

KERNELS = [
    "pipeline.grid",
    "pipeline.ground_level",
    "pipeline.rasterize",
    "pipeline.config",
    "pipeline.footprint",
    "pipeline.sensor.sums",
    "pipeline.sensor.trajectory",
    "pipeline.sensor.sight",
    "pipeline.holes",
    "pipeline.holes._kernels",
    "pipeline.holes.masks",
    "pipeline.holes.stats",
    "pipeline.holes.detect",
    "pipeline.holes.link",
    "pipeline.holes.causes",
    "pipeline.holes.walls",
    "pipeline.holes.outlines",
]

#: The kernel modules in the order of the data flow: each may import only modules before it
#: (and pipeline.config / pipeline.errors, which depend on nothing). stats comes before detect:
#: it defines the statistics tables that detection fills.
FLOW = [
    "pipeline.grid",
    "pipeline.rasterize",
    "pipeline.footprint",
    "pipeline.sensor.sums",
    "pipeline.sensor.trajectory",
    "pipeline.sensor.sight",
    "pipeline.holes._kernels",
    "pipeline.holes.masks",
    "pipeline.holes.stats",
    "pipeline.holes.detect",
    "pipeline.holes.link",
    "pipeline.holes.causes",
    "pipeline.holes.walls",
    "pipeline.holes.outlines",
]
LEAVES = {"pipeline.config", "pipeline.errors"}
IO_LIBRARIES = ["laspy", "rasterio", "pyogrio", "geopandas", "distributed", "dask"]


@pytest.mark.parametrize("module", KERNELS)
def test_kernel_modules_import_no_io_or_dask(module):
    code = f"import sys, {module}; bad = [m for m in {IO_LIBRARIES!r} if m in sys.modules]; print(','.join(bad))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"{module} imports {loaded}"


def test_only_run_and_cluster_modules_import_dask():
    """Graphs are built in run.py and the client's lifecycle is in cluster.py; nothing else knows Dask."""
    import ast
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "pipeline"
    offenders = []
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            if any(name.split(".")[0] in ("dask", "distributed") for name in names):
                offenders.append(path.name)
    assert set(offenders) <= {"run.py", "cluster.py"}, offenders
    assert "cluster.py" in offenders  # the check sees imports inside functions


def _pipeline_imports(module: str) -> set[str]:
    """The pipeline modules a module imports (at module level and inside functions)."""
    import ast
    import importlib.util

    path = importlib.util.find_spec(module).origin
    package = module if path.endswith("__init__.py") else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.ImportFrom):
            base = package.rsplit(".", node.level - 1)[0] if node.level else ""
            target = ".".join(p for p in (base, node.module) if p)
            for alias in node.names:  # "from package import module" imports the module
                found.add(f"{target}.{alias.name}" if _is_module(f"{target}.{alias.name}") else target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m.startswith("pipeline.") and m != module}


def _is_module(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.parametrize("module", FLOW)
def test_kernels_import_only_earlier_stages(module):
    earlier = set(FLOW[: FLOW.index(module)]) | LEAVES
    later = _pipeline_imports(module) - earlier
    assert not later, f"{module} imports {sorted(later)}: later in the data flow, or not a kernel"
