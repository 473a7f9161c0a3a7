"""The Dask client of a run: a local cluster started in the background, or a running scheduler.

Start-up is part of a run's time: a local cluster's worker processes take about a second
to start and another to import the stages. :class:`ClusterStart` starts them in a
background thread as the very first thing a run does, with the stages preloaded, so that
the client imports its own modules and scans the tile headers meanwhile; the run asks
for the client (:meth:`ClusterStart.client`) only when it submits its first task.

This module and :mod:`pipeline.run` are the only ones that know about Dask.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FuturesTimeout
from typing import Any

from .config import Config
from .errors import ClusterError, HolefillError

logger = logging.getLogger(__name__)

#: One thread per worker process for BLAS and OpenMP (workers are single-threaded
#: processes; oversubscription slows every kernel), and a bounded GDAL cache each.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "GDAL_CACHEMAX": "256"}

#: distributed's settings for the local cluster (the scheduler and the nannies live in the
#: client's process): its event loops' health check every second, not every 20 ms; the
#: dashboard's CPU and memory samples every 2 s, not 0.5 s; work stealing rebalances every
#: 0.5 s, not 0.1 s. Idle, a 2-worker cluster's client process used 60-62 ms of CPU a second
#: with the defaults and 19-20 ms with these (2-core VM; the tick alone 42 ms): CPU the workers
#: had not, on a machine whose cores they fill. A user's own scheduler keeps its own settings.
LOCAL_CLUSTER_CONFIG = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.scheduler.work-stealing-interval": "500ms",
    # the workers' statistical profiler samples the task thread's stack every 10 ms for a
    # dashboard a local run never shows: 30 ms of CPU a second per idle worker (37 -> 8 with it off)
    "distributed.worker.profile.enabled": False,
    # a worker is handed up to three ready tasks, not 1.1 (one and the next): the scheduler lives in
    # the client's process, whose main thread holds the GIL while it writes the layers and plans the
    # flights, and the walls' 80 ms tasks waited on it, both workers idle 0.13-0.22 s four times
    # in a 42 M-point run's outputs lap (interleaved A/B, 4 rounds: 20.2 -> 19.4 s mean). A task
    # handed over holds no memory until it runs.
    "distributed.scheduler.worker-saturation": 3.0,
}

#: Seconds to wait for a ``--scheduler`` before giving up with one line.
SCHEDULER_TIMEOUT_S = 10

#: Imported by every local worker as it starts (while the client scans the headers), so
#: that the first task does not pay for it.
WORKER_PRELOAD = ["pipeline.stages.bin_tiles", "pipeline.stages.merge_cells"]

#: Imported once by the server the local workers fork from (:func:`start_fork_server`): the
#: stages and numba's code generator (:mod:`pipeline.worker_start`).
SERVER_PRELOAD = [*WORKER_PRELOAD, "pipeline.worker_start"]


class ClusterStart:
    """A local cluster being started in a background thread.

    A terminal's Ctrl-C reaches the whole process group, and only the client should
    answer it, in one line. The workers are forked from a fork server (the
    ``forkserver`` start method) that :meth:`begin` starts with SIGINT blocked
    (:func:`start_fork_server`): the server and every worker it forks keep it blocked.
    The client's own handler never leaves, so a Ctrl-C in a run's first seconds
    stops it (SIGINT ignored until the workers were up lost it, and the run went on
    to exit 0). The workers fork with distributed already imported, which also
    shortens their start.
    """

    def __init__(self, config: Config) -> None:
        self._config = config
        self._future: Future = Future()
        self._lock = threading.Lock()
        self._closed = False
        self._stopping: threading.Thread | None = None

    @classmethod
    def begin(cls, config: Config) -> ClusterStart:
        """Start the workers now; returns once distributed is imported (a fraction of a second).

        Every module the start needs is imported here, in the calling thread, before the
        background thread exists: two threads importing at once can deadlock on
        Python's per-module import locks (``_DeadlockError``, about once in 200 starts
        while the main thread imported the stages and the thread imported distributed).
        """
        start_fork_server()  # first: the server imports the stages while this process imports distributed
        import_cluster_modules()
        import dask

        dask.config.set(LOCAL_CLUSTER_CONFIG)  # the nannies hand the workers this process's settings
        start = cls(config)
        threading.Thread(target=start._start, name="holefill-cluster-start", daemon=True).start()
        return start

    def _start(self) -> None:
        try:
            self._future.set_result(_local_cluster(self._config))
        except HolefillError as e:
            self._future.set_exception(e)
        except Exception as e:  # a worker killed while starting, no free port, ...: one line
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            self._future.set_exception(ClusterError(f"the local Dask cluster cannot start: {reason}"))
        except BaseException as e:
            self._future.set_exception(e)

    def client(self) -> Any:
        """The client, once the workers are up (waits for them)."""
        return self._future.result()[1]

    def close(self) -> None:
        """Stop the client and the workers (waiting for a start still under way); idempotent.

        Waits for a stop begun by :meth:`close_in_background`.
        """
        with self._lock:
            stopping, self._stopping = self._stopping, None
            first, self._closed = not self._closed, True
        if stopping is not None:
            stopping.join()
        elif first:
            self._stop()

    def close_in_background(self) -> None:
        """Begin stopping the workers and return at once (the products are written meanwhile)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stopping = threading.Thread(target=self._stop, name="holefill-cluster-stop", daemon=True)
            self._stopping.start()

    def _stop(self) -> None:
        try:
            cluster, client = self._future.result()
        except Exception:
            return  # it never started: nothing to stop
        client.close()
        cluster.close()


