"""Run many independent jobs: a local process pool, or a Dask ``distributed`` cluster.

One execution engine for the fleet commands (``lampsam compare``, ``lampsam batch``):
:func:`run_jobs` applies a picklable module-level function to every job and returns
the results in job order.

- Default: a local ``ProcessPoolExecutor`` (spawned processes, one fresh process per
  job so its peak memory is its own, one BLAS thread each).
- ``dask="local"``: a ``distributed.LocalCluster`` on this machine with ``workers``
  single-threaded worker processes (dashboard on a free port, see ``client.dashboard_link``).
- ``dask="tcp://host:8786"``: an existing scheduler. Its workers must import the same
  ``lampsam`` version, and the run directories and the output directory must be at
  the same paths on every worker (a shared file system): the jobs read their run
  and write their outputs there; only small result records travel back.

Every job yields a result: a job whose function raises, whose worker dies, or whose
future is lost becomes ``failed(job, reason)``, so a failure stays a failed row. A
stop request (SIGINT/SIGTERM) cancels the jobs not started; they are returned as
unfinished, never as results.
A progress bar (tqdm, stderr) follows completion of the pool's or Dask's futures.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from lampsam.errors import LampsamError
from lampsam.interrupt import stop_requested

if TYPE_CHECKING:
    from distributed import Client

log = logging.getLogger(__name__)

J = TypeVar("J")
R = TypeVar("R")

#: ``dask`` value that starts a ``LocalCluster`` instead of connecting to a scheduler.
DASK_LOCAL = "local"
#: Seconds to wait for an existing scheduler to answer.
CONNECT_TIMEOUT_S = 20.0

_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


class FleetError(LampsamError):
    """The execution engine could not be set up (no Dask installed, scheduler unreachable)."""


@contextlib.contextmanager
def single_threaded_children() -> Iterator[None]:
    """One BLAS/OpenMP thread in processes spawned inside the block; restored after.

    Parallelism comes from the worker processes, and a threaded BLAS on the EKF's
    small matrices was measured ~7x slower on 2 cores (scripts/bench/bench_scaling.py).
    Spawned children read these variables when they import numpy. A value the user
    set is kept.
    """
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    for v in _THREAD_VARS:
        os.environ.setdefault(v, "1")
    try:
        yield
    finally:
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old


def _bar(total: int, desc: str, show: bool) -> Any:
    """A tqdm progress bar on stderr, or None."""
    if not show:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="job")


def _reason(exc: BaseException) -> str:
    return f"failed: {type(exc).__name__}: {exc}"


def run_local(fn: Callable[[J], R], jobs: Sequence[J], failed: Callable[[J, str], R],
              workers: int = 2, progress: bool = True, desc: str = "jobs",
              interrupted: Callable[[R], bool] | None = None) -> tuple[list[R], list[J]]:
    """Every job in a fresh spawned process, ``workers`` at a time (see :func:`run_jobs`).

    A stop request (SIGINT or SIGTERM, :mod:`lampsam.interrupt`) starts no further job
    and waits for the running ones (each stops at its next step when the signal
    reached it too, as Ctrl-C in a terminal does, or finishes); a second signal stops
    waiting and terminates the workers. Jobs are handed to the pool only as workers
    free up: a job the executor had already queued for a worker could no longer be
    cancelled, and would run after the stop.
    """
    done_results: dict[int, R] = {}
    unfinished: set[int] = set()
    ctx = mp.get_context("spawn")
    bar = _bar(len(jobs), desc, progress)
    n_workers = max(1, workers)
    with single_threaded_children(), cf.ProcessPoolExecutor(
        max_workers=n_workers, mp_context=ctx, max_tasks_per_child=1
    ) as pool:
        futures: dict[cf.Future[R], int] = {}
        pending: set[cf.Future[R]] = set()
        queue = iter(range(len(jobs)))

        def top_up() -> None:
            while len(pending) < n_workers and stop_requested() is None:
                i = next(queue, None)
                if i is None:
                    return
                fut = pool.submit(fn, jobs[i])
                futures[fut] = i
                pending.add(fut)

        try:
            top_up()
            while pending:
                done, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
                for fut in done:
                    _collect_local(fut, futures[fut], jobs, failed, done_results, unfinished)
                    if bar is not None:
                        bar.update(1)
                if stop_requested() is not None:
                    for fut in pending:
                        fut.cancel()
                    pending = {f for f in pending if not f.cancelled()}
                top_up()
        except KeyboardInterrupt:  # a second signal: stop waiting for the running jobs
            pool.shutdown(wait=False, cancel_futures=True)
            for child in mp.active_children():
                child.terminate()
        for fut, i in futures.items():
            if i in done_results or i in unfinished:
                continue
            if fut.done() and not fut.cancelled():
                _collect_local(fut, i, jobs, failed, done_results, unfinished)
            else:
                unfinished.add(i)
        unfinished |= set(queue)  # never handed to the pool
    if bar is not None:
        bar.close()
    return _ordered(jobs, done_results, unfinished, interrupted)


def _collect_local(fut: cf.Future[R], i: int, jobs: Sequence[J], failed: Callable[[J, str], R],
                   done_results: dict[int, R], unfinished: set[int]) -> None:
    """Store a finished pool future's result (or its failure) under job index ``i``."""
    if fut.cancelled():
        unfinished.add(i)
        return
    try:
        done_results[i] = fut.result()
    except KeyboardInterrupt:  # stopped at once in the worker (second signal)
        unfinished.add(i)
    except cf.process.BrokenProcessPool as exc:  # the worker process itself died
        done_results[i] = failed(jobs[i], f"failed: worker died: {type(exc).__name__}: {exc}")
    except Exception as exc:  # raised by the job
        done_results[i] = failed(jobs[i], _reason(exc))


