"""The garbage collector paused over imports, and what they made frozen in holefill's own processes (pipeline.gc_pause)."""

from __future__ import annotations

import gc

import pytest

from pipeline import gc_pause
from pipeline.gc_pause import collector_paused


@pytest.fixture
def collector_state(monkeypatch):
    """Restore the collector as the test found it (frozen objects go back to the oldest generation)."""
    enabled = gc.isenabled()
    monkeypatch.setattr(gc_pause, "_own_process", False)
    gc.unfreeze()
    yield
    gc.unfreeze()
    if enabled:
        gc.enable()
    else:
        gc.disable()


def test_holefill_s_own_process_freezes_what_the_block_made(collector_state):
    gc_pause.own_process()
    gc.enable()
    with collector_paused():
        assert not gc.isenabled()
        made = [[] for _ in range(1000)]
    assert gc.isenabled()
    assert gc.get_freeze_count() >= len(made)  # frozen: no later collection walks them


def test_a_program_calling_holefill_keeps_its_collector_unfrozen(collector_state):
    """In another program's process the collector is only paused over the imports: frozen objects are
    never collected, and that program may call holefill again and again."""
    gc.enable()
    with collector_paused():
        assert not gc.isenabled()
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_a_paused_collector_stays_paused_and_an_error_still_freezes(collector_state):
    gc_pause.own_process()
    gc.disable()
    with pytest.raises(ImportError), collector_paused():
        raise ImportError("no such module")
    assert not gc.isenabled()  # a program that had paused it keeps it paused
    assert gc.get_freeze_count() > 0


#: The ``holefill`` script in a fresh interpreter, stopped by a missing AOI right after its start's imports.
SCRIPT_PROBE = """
import atexit, gc, sys
from pipeline.cli import console_main
atexit.register(lambda: print("frozen", gc.get_freeze_count(), gc.isenabled(), flush=True))
sys.argv = ["holefill", "run", "tile.laz", "--out", "out", "--aoi", "missing.gpkg"]
console_main()
"""


def test_the_holefill_script_freezes_its_start_s_imports(tmp_path):
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", SCRIPT_PROBE], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.returncode != 0 and "AOI file not found" in done.stderr
    frozen, count, enabled = done.stdout.split()
    assert frozen == "frozen" and int(count) > 10_000 and enabled == "True"
