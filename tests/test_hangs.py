"""A run never hangs: a port that is no Dask scheduler, or a cluster whose workers all die, is one line and exit 1."""

from __future__ import annotations

import http.server
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from .lasfiles import random_points, write_points


def holefill(*args: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "pipeline.cli", "run", *args, "--no-progress"]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


@pytest.fixture
def tile(tmp_path, rng) -> Path:
    return write_points(tmp_path / "a.laz", *random_points(rng, 3000))


@pytest.fixture
def http_port():
    """A local HTTP server: it accepts the connection and never speaks Dask's protocol."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1]
    server.shutdown()


def test_a_port_that_speaks_another_protocol_is_one_line_and_exit_1(tile, tmp_path, http_port):
    started = time.monotonic()
    run = holefill(str(tile), "--out", str(tmp_path / "o"), "--scheduler", f"tcp://127.0.0.1:{http_port}",
                   "--set", "dask.connect_timeout_s=2")  # fmt: skip
    _, err = run.communicate(timeout=60)
    assert run.returncode == 1, err
    assert err.strip().splitlines() == [
        f"holefill: error: tcp://127.0.0.1:{http_port}: no Dask scheduler answered within 2 s "
        "(dask.connect_timeout_s): is it a Dask scheduler's address?"
    ]
    assert time.monotonic() - started < 30
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("log_format", ["text", "json"])
def test_an_address_that_is_no_url_is_one_line(tile, tmp_path, log_format):
    command = [sys.executable, "-m", "pipeline.cli", "--log-format", log_format, "run", str(tile)]
    done = subprocess.run(command + ["--out", str(tmp_path / "o"), "--scheduler", "notaurl"], capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert done.returncode == 1 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "notaurl: not a Dask scheduler address" in done.stderr and "Traceback" not in done.stderr
