"""Benchmark: whole `holefill run` commands as a user runs them, against decoding alone.

Both sides are timed as commands from process start to exit: `holefill run` (Python start,
imports, header scan, cluster start, every stage, outputs) against the plainest baseline,
a Python process that decodes every tile with laspy + lazrs in a `ProcessPoolExecutor`
with as many processes as holefill has workers. Runs are interleaved (decode, DSM only,
default, decode, ...) so every command sees the same machine state; best of N.

    .venv/bin/python bench/bench_command.py                       # ~42 M points
    .venv/bin/python bench/bench_command.py --points 200e6        # ~211 M points, 320 tiles
    .venv/bin/python bench/bench_command.py --tile-m 500          # the same points in 16 tiles (issue 18's layout)
    .venv/bin/python bench/bench_command.py --workers 16,4,1      # scaling: each count in turn
    .venv/bin/python bench/bench_command.py --compare before=/tmp/old-checkout   # and another version

With ``--compare NAME=CHECKOUT`` (repeatable) the DSM-only and default commands of another
checkout of holefill run in the same rounds, interleaved with this one's (``dsm_only@NAME``,
``default@NAME``): the code of that folder on ``PYTHONPATH``, every command started from the
system's temporary folder, so that no checkout's ``pipeline`` folder is on the path by accident.
On a machine whose speed drifts, only such interleaved rounds show a change of a few percent.

With several worker counts (``--workers 16,4,1``) each count is timed in turn, decode and
holefill interleaved at that count, round after round; ``--json`` is rewritten after every
command, so a run stopped early still leaves its figures, and ``--time-limit`` starts no
repeat that would end past it. Where no ``holefill`` script lies beside the interpreter (a
checkout run with ``PYTHONPATH``), the command is ``python -m pipeline.cli``.

The survey: `pipeline.synth` preset `bench` (2 km x 2 km, 64 LAZ tiles, ~42 M points),
generated once into bench-out/ and, for more points, copied side by side with shifted
header offsets (the compressed points are copied byte for byte, tile by tile: the
survey is streamed to disk, never held in memory). The peak memory printed is the
largest resident set of any process of the command (the client or a worker):
``getrusage(RUSAGE_CHILDREN)`` of a wrapper process around each command.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import NamedTuple

#: LAS header byte positions of the x/y offsets and bounds (the same in LAS 1.0 to 1.4).
X_OFFSET, Y_OFFSET = 155, 163
MAX_X, MIN_X, MAX_Y, MIN_Y = 179, 187, 195, 203


def decode_file(path: str) -> int:
    """The baseline task: laspy + lazrs decoding every point of one file, in chunks.

    Like ``bench_rasterize.decode_tile``, but kept here: importing that module would import
    the pipeline into the baseline's start-up, which this benchmark times.
    """
    import laspy

    total = 0
    with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs) as reader:
        for chunk in reader.chunk_iterator(1_000_000):
            total += len(chunk)
    return total


def decode_command(workers: int, files: list[str]) -> None:
    """The baseline command's body (run as ``bench_command.py decode``)."""
    with ProcessPoolExecutor(workers) as pool:
        points = sum(pool.map(decode_file, files, chunksize=1))
    print(points)


class Command(NamedTuple):
    """A timed command, and the checkout whose code it runs (``PYTHONPATH``; None: this interpreter's holefill)."""

    argv: list[str]
    pythonpath: str | None = None


