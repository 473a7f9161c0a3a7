"""The garbage collector paused over imports, and what they made frozen (pipeline.gc_pause)."""

from __future__ import annotations

import gc

import pytest

from pipeline.gc_pause import collector_paused


@pytest.fixture
def collector_state():
    """Restore the collector as the test found it (frozen objects go back to the oldest generation)."""
    enabled = gc.isenabled()
    yield
    gc.unfreeze()
    if enabled:
        gc.enable()
    else:
        gc.disable()


def test_the_collector_is_paused_over_the_block_then_runs_over_new_objects_only(collector_state):
    gc.enable()
    gc.unfreeze()
    with collector_paused():
        assert not gc.isenabled()
        made = [[] for _ in range(1000)]
    assert gc.isenabled()
    assert gc.get_freeze_count() >= len(made)  # frozen: no later collection walks them


def test_a_paused_collector_stays_paused_and_an_error_still_freezes(collector_state):
    gc.disable()
    gc.unfreeze()
    with pytest.raises(ImportError), collector_paused():
        raise ImportError("no such module")
    assert not gc.isenabled()  # a program that had paused it keeps it paused
    assert gc.get_freeze_count() > 0
