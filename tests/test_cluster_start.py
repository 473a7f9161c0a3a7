"""Starting the local cluster in a background thread while the main thread imports must not race on imports."""

from __future__ import annotations

import json
import subprocess
import sys

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