def timed(command: list[str], pythonpath: str | None = None) -> tuple[float, int, str]:
    """Wall seconds, peak RSS (bytes) of the command's largest process, and its stdout+stderr.

    Timed in a fresh wrapper process so that RUSAGE_CHILDREN covers this command alone. With
    ``pythonpath``, the command runs that checkout's code, started from the temporary folder.
    """
    wrapper = (
        "import json, resource, subprocess, sys, time\n"
        "t = time.perf_counter()\n"
        "p = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
        "s = time.perf_counter() - t\n"
        "peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024\n"
        "print(json.dumps({'s': s, 'peak': peak, 'rc': p.returncode, 'out': p.stdout + p.stderr}))\n"
    )
    env, cwd = None, None
    if pythonpath is not None:
        env, cwd = {**os.environ, "PYTHONPATH": pythonpath}, tempfile.gettempdir()
    done = subprocess.run(
        [sys.executable, "-c", wrapper, *command], capture_output=True, text=True, check=True, env=env, cwd=cwd
    )
    result = json.loads(done.stdout)
    if result["rc"] != 0:
        raise SystemExit(f"{' '.join(command)} failed ({result['rc']}):\n{result['out']}")
    return result["s"], result["peak"], result["out"]


def base_survey(bench_dir: Path, tile_m: float = 250.0) -> Path:
    """The 42 M-point survey in tiles of ``tile_m`` (250 m: 64 tiles; 500 m: 16), generated once."""
    from pipeline.synth import generate_survey, preset

    folder = bench_dir / f"survey_2000m_{tile_m:g}m"
    marker = folder / "complete.json"
    if not marker.exists():
        shutil.rmtree(folder, ignore_errors=True)
        t0 = time.perf_counter()
        spec = preset("bench", width_m=2000.0, height_m=2000.0, tile_size_m=tile_m)
        synthetic = generate_survey(folder, spec, keep_truth=False)
        seconds = time.perf_counter() - t0
        marker.write_text(
            json.dumps({"points": synthetic.n_points, "tiles": len(synthetic.tiles), "generation_s": round(seconds, 1)})
        )
        print(f"generated {synthetic.n_points:,} points in {seconds:.0f} s", flush=True)
    return folder


def shifted_copy(source: Path, target: Path, dx: float, dy: float) -> None:
    """Copy a LAS/LAZ file with its x/y offsets and bounds moved by (dx, dy): same points, elsewhere."""
    shutil.copyfile(source, target)
    with open(target, "r+b") as fh:
        for position, delta in ((X_OFFSET, dx), (Y_OFFSET, dy), (MAX_X, dx), (MIN_X, dx), (MAX_Y, dy), (MIN_Y, dy)):
            fh.seek(position)
            (value,) = struct.unpack("<d", fh.read(8))
            fh.seek(position)
            fh.write(struct.pack("<d", value + delta))


