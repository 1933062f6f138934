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
                raise UsdForestError(f"a tile task failed: {type(exc).__name__}: {exc}")
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

    logging.getLogger("distributed").setLevel(logging.ERROR)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")  # (the workers too)
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, ValueError, TypeError) as exc:
            raise UsdForestError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


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