#: Modules distributed imports lazily while a local cluster starts (in its start thread or
#: its event loop's): imported beforehand by :func:`import_cluster_modules`.
CLUSTER_MODULES = (
    "distributed",
    "distributed.deploy.local",
    "distributed.nanny",
    "distributed.dashboard",
    "distributed.dashboard.components",
    "distributed.dashboard.scheduler",
    "distributed.diagnostics.websocket",
    "distributed.http.health",
    "distributed.http.prometheus",
    "distributed.http.proxy",
    "distributed.http.scheduler",
    "distributed.http.scheduler.info",
    "distributed.http.scheduler.json",
    "distributed.http.scheduler.missing_bokeh",
    "distributed.http.scheduler.prometheus",
    "distributed.http.statics",
    "email.policy",
    "email.headerregistry",
    "email.contentmanager",
    "importlib_metadata",
    "importlib_metadata._adapters",
    "importlib_metadata._text",
    "multiprocessing.resource_tracker",
    "multiprocessing.synchronize",
    "multiprocessing.popen_spawn_posix",
    "multiprocessing.popen_forkserver",
    "multiprocessing.forkserver",
    "tornado.platform.asyncio",
)


#: What the fork server imports, in order: the garbage collector paused (until
#: :mod:`pipeline.worker_start` freezes what the others made: :mod:`pipeline.gc_pause`), distributed, the stages.
SERVER_MODULES = ["pipeline.fork_server_start", "distributed", *SERVER_PRELOAD]

#: How local workers are started: forked from a server process (see :class:`ClusterStart`).
START_METHOD = "forkserver"


def start_fork_server() -> None:
    """Start the server the local workers fork from, with SIGINT blocked while it starts (main thread only).

    A blocked signal stays blocked across fork and exec: in the server and in every worker
    it forks, so none of them answers a Ctrl-C. It is blocked in the calling thread alone,
    so a Ctrl-C meanwhile still reaches the client (another thread takes it, and Python
    raises it in the main thread). The resource tracker starts first: its own start
    unblocks the signal. Elsewhere (a program calling holefill from a thread) the server
    starts with the first worker, and the workers answer Ctrl-C themselves.

    The server imports distributed and the stages (:data:`SERVER_PRELOAD`) once, and every
    worker forks with them imported: each worker importing the stages itself took 0.9 s of
    a 2-core run's start. It starts before this process imports distributed, so that both
    import at once (the workers were up 0.9 s later when it started after). The server starts with :data:`WORKER_ENV`: the BLAS libraries it
    loads size their thread pools as they load, so the workers' own environment would come
    too late (a fill stage 5 x slower, its least-squares fits on two threads per worker).
    And with ``PYTHONSAFEPATH``: the server is a ``python -c`` whose path would begin with
    the working directory (Python 3.11 passes it the client's path and does not use it), so
    a ``pipeline`` folder where holefill is run from would be imported instead of holefill's.
    """
    import multiprocessing
    import multiprocessing.forkserver
    import multiprocessing.resource_tracker

    context = multiprocessing.get_context(START_METHOD)
    context.set_forkserver_preload(SERVER_MODULES)  # also for a server the first worker starts
    if threading.current_thread() is threading.main_thread():
        multiprocessing.resource_tracker.ensure_running()
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            with _environment({**WORKER_ENV, "PYTHONSAFEPATH": "1"}):
                multiprocessing.forkserver.ensure_running()
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _use_fork_server()
    # whatever distributed set: a server started again (one killed) imports the stages too
    context.set_forkserver_preload(SERVER_MODULES)


