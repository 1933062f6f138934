"""Work on Dask: a dask.distributed client for a build (a local cluster of processes or a
running scheduler) and its tasks, run in order of submission whatever order they finish in."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from usdforest.errors import UsdForestError

Progress = Callable[[str, int, int], None]


def run_tasks(
    client, fn: Callable, jobs: list[tuple], shared_arg, tick: Progress, stage: str
) -> list:
    """``fn(*job, shared_arg)`` for every job, results in job order: as tasks on ``client``
    (a dask.distributed Client; ``shared_arg`` sent to each worker once), or here one after
    another when it is None. Progress is reported as ``stage``. The first failure stops the
    rest and is reported as the task's error; so does an interruption, after the running
    tasks have finished (they write into the staging folder)."""
    if client is None:
        out = []
        for k, job in enumerate(jobs):
            tick(stage, k, len(jobs))
            out.append(fn(*job, shared_arg))
        tick(stage, len(jobs), len(jobs))
        return out
    from distributed import as_completed

    shared = client.scatter(shared_arg, broadcast=True)
    futures = [client.submit(fn, *job, shared, pure=False) for job in jobs]
    try:
        for k, f in enumerate(as_completed(futures)):
            tick(stage, k, len(jobs))
            if f.status == "error":
                exc = f.exception()
                if isinstance(exc, UsdForestError):
                    raise exc
                kind = {"sampling sites": "survey", "flight lines": "flight line"}.get(
                    stage, "tile"
                )
                raise UsdForestError(f"a {kind} task failed: {type(exc).__name__}: {exc}")
        tick(stage, len(jobs), len(jobs))
        return client.gather(futures)
    except BaseException:
        client.cancel(futures, force=True)
        settle(client)
        raise


def settle(client, timeout: float = 30.0) -> None:
    """Wait (up to ``timeout`` s) until no worker is running a task."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            busy = client.run(lambda dask_worker: len(dask_worker.state.executing))
        except Exception:
            return
        if not any(busy.values()):
            return
        time.sleep(0.1)


CONNECT_TIMEOUT = 10.0  # seconds for a scheduler to answer
WORKER_TIMEOUT = 30.0  # seconds for a scheduler to have a worker
CONNECT_GRACE = 5.0  # seconds more for Dask's own attempt to give up before the build does


def scheduler_address(address: str, name: str = "scheduler") -> str:
    """``address`` if it reads as a Dask scheduler's (``tcp://host:port``, ``tls://`` too;
    ``host:port`` means tcp), else an error naming ``name`` (the argument)."""
    import re

    text = address.strip()
    if text.startswith("inproc://") and len(text) > len("inproc://"):  # a cluster in this process
        return text
    if "://" not in text:
        text = "tcp://" + text
    m = re.fullmatch(r"(tcp|tls)://([^\s/:]+|\[[0-9A-Fa-f:]+\]):(\d{1,5})", text)
    if m is None or not 0 < int(m.group(3)) < 65536:
        raise UsdForestError(
            f"{name}: {address!r} is not a Dask scheduler's address (tcp://host:port, "
            "e.g. tcp://10.0.0.5:8786)"
        )
    return text


def connect(
    address: str,
    timeout: float = CONNECT_TIMEOUT,
    workers_timeout: float = WORKER_TIMEOUT,
    grace: float = CONNECT_GRACE,
):
    """A client of the scheduler at ``address`` that has at least one worker, or an error
    naming ``--scheduler`` within about ``timeout + grace + workers_timeout`` seconds: nothing
    listening, something that is not a Dask scheduler (silent, or another protocol), a
    scheduler without workers. The attempt runs in a daemon thread, so a peer that never
    answers cannot hold the build."""
    import threading

    from distributed import Client

    address = scheduler_address(address)
    box: dict = {}

    def attempt() -> None:
        try:
            client = Client(address, timeout=f"{timeout:g}s")
        except BaseException as exc:  # reported below
            box["error"] = exc
            return
        box["client"] = client
        if box.get("abandoned"):  # the wait gave up: nobody will close it
            client.close()

    t = threading.Thread(target=attempt, daemon=True, name="usdforest-connect")
    t.start()
    t.join(timeout + grace)
    box["abandoned"] = True
    if t.is_alive() or "client" not in box:
        exc = box.get("error")
        why = f"{type(exc).__name__}: {exc}".splitlines()[0][:160] if exc else "no answer"
        raise UsdForestError(
            f"--scheduler {address}: no Dask scheduler answered within {timeout:g} s ({why})"
        )
    client = box["client"]
    try:
        client.wait_for_workers(1, timeout=workers_timeout)
    except Exception:
        client.close()
        raise UsdForestError(
            f"--scheduler {address}: the scheduler has no workers (waited {workers_timeout:g} s); "
            "start some with dask worker " + address
        ) from None
    return client


