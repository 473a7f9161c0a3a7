"""SIGTERM and Ctrl-C have one outcome whatever their timing: stop (130, tasks kept) before the commit, nothing after."""

from __future__ import annotations

import os
import signal
import time

import pytest

from pipeline import interrupt


@pytest.fixture
def handler():
    # as in a terminal's foreground: a suite started in a shell's background inherits SIGINT ignored
    # (a run there leaves it so; test_ctrl_c_stays_ignored_where_the_process_ignores_it)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    previous = interrupt.install()
    yield
    interrupt.STATE.reset()  # before the handler goes: a watchdog left over stops
    interrupt.restore(previous)
    signal.signal(signal.SIGINT, outer)
    time.sleep(interrupt.RERAISE_AFTER_S + 0.2)  # and has stopped before the next test


def term(signum: int = signal.SIGTERM) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.05)  # the handler runs in the main thread at the next bytecode


def test_a_swallowed_term_is_raised_again_until_the_run_answers_it(handler):
    try:
        term()
    except KeyboardInterrupt:
        pass  # what Python does with an exception raised in a gc callback: print it, go on
    with pytest.raises(KeyboardInterrupt):
        deadline = time.monotonic() + 5 * interrupt.RERAISE_AFTER_S
        while time.monotonic() < deadline:
            time.sleep(0.05)
    interrupt.acknowledge()
    term()  # the clean-up is under way: a second TERM (scancel and the batch script's trap) is ignored
    time.sleep(interrupt.RERAISE_AFTER_S + 0.5)  # and the watchdog stops


def test_a_swallowed_ctrl_c_is_raised_again_and_a_second_one_is_ignored(handler):
    """A Ctrl-C lost in a gc callback used to be lost for good: the run went on as if none came."""
    seen = []
    try:
        term(signal.SIGINT)
    except KeyboardInterrupt:
        pass  # swallowed
    with pytest.raises(KeyboardInterrupt):
        deadline = time.monotonic() + 5 * interrupt.RERAISE_AFTER_S
        while time.monotonic() < deadline:
            time.sleep(0.05)
    seen.append(interrupt.STATE.signum)
    interrupt.acknowledge()
    term(signal.SIGINT)  # a second Ctrl-C during the clean-up is ignored
    assert seen == [signal.SIGINT]
    time.sleep(interrupt.RERAISE_AFTER_S + 0.5)


def test_ctrl_c_stays_ignored_where_the_process_ignores_it():
    """A run started in a shell's background inherits SIGINT ignored: install leaves it so."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        previous = interrupt.install()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert set(previous) == {signal.SIGTERM}
        interrupt.STATE.reset()
        interrupt.restore(previous)
    finally:
        signal.signal(signal.SIGINT, before)


def test_a_term_after_the_commit_began_is_ignored(handler):
    interrupt.begin_commit()
    term()
    term()


def test_a_pending_term_stops_the_run_at_the_commit(handler):
    try:
        term()
    except KeyboardInterrupt:
        pass
    with pytest.raises(KeyboardInterrupt):
        interrupt.begin_commit()
    interrupt.acknowledge()


def test_a_term_during_a_gc_callback_waits_until_it_returns(handler):
    """A callback cut short keeps a half-changed state: distributed's GCDiagnosis, stopped between
    its start and stop timings, failed an assertion at the next full collection, with a traceback
    above the run's one line (CI, a SIGTERM test). The TERM is raised once the callback returned."""
    import gc

    phases = []

    def timing(phase, info):
        if phase == "start":
            term()
        phases.append(phase)  # reached: the callback ran to its end

    gc.callbacks.append(timing)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(timing)
    assert phases[:2] == ["start", "stop"]
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):  # raised where the run can answer it, at once
        while time.monotonic() < started + interrupt.RERAISE_AFTER_S / 2:
            time.sleep(0.005)
    interrupt.acknowledge()


def test_a_term_swallowed_by_a_finalizer_prints_no_traceback(handler):
    """Python reports an exception a finalizer raises ("Exception ignored in", a traceback); a
    TERM's is raised again by the watchdog, so it is not reported. Others still are."""
    import sys

    pytest_hook = sys.unraisablehook  # pytest sets its own around each test's call
    interrupt.install()
    reported = []
    interrupt._previous_unraisable = reported.append  # where a report goes on (Python's printer)

    class Stopped:
        def __del__(self):
            term()

    class Failing:
        def __del__(self):
            raise ValueError("a finalizer's own failure")

    try:
        Stopped()  # dropped at once: its finalizer runs and the TERM comes there
        assert reported == []
        with pytest.raises(KeyboardInterrupt):  # raised again where the run can answer it
            deadline = time.monotonic() + 5 * interrupt.RERAISE_AFTER_S
            while time.monotonic() < deadline:
                time.sleep(0.05)
        interrupt.acknowledge()
        Failing()
        assert [r.exc_type for r in reported] == [ValueError]
    finally:
        sys.unraisablehook = interrupt._previous_unraisable = pytest_hook
