"""Pure kernels stay pure: no I/O library is imported by them (scikit-image's rule, made a test)."""

from __future__ import annotations

import subprocess
import sys

import pytest

KERNELS = [
    "pipeline.quantiles",
    "pipeline.grid",
    "pipeline.survey.density",
    "pipeline.survey.blocks",
    "pipeline.survey.ground_level",
    "pipeline.rasterize",
    "pipeline.config",
    "pipeline.survey.footprint",
    "pipeline.sensor.sums",
    "pipeline.sensor.trajectory",
    "pipeline.sensor.sight",
    "pipeline.holes",
    "pipeline.holes.coverage",
    "pipeline.holes.flight_lines",
    "pipeline.holes._kernels",
    "pipeline.holes.masks",
    "pipeline.holes.stats",
    "pipeline.holes.detect",
    "pipeline.holes.link",
    "pipeline.holes.causes",
    "pipeline.holes.wall_step",
    "pipeline.holes.walls",
    "pipeline.holes.outlines",
    "pipeline.holes.vertical",
    "pipeline.fill",
    "pipeline.fill.settings",
    "pipeline.fill._problem",
    "pipeline.fill.baselines",
    "pipeline.fill.laplace",
    "pipeline.fill.mls",
    "pipeline.fill.scattered",
    "pipeline.fill.natural",
    "pipeline.fill.region",
    "pipeline.fill.provenance",
    "pipeline.fill.causes",
    "pipeline.fill.water_level",
    "pipeline.fill.hydro",
    "pipeline.fill.seams",
    "pipeline.fill.by_cause",
    "pipeline.flightplan",
    "pipeline.flightplan.coverage",
    "pipeline.flightplan.route",
    "pipeline.flightplan.altitude",
    "pipeline.flightplan.rescan",
    "pipeline.flightplan.takeoff",
    "pipeline.flightplan.takeoff_search",
    "pipeline.flightplan.clearance",
    "pipeline.flightplan.mission",
]

#: The kernel modules in the order of the data flow: each may import only modules before it
#: (and the leaves, which depend on nothing: pipeline.errors, pipeline.quantiles). No kernel imports pipeline.config: its
#: parameters are a record of its own, built from the configuration by pipeline.parameters.
#: stats comes before detect: it defines the statistics tables that detection fills. The
#: fill kernels come after the hole kernels and before the flight-plan kernels, as in a run.
FLOW = [
    "pipeline.grid",
    "pipeline.survey.density",
    "pipeline.survey.blocks",
    "pipeline.rasterize",
    "pipeline.survey.footprint",
    "pipeline.sensor.sums",
    "pipeline.sensor.trajectory",
    "pipeline.sensor.sight",
    "pipeline.holes.coverage",
    "pipeline.holes.flight_lines",
    "pipeline.holes._kernels",
    "pipeline.holes.masks",
    "pipeline.holes.stats",
    "pipeline.holes.detect",
    "pipeline.holes.link",
    "pipeline.holes.causes",
    "pipeline.holes.wall_step",
    "pipeline.holes.walls",
    "pipeline.holes.outlines",
    "pipeline.holes.vertical",
    "pipeline.fill.settings",
    "pipeline.fill._problem",
    "pipeline.fill.baselines",
    "pipeline.fill.laplace",
    "pipeline.fill.mls",
    "pipeline.fill.scattered",
    "pipeline.fill.natural",
    "pipeline.fill.region",
    "pipeline.fill.provenance",
    "pipeline.fill.causes",
    "pipeline.fill.water_level",
    "pipeline.fill.hydro",
    "pipeline.fill.seams",
    "pipeline.fill.by_cause",
    "pipeline.flightplan.coverage",
    "pipeline.flightplan.route",
    "pipeline.flightplan.altitude",
    "pipeline.flightplan.rescan",
    "pipeline.flightplan.takeoff",
    "pipeline.flightplan.takeoff_search",
    "pipeline.flightplan.clearance",
    "pipeline.flightplan.mission",
]
LEAVES = {"pipeline.errors", "pipeline.quantiles"}
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


@pytest.mark.parametrize("package", ["pipeline.holes", "pipeline.fill", "pipeline.flightplan"])
def test_every_kernel_module_is_in_the_flow(package):
    """A new module of a kernel package takes its place in FLOW (and so in the checks above)."""
    import pathlib

    folder = pathlib.Path(__file__).resolve().parents[1] / package.replace(".", "/")
    modules = {f"{package}.{path.stem}" for path in folder.glob("*.py") if path.stem != "__init__"}
    assert modules <= set(FLOW), sorted(modules - set(FLOW))


#: The root's families and what each may import of holefill: the survey's facts come before
#: the plan and the stages (only the lattice, the errors, the formats and themselves);
#: evaluation comes after everything (only the command line imports it).
FAMILY_IMPORTS = {
    "pipeline.survey": ("pipeline.errors", "pipeline.grid", "pipeline.io.", "pipeline.survey."),
}
EVALUATION_USERS = ("pipeline.evaluate", "pipeline.cli")


def _modules_of(package: str) -> list[str]:
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1]
    folder = root / package.replace(".", "/")
    names = []
    for path in folder.rglob("*.py"):
        parts = path.relative_to(root).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return sorted(names)


@pytest.mark.parametrize("family", sorted(FAMILY_IMPORTS))
def test_family_imports_nothing_that_runs_after_it(family):
    allowed = FAMILY_IMPORTS[family]
    for module in _modules_of(family):
        later = {m for m in _pipeline_imports(module) if not m.startswith(allowed) and m not in allowed}
        assert not later, f"{module} imports {sorted(later)}: later than {family}"


def test_only_the_command_line_imports_evaluation():
    """Evaluation reads a run's products: nothing the run needs may import it."""
    users = []
    for module in _modules_of("pipeline"):
        if not module.startswith(EVALUATION_USERS) and any(
            m.startswith("pipeline.evaluate") for m in _pipeline_imports(module)
        ):
            users.append(module)
    assert not users, users


#: Import circles not opened yet (none: io.las and io.copc, survey.scan and survey.footprint_density,
#: synth.scene and synth.water_bodies closed one each through an import for type checking).
KNOWN_CIRCLES: set[tuple[str, ...]] = set()


def test_no_new_import_circle():
    """No two modules import each other, even inside a function or for type checking (io.las and io.copc did)."""
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "pipeline"
    modules = []
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        modules.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    graph = {module: _pipeline_imports(module) for module in modules}
    circles = {tuple(sorted(c)) for c in _strongly_connected(graph) if len(c) > 1}
    assert circles <= KNOWN_CIRCLES, sorted(circles - KNOWN_CIRCLES)


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative) of a module graph."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start] & graph.keys())))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child] & graph.keys()))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                found.append(component)
    return found