@contextmanager
def dask_client(workers: int, scheduler: str | None):
    """A dask.distributed client for a tiled build: the cluster at ``scheduler``, a local
    cluster of ``workers`` processes, or None (tiles written here) for one worker."""
    if scheduler is None and workers <= 1:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UsdForestError(
            "building tiles on Dask needs dask.distributed: pip install 'usdforest[dask]'"
        ) from None
    import logging
    import os

    # Dask reports what matters as the exceptions a build raises (a worker lost, a task's
    # error); its logs (heartbeats to a closing cluster, tornado callbacks and asyncio tasks
    # a Ctrl-C cut short) are noise on a user's terminal: silent here and in the workers
    for name in ("distributed", "tornado", "tornado.application", "asyncio"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")  # (the workers too)
    if scheduler is not None:
        client = connect(scheduler)
        with client:
            yield client
        return
    with _spawned_ignoring_ctrl_c():
        # its HTTP server on a free port (":0"): with none named the scheduler still served
        # on 8787, and a second build at once warned "Port 8787 is already in use"
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
        )
    with cluster, Client(cluster) as client:
        yield client


@contextmanager
def _spawned_ignoring_ctrl_c():
    """The worker processes started inside ignore SIGINT: a terminal's Ctrl-C reaches the
    whole process group, and each Dask worker printed its KeyboardInterrupt traceback
    (about 70 lines before the build's one). This process still handles it and closes them;
    a Ctrl-C in the second or two the workers take to start is not seen (press it again).
    (A signal ignored when a process starts stays ignored in it: Python keeps it so. Only the
    main thread may set handlers; elsewhere the workers start as they would.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


@contextmanager
def process_cluster(workers: int, folder: Path, timeout: float = 120.0):
    """A scheduler and ``workers`` single-threaded workers, each its own process started with
    the ``dask`` command as a user starts them on a cluster (``dask scheduler``, ``dask
    worker``), on this machine; yields a connected client. ``folder`` holds the scheduler
    file. (For tests and benchmarks: the client's process holds no scheduler.)"""
    import os
    import subprocess
    import sys
    import time

    from distributed import Client

    exe = str(Path(sys.executable).parent / "dask")
    info = folder / "scheduler.json"
    env = {**os.environ, "DASK_LOGGING__DISTRIBUTED": "error"}
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env}
    host = ["--host", "127.0.0.1", "--no-dashboard"]
    procs = [
        subprocess.Popen(
            [exe, "scheduler", "--scheduler-file", str(info), "--port", "0", *host], **quiet
        )
    ]
    try:
        end = time.monotonic() + timeout
        while not info.is_file():
            if time.monotonic() > end or procs[0].poll() is not None:
                raise UsdForestError(f"dask scheduler did not start (see {exe})")
            time.sleep(0.1)
        worker = [exe, "worker", "--scheduler-file", str(info), "--nthreads", "1", *host]
        procs += [
            subprocess.Popen([*worker, "--memory-limit", "0"], **quiet) for _ in range(workers)
        ]
        with Client(scheduler_file=str(info), timeout=f"{timeout:g}s") as client:
            if workers:
                client.wait_for_workers(workers, timeout=timeout)
            yield client
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
