"""Starting the local cluster in a background thread while the main thread imports must not race on imports."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

#: Run in a fresh interpreter: records every module first imported by a thread other than the main one.
PROBE = """
import json, sys, threading

class Record:
    seen = set()

    def find_spec(self, name, path=None, target=None):
        if threading.current_thread() is not threading.main_thread():
            self.seen.add(name)
        return None

sys.meta_path.insert(0, Record())

def main():
    from pipeline.cluster import ClusterStart
    from pipeline.config import load_config

    start = ClusterStart.begin(load_config(None, ["dask.workers=1"]))
    start.client()
    start.close()
    # modules that failed to import (optional ones distributed tries) are in no one's way
    print(json.dumps(sorted(name for name in Record.seen if name in sys.modules)))

if __name__ == "__main__":
    main()
"""


def test_the_cluster_start_thread_imports_nothing(tmp_path):
    """Two threads importing at once can deadlock on the per-module import locks (_DeadlockError, about
    once in 200 starts): every module the start needs is imported by the main thread before the thread starts."""
    probe = tmp_path / "probe.py"
    probe.write_text(PROBE)
    done = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, timeout=120, check=True)
    imported_elsewhere = json.loads(done.stdout.strip().splitlines()[-1])
    assert imported_elsewhere == [], imported_elsewhere


def test_an_interrupted_run_drops_distributed_s_shutdown_records():
    """After Ctrl-C the cluster's stop logs what the stop causes ("Couldn't gather keys ...
    forgotten"); holefill's one line says what happened. With -vv (distributed at INFO) they stay."""
    import logging

    from pipeline.cluster import quiet_shutdown

    logger = logging.getLogger("distributed")
    before = logger.level
    try:
        logger.setLevel(logging.ERROR)
        quiet_shutdown()
        assert not logging.getLogger("distributed.scheduler").isEnabledFor(logging.CRITICAL)
        logger.setLevel(logging.INFO)
        quiet_shutdown()
        assert logging.getLogger("distributed.scheduler").isEnabledFor(logging.ERROR)
    finally:
        logger.setLevel(before)


#: Run in a fresh interpreter: what the local workers' fork server had in its environment and imported.
FORK_SERVER_PROBE = """
import json, os, sys

def server_state():
    server = os.getppid()  # a worker is forked by the fork server
    with open(f"/proc/{server}/environ", "rb") as fh:
        environ = dict(item.split(b"=", 1) for item in fh.read().split(b"\\0") if b"=" in item)
    return {
        "environ": {k.decode(): v.decode() for k, v in environ.items() if k.decode().endswith("_NUM_THREADS")},
        "stages_imported": "pipeline.stages.bin_tiles" in sys.modules,
        "pipeline": sys.modules["pipeline"].__file__,
        "numba_ready": _numba_ready(),
    }

def _numba_ready():
    from numba.core.registry import cpu_target
    return len(cpu_target.target_context._registries) > 0  # refreshed (pipeline.worker_start)

def main():
    from pipeline.cluster import ClusterStart
    from pipeline.config import load_config

    start = ClusterStart.begin(load_config(None, ["dask.workers=1"]))
    result = list(start.client().run(server_state).values())[0]
    start.close()
    print(json.dumps({"server": result}))

if __name__ == "__main__":
    main()
"""


def test_workers_fork_from_a_server_with_one_blas_thread_and_the_stages_imported(tmp_path):
    """The server loads numpy and scipy for every worker; their BLAS pools take their size as
    they load, so the server itself must start with WORKER_ENV (two BLAS threads per worker made
    the fill stage 5 x slower on 2 cores). A folder named like holefill's package where holefill
    runs from is not what the server imports. numba's code generator comes set up (0.2-0.3 s a worker)."""
    import os

    from pipeline.cluster import WORKER_ENV

    if not os.path.exists("/proc/self/environ"):
        import pytest

        pytest.skip("reads the fork server's environment from /proc")
    probe = tmp_path / "probe.py"
    probe.write_text(FORK_SERVER_PROBE)
    elsewhere = tmp_path / "project"
    (elsewhere / "pipeline").mkdir(parents=True)
    (elsewhere / "pipeline" / "__init__.py").write_text("")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(Path(__file__).resolve().parents[1]), env.get("PYTHONPATH")) if p
    )
    done = subprocess.run(
        [sys.executable, str(probe)], capture_output=True, text=True, timeout=120, check=True, env=env, cwd=elsewhere
    )
    found = json.loads(done.stdout.strip().splitlines()[-1])
    assert found["server"]["environ"] == {k: v for k, v in WORKER_ENV.items() if k.endswith("_NUM_THREADS")}
    assert found["server"]["stages_imported"]
    assert found["server"]["numba_ready"]  # set up once in the server, not in each worker
    assert not found["server"]["pipeline"].startswith(str(elsewhere)), found["server"]["pipeline"]