def _ordered(jobs: Sequence[J], done_results: dict[int, R], unfinished: set[int],
             interrupted: Callable[[R], bool] | None) -> tuple[list[R], list[J]]:
    """Results in job order, and the unfinished jobs (not run, or interrupted results)."""
    results = [done_results[i] for i in sorted(done_results)]
    stopped = set(unfinished)
    if interrupted is not None:
        stopped |= {i for i, r in done_results.items() if interrupted(r)}
    return results, [jobs[i] for i in sorted(stopped)]


@contextlib.contextmanager
def dask_client(address: str, workers: int = 2) -> Iterator[Client]:
    """A ``distributed.Client``: on a new ``LocalCluster`` (``address == "local"``) or a scheduler.

    Args:
        address: ``"local"`` or a scheduler address such as ``tcp://10.0.0.5:8786``.
        workers: worker processes of the local cluster (ignored for a scheduler).

    Raises:
        FleetError: ``distributed`` is not installed, or the scheduler does not answer
            within :data:`CONNECT_TIMEOUT_S`.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise FleetError("--dask needs the 'distributed' package (pip install 'dask[distributed]')"
                         ) from exc
    if address == DASK_LOCAL:
        with single_threaded_children(), LocalCluster(
            n_workers=max(1, workers), threads_per_worker=1, processes=True,
            # ":0": a free port (None does not disable it: dask/distributed#8136), so
            # several clusters on one machine do not fight over 8787
            dashboard_address=":0", host="127.0.0.1",
        ) as cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise FleetError(f"--dask {address}: cannot reach the scheduler: {exc}") from exc
    with client:
        yield client


def run_dask(client: Client, fn: Callable[[J], R], jobs: Sequence[J],
             failed: Callable[[J, str], R], progress: bool = True, desc: str = "jobs",
             interrupted: Callable[[R], bool] | None = None) -> tuple[list[R], list[J]]:
    """Every job as one Dask future on ``client`` (see :func:`run_jobs`).

    A stop request cancels the futures not finished yet (they are the unfinished
    jobs); a second signal stops waiting at once.
    """
    futures = [client.submit(fn, job, pure=False) for job in jobs]
    index = {fut.key: i for i, fut in enumerate(futures)}
    done_results: dict[int, R] = {}
    unfinished: set[int] = set()
    bar = _bar(len(jobs), desc, progress)
    pending = set(futures)
    try:
        while pending:
            # futures' states are kept up to date by the client: poll them, so a stop
            # request is seen within the polling interval
            done = {f for f in pending if f.done()}
            pending -= done
            if not done:
                time.sleep(0.1)
            for fut in done:
                i = index[fut.key]
                try:
                    done_results[i] = fut.result()
                except Exception as exc:  # raised in the job, or the worker was lost
                    done_results[i] = failed(jobs[i], _reason(exc))
                if bar is not None:
                    bar.update(1)
            if stop_requested() is not None and pending:
                client.cancel(list(pending))
                unfinished |= {index[f.key] for f in pending}
                pending = set()
    except KeyboardInterrupt:  # a second signal
        client.cancel([f for f in futures if not f.done()])
        unfinished |= {i for i in range(len(jobs)) if i not in done_results}
    finally:
        if bar is not None:
            bar.close()
    return _ordered(jobs, done_results, unfinished, interrupted)


def run_jobs(fn: Callable[[J], R], jobs: Sequence[J], failed: Callable[[J, str], R],
             workers: int = 2, dask: str | None = None, progress: bool = True,
             desc: str = "jobs", interrupted: Callable[[R], bool] | None = None
             ) -> tuple[list[R], list[J]]:
    """Apply ``fn`` to every job in parallel; failures included, stop requests honoured.

    Args:
        fn: a module-level function (pickled by reference to the workers). It should
            turn its own errors into a failed result; anything it raises becomes
            ``failed(job, reason)``.
        jobs: picklable job descriptions.
        failed: builds the result of a job that raised or whose worker died.
        workers: local processes (pool, or the ``LocalCluster``'s workers).
        dask: None (local process pool), ``"local"`` or a scheduler address.
        progress: show a progress bar on stderr.
        desc: the progress bar's label.
        interrupted: tells a result of a job stopped by a signal (it is returned and
            its job is also listed as unfinished).

    Returns:
        ``(results, unfinished)``: the results of the jobs that came back, in job
        order (every job when nothing stopped the run), and the jobs not run or
        interrupted by a stop request (SIGINT/SIGTERM, :mod:`lampsam.interrupt`).

    Raises:
        FleetError: the Dask engine cannot be set up.
    """
    if not jobs:
        return [], []
    if dask is None:
        return run_local(fn, jobs, failed, workers, progress, desc, interrupted)
    with dask_client(dask, workers) as client:
        log.info("running %d jobs on %s", len(jobs), client)
        return run_dask(client, fn, jobs, failed, progress, desc, interrupted)