def _use_fork_server() -> None:
    """Have distributed start its workers from the fork server, with our preload list, not its own.

    Its own list would import, in this process, every package distributed knows of (pandas
    among them, 0.3 s of the client's start) only to hand their names to a server that is
    already running with ours; and it would do so in the cluster's start thread, where
    imports must not happen (see :meth:`ClusterStart.begin`). Where distributed does not
    know the flag that skips it, it sets its list here, in the calling thread, and
    :func:`start_fork_server` sets ours again.
    """
    import dask
    import distributed.utils
    from distributed.utils import get_mp_context

    dask.config.set({"distributed.worker.multiprocessing-method": START_METHOD})
    distributed.utils._forkserver_preload_set = True  # its list is set: it builds none (distributed 2023-2026)
    get_mp_context()


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """``os.environ`` with ``values`` while a child process is started from it, then as it was."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def import_cluster_modules() -> None:
    """Import, in the calling thread, what starting a local cluster imports (see :meth:`ClusterStart.begin`)."""
    import importlib

    for name in CLUSTER_MODULES:
        with contextlib.suppress(ImportError):  # an optional module distributed may do without
            importlib.import_module(name)


def _quiet_event_loop() -> None:
    """Keep the event loop's own tracebacks off stderr unless distributed logs at INFO (``-vv``).

    Importing distributed configures ``tornado.application`` to log errors: a callback
    cut short by Ctrl-C or SIGTERM while the client closes then prints a traceback
    after holefill's one line. A task that fails reaches the user as one line anyway.
    """
    if not logging.getLogger("distributed").isEnabledFor(logging.INFO):
        for name in ("tornado", "tornado.application", "tornado.general", "asyncio"):
            logging.getLogger(name).setLevel(logging.CRITICAL)


def quiet_shutdown() -> None:
    """Drop distributed's own log records from now on, unless it logs at INFO (``-vv``): the run
    was interrupted, and what the cluster's stop then reports is what the stop itself causes (a
    gather of keys the client has released: "Couldn't gather keys ... forgotten", comms closed
    under a task). holefill says what happened in one line; the ERROR line before it made a Ctrl-C
    print two (``tests/test_resume.py``, now and then on a 2-core machine)."""
    if not logging.getLogger("distributed").isEnabledFor(logging.INFO):
        logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)
    _quiet_event_loop()


def _local_cluster(config: Config) -> tuple[Any, Any]:
    from distributed import Client, LocalCluster

    _quiet_event_loop()

    workers = config.dask.workers or os.cpu_count() or 1
    verbose = logging.getLogger("distributed").isEnabledFor(logging.INFO)
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        memory_limit=config.dask.memory_limit,
        dashboard_address=":0",  # any free port: never collide with another cluster
        silence_logs=logging.INFO if verbose else logging.CRITICAL,  # task errors reach the client anyway
        env=WORKER_ENV,
        preload=WORKER_PRELOAD,
    )
    try:
        return cluster, Client(cluster)
    except BaseException:
        cluster.close()
        raise


def connect_scheduler(address: str, timeout_s: float = SCHEDULER_TIMEOUT_S) -> Any:
    """A client of a running scheduler; one line within ``timeout_s`` when it cannot be reached.

    The connection is made in a background thread and waited for: a port where another
    service answers (an HTTP server) would otherwise hold distributed's handshake for ever.
    """
    from distributed import Client

    _quiet_event_loop()
    connected: Future = Future()

    def connect() -> None:
        try:
            connected.set_result(Client(address, timeout=timeout_s))
        except BaseException as e:
            connected.set_exception(e)

    threading.Thread(target=connect, name="holefill-connect", daemon=True).start()
    try:
        return connected.result(timeout=timeout_s + 2)
    except FuturesTimeout:
        raise ClusterError(
            f"{address}: no Dask scheduler answered within {timeout_s:g} s (dask.connect_timeout_s): "
            "is it a Dask scheduler's address?"
        ) from None
    except (OSError, TimeoutError) as e:
        raise ClusterError(
            f"{address}: cannot reach the Dask scheduler within {timeout_s:g} s ({type(e).__name__})"
        ) from None
    except Exception as e:  # an address distributed cannot parse, or a protocol it does not speak
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ClusterError(f"{address}: not a Dask scheduler address ({reason})") from None


@contextlib.contextmanager
def dask_client(
    client: Any = None, scheduler: str | None = None, config: Config | None = None, *, start: ClusterStart | None = None
) -> Iterator[Any]:
    """A callable returning the run's client: the given one, a scheduler's, or a local cluster's.

    A local cluster is started at once and stopped on exit; ``start``, a cluster
    the caller is already starting, is only begun to be stopped on exit (the caller
    calls its :meth:`ClusterStart.close`). The callable waits for the workers.
    """
    if client is not None:
        yield lambda: client
        return
    if scheduler:
        remote = connect_scheduler(scheduler, config.dask.connect_timeout_s if config else SCHEDULER_TIMEOUT_S)
        with remote:
            yield lambda: remote
        return
    if start is not None:  # the caller's: stopped here in the background, the caller waits for it
        try:
            yield start.client
        finally:
            start.close_in_background()
        return
    assert config is not None
    starting = ClusterStart.begin(config)
    try:
        yield starting.client
    finally:
        starting.close()


class WorkerWatch:
    """Cancels a batch of futures once no worker has been alive for ``limit_s`` (a run would wait for ever).

    A scheduler whose workers all died (or that never had any) keeps the tasks waiting,
    saying at most "Couldn't gather 1 keys, rescheduling"; the watch asks the scheduler
    every few seconds how many workers it has. Use as a context manager around a gather;
    :attr:`lost` says whether it cancelled.
    """

    def __init__(self, client: Any, futures: list[Any], limit_s: float) -> None:
        self._client = client
        self._futures = futures
        self.limit_s = limit_s
        self.lost = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="holefill-worker-watch", daemon=True)

    def __enter__(self) -> WorkerWatch:
        if self._futures:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()

    def _watch(self) -> None:
        none_since: float | None = None
        while not self._stop.wait(min(2.0, self.limit_s / 4)):
            try:
                alive = len(self._client.nthreads())
            except Exception:  # the scheduler itself is gone: as good as no worker
                alive = 0
            if alive:
                none_since = None
                continue
            none_since = none_since if none_since is not None else time.monotonic()
            if time.monotonic() - none_since >= self.limit_s:
                self.lost = True
                with contextlib.suppress(Exception):
                    self._client.cancel(self._futures)
                return

    def error(self) -> ClusterError:
        return ClusterError(
            f"no Dask worker alive for {self.limit_s:g} s (dask.no_worker_timeout_s): every worker died or "
            "none joined the scheduler; finished tasks are kept: run again with --resume"
        )


class TaskStream:
    """Dask's record of the tasks run while the block is open (``distributed.get_task_stream``).

    ``data``: one dict per task (``key``, ``startstops`` with each ``compute`` interval, ``worker``);
    empty when the scheduler could not give it (the run goes on: the record is for the manifest).
    """

    def __init__(self, client: Any) -> None:
        self.client = client
        self.data: list[dict[str, Any]] = []
        self._stream: Any = None

    def __enter__(self) -> TaskStream:
        from distributed import get_task_stream

        try:
            self._stream = get_task_stream(client=self.client).__enter__()
        except Exception as e:  # a scheduler without the plugin: no record, same run
            logger.debug("no task stream: %s", e)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._stream is None or exc[0] is not None:  # a run that failed or was interrupted asks nothing more
            return
        try:
            self._stream.__exit__(*exc)
            self.data = list(self._stream.data)
        except Exception as e:
            logger.debug("no task stream: %s", e)


def task_stream(client: Any) -> TaskStream:
    """The tasks run while the returned context is open, with their compute seconds (:class:`TaskStream`)."""
    return TaskStream(client)