def test_the_fork_server_environment_is_restored():
    import os

    from pipeline.cluster import _environment

    os.environ.pop("HOLEFILL_TEST_UNSET", None)
    os.environ["HOLEFILL_TEST_SET"] = "before"
    try:
        with _environment({"HOLEFILL_TEST_UNSET": "1", "HOLEFILL_TEST_SET": "1"}):
            assert os.environ["HOLEFILL_TEST_UNSET"] == os.environ["HOLEFILL_TEST_SET"] == "1"
        assert "HOLEFILL_TEST_UNSET" not in os.environ
        assert os.environ["HOLEFILL_TEST_SET"] == "before"
    finally:
        os.environ.pop("HOLEFILL_TEST_SET", None)


#: Run in a fresh interpreter: what the client imported to start the cluster, and the settings its workers run with.
LIGHT_START_PROBE = """
import json, sys

def tick(dask_worker):
    import dask
    import gc

    return (
        dask.config.get("distributed.admin.tick.interval"),
        "profile" in dask_worker.periodic_callbacks,
        gc.isenabled(),
        gc.get_freeze_count(),
    )

def main():
    from pipeline.cluster import LOCAL_CLUSTER_CONFIG, ClusterStart
    from pipeline.config import load_config

    start = ClusterStart.begin(load_config(None, ["dask.workers=1"]))
    client = start.client()
    found = {"pandas": "pandas" in sys.modules, "ticks": sorted(client.run(tick).values())}
    found["saturation"] = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.WORKER_SATURATION)
    start.close()
    print(json.dumps(found))

if __name__ == "__main__":
    main()
"""


def test_the_client_starts_the_cluster_without_pandas_and_its_workers_tick_slowly(tmp_path):
    """distributed's own fork-server preload list imported pandas into the client (0.3 s of its
    start) only to name it to a server already running ours; the workers run with the local
    cluster's settings (an event-loop check every second, not every 20 ms; no statistical profiler),
    and with the garbage collector running over their own objects: the fork server's imports frozen."""
    from pipeline.cluster import LOCAL_CLUSTER_CONFIG

    probe = tmp_path / "probe.py"
    probe.write_text(LIGHT_START_PROBE)
    done = subprocess.run([sys.executable, str(probe)], capture_output=True, text=True, timeout=120, check=True)
    found = json.loads(done.stdout.strip().splitlines()[-1])
    assert found["pandas"] is False
    [(tick, profiler, collecting, frozen)] = found["ticks"]
    assert (tick, profiler) == (LOCAL_CLUSTER_CONFIG["distributed.admin.tick.interval"], False)  # and no profiler
    assert collecting and frozen > 100_000  # distributed, numpy, numba and the stages: some 400,000 objects
    # each worker holds three ready tasks, not one and a tenth: walls tasks of 80 ms do not wait on a
    # scheduler whose thread the client's writing holds up
    assert found["saturation"] == LOCAL_CLUSTER_CONFIG["distributed.scheduler.worker-saturation"] == 3.0


def test_the_run_module_leaves_scipy_optimize_to_the_fills_that_need_it():
    """scipy.optimize (with linprog and HiGHS) was imported by every process importing the fill, at
    its start; only a river's levels (least squares) and the linear fill (scipy.interpolate) use it."""
    code = "import sys, pipeline.run; print(sorted(m for m in ('scipy.optimize', 'scipy.interpolate') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip().splitlines()[-1] == "[]"
