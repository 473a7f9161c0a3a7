"""SIGTERM has one outcome whatever its timing: stop (130, tasks kept) before the commit, nothing after."""

from __future__ import annotations

import os
import signal
import time

import pytest

from pipeline import interrupt


@pytest.fixture
def handler():
    previous = interrupt.install()
    yield
    interrupt.STATE.reset()  # before the handler goes: a watchdog left over stops
    signal.signal(signal.SIGTERM, previous)
    time.sleep(interrupt.RERAISE_AFTER_S + 0.2)  # and has stopped before the next test


def term() -> None:
    os.kill(os.getpid(), signal.SIGTERM)
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