def large_survey(bench_dir: Path, base: Path, copies: int, columns: int | None = None) -> Path:
    """``copies`` shifted copies of the base survey in rows of ``columns`` (default: one row), east then north."""
    if copies == 1:
        return base
    columns = columns or copies
    tiles = "" if base.name == "survey_2000m_250m" else "_" + base.name.rsplit("_", 1)[1]  # e.g. "_500m"
    folder = bench_dir / (f"survey_2000m_x{copies}{tiles}" + (f"_{columns}cols" if columns < copies else ""))
    marker = folder / "complete.json"
    if not marker.exists():
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        for k in range(copies):
            for tile in sorted(base.glob("*.laz")):
                dx, dy = 2000.0 * (k % columns), 2000.0 * (k // columns)
                shifted_copy(tile, folder / f"copy{k}_{tile.name}", dx=dx, dy=dy)
        info = json.loads((base / "complete.json").read_text())
        marker.write_text(json.dumps({"points": info["points"] * copies, "tiles": info["tiles"] * copies}))
    return folder


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "decode":
        decode_command(int(sys.argv[2]), sys.argv[3:])
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=float, default=42e6, help="at least this many points (copies of 42 M)")
    parser.add_argument(
        "--workers",
        type=worker_counts,
        default=[os.cpu_count() or 1],
        help="worker count, or several separated by commas (e.g. 16,4,1), timed in that order",
    )
    parser.add_argument(
        "--columns",
        type=int,
        help="copies of the 42 M survey per row (default: all in one row); 5 with 1e9: 10 x 10 km",
    )
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--bench-dir", type=Path, default=Path("bench-out"))
    parser.add_argument("--json", type=Path, help="also write the figures to this file (after every command)")
    parser.add_argument("--tiles", type=int, help="time only the first N tiles of the survey (a quick check)")
    parser.add_argument(
        "--tile-m",
        type=float,
        default=250.0,
        help="tile size of the generated survey in metres: 250 (64 tiles a 42 M copy, the default) or 500 (16)",
    )
    parser.add_argument(
        "--time-limit",
        type=float,
        help="seconds: start no repeat of a command that would end after this (the first round always runs)",
    )
    parser.add_argument(
        "--compare",
        action="append",
        default=[],
        type=checkout,
        metavar="NAME=CHECKOUT",
        help="also time another checkout's DSM-only and default commands in the same rounds (repeatable)",
    )
    parser.add_argument(
        "--sensor-off",
        action="store_true",
        help="also time the default run without the sensor's geometry (sensor.enabled=false): what the causes cost",
    )
    args = parser.parse_args()
    started = time.perf_counter()

    args.bench_dir = args.bench_dir.resolve()  # the compared checkouts' commands start elsewhere
    base = base_survey(args.bench_dir, args.tile_m)
    per_copy = json.loads((base / "complete.json").read_text())["points"]
    survey = large_survey(args.bench_dir, base, max(1, -(-int(args.points) // per_copy)), args.columns)
    files = sorted(str(p) for p in survey.glob("*.laz"))
    if args.tiles:
        files = files[: args.tiles]
    points = survey_points(files)
    out = args.bench_dir / "command-out"
    print(
        f"survey: {points:,} points, {len(files)} LAZ tiles, "
        f"{sum(os.path.getsize(f) for f in files) / 1e6:.0f} MB; workers {args.workers}; "
        f"{processor()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}",
        flush=True,
    )
    figures: dict = {
        "points": points,
        "tiles": len(files),
        "megabytes": round(sum(os.path.getsize(f) for f in files) / 1e6),
        "machine": {"processor": processor(), "cores": os.cpu_count(), "python": sys.version.split()[0], **versions()},
        "generation_s": json.loads((base / "complete.json").read_text()).get("generation_s"),
        "by_workers": {},
    }
    runs = {n: commands(n, files, survey, out / f"w{n}", args.sensor_off, tuple(args.compare)) for n in args.workers}
    seconds = {n: {name: [] for name in runs[n]} for n in args.workers}
    peaks = {n: {name: 0 for name in runs[n]} for n in args.workers}
    stages: dict[int, dict] = {n: {} for n in args.workers}
    for i in range(args.repeat):
        for n in args.workers:
            for name, command in runs[n].items():
                elapsed = time.perf_counter() - started
                if i and args.time_limit and seconds[n][name] and elapsed + seconds[n][name][-1] > args.time_limit:
                    print(f"run {i + 1}: {n} workers {name} skipped (time limit)", flush=True)
                    continue
                s, peak, output = timed(command.argv, command.pythonpath)
                seconds[n][name].append(s)
                peaks[n][name] = max(peaks[n][name], peak)
                if name == "decode":
                    assert int(output.split()[-1]) == points, output
                else:
                    argv = command.argv
                    manifest = json.loads((Path(argv[argv.index("--out") + 1]) / "manifest.json").read_text())
                    assert manifest["summary"]["points_read"] == points
                    stages[n][name] = manifest["summary"]["stage_seconds"]
                print(f"run {i + 1}: {n} workers {name} {s:.2f} s, peak {peak / 2**20:.0f} MB", flush=True)
                figures["by_workers"][str(n)] = summary(points, seconds[n], peaks[n], stages[n])
                if args.json:
                    args.json.write_text(json.dumps(figures, indent=2))
    print(json.dumps(figures, indent=2))


def checkout(text: str) -> tuple[str, str]:
    """``"before=/tmp/old"`` -> ``("before", "/tmp/old")``: a name and a folder holding ``pipeline/``."""
    name, _, folder = text.partition("=")
    if not name or not folder or not (Path(folder) / "pipeline" / "__init__.py").is_file():
        raise argparse.ArgumentTypeError(f"expected NAME=CHECKOUT, a folder holding pipeline/: {text!r}")
    return name, str(Path(folder).resolve())


def worker_counts(text: str) -> list[int]:
    """``"16,4,1"`` -> ``[16, 4, 1]``."""
    counts = [int(part) for part in text.split(",") if part.strip()]
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"worker counts must be positive integers: {text!r}")
    return counts


def survey_points(files: list[str]) -> int:
    """Points in the files, from their headers."""
    import laspy

    total = 0
    for path in files:
        with laspy.open(path) as reader:
            total += reader.header.point_count
    return total


def holefill_command() -> list[str]:
    """The ``holefill`` script beside this interpreter, or ``python -m pipeline.cli`` (a checkout on PYTHONPATH)."""
    script = Path(sys.executable).with_name("holefill")
    return [str(script)] if script.exists() else [sys.executable, "-m", "pipeline.cli"]


def commands(
    workers: int,
    files: list[str],
    survey: Path,
    out: Path,
    sensor_off: bool,
    compare: tuple[tuple[str, str], ...] = (),
) -> dict[str, Command]:
    """The timed commands at one worker count: decode, DSM only, default (and default without the
    sensor), then the DSM-only and default commands of each compared checkout."""
    inputs = files if len(files) < len(list(survey.glob("*.laz"))) else [str(survey)]
    run = [*holefill_command(), "run", *inputs, "--workers", str(workers), "--no-progress", "--overwrite"]
    named = {
        "decode": Command([sys.executable, str(Path(__file__).resolve()), "decode", str(workers), *files]),
        "dsm_only": Command([*run, "--out", str(out / "dsm"), "--set", "holes.enabled=false"]),
        "default": Command([*run, "--out", str(out / "default")]),
    }
    if sensor_off:
        named["default_sensor_off"] = Command([*run, "--out", str(out / "sensor_off"), "--set", "sensor.enabled=false"])
    for name, folder in compare:
        named[f"dsm_only@{name}"] = Command(
            [*run, "--out", str(out / f"dsm@{name}"), "--set", "holes.enabled=false"], folder
        )
        named[f"default@{name}"] = Command([*run, "--out", str(out / f"default@{name}")], folder)
    return named


def summary(points: int, seconds: dict[str, list[float]], peaks: dict[str, int], stages: dict) -> dict:
    """The figures at one worker count so far: best seconds, ratios to decode, rates, peaks, stage seconds."""
    best = {name: min(v) for name, v in seconds.items() if v}
    return {
        "seconds": {name: round(s, 2) for name, s in best.items()},
        "runs": {name: [round(s, 2) for s in v] for name, v in seconds.items() if v},
        "ratio_vs_decode": {
            name: round(s / best["decode"], 3) for name, s in best.items() if name != "decode" and "decode" in best
        },
        "points_per_s": {name: round(points / s) for name, s in best.items()},
        "peak_process_rss_mb": {name: round(p / 2**20) for name, p in peaks.items() if p},
        "stage_seconds_last_run": stages,
    }


def processor() -> str:
    """The CPU's model name where Linux says it, else what ``platform`` says."""
    try:
        match = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
    except OSError:
        match = None
    return match.group(1).strip() if match else (platform.processor() or platform.machine())


def versions() -> dict[str, str]:
    """Versions of the packages that set the pace (read from their metadata: nothing is imported)."""
    from importlib.metadata import PackageNotFoundError, version

    found = {}
    for name in ("numpy", "numba", "laspy", "lazrs", "dask", "distributed", "rasterio", "scipy"):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            pass
    return found


if __name__ == "__main__":
    main()
