"""Computing a dask graph under the workflow's scheduler, with a progress bar that suits it.

* ``synchronous`` / ``threads``: dask's local schedulers; progress is a rich bar fed by a dask callback.
* ``processes``: a ``distributed.LocalCluster`` of single-threaded worker processes (one XLA thread each).
* ``tcp://host:port``: an existing dask scheduler. ``DASK_SCHEDULER_ADDRESS`` overrides any of these.
  Distributed progress uses distributed's own progress bar, which follows tasks on the workers.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import dask
from dask.callbacks import Callback
from rich.progress import Progress, TextColumn, TimeElapsedColumn

from selpath.pipeline.errors import EnvironmentFault, Problem
from selpath.pipeline.progress import BAR_COLUMNS, show_bars

#: Environment of worker processes: one thread for XLA and BLAS each, since dask owns the parallelism.
WORKER_ENV = {
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}

#: glibc malloc settings worker processes start with: distributed's ``pre-spawn-environ``, because malloc reads them
#: at process start (``env`` is set too late). Distributed sets ``MALLOC_TRIM_THRESHOLD_`` = 64 KiB there, to give
#: freed memory back to the OS; any such setting also freezes glibc's mmap threshold at 128 KiB, so that every
#: larger temporary is a fresh mmap whose pages fault in on first touch: a 4-frame render chunk of the volume
#: benchmark took 1.9 s in a worker against 0.6 s in-process. Arrays up to 4 MiB come from the heap again (the
#: kernels' per-row temporaries); frame-sized arrays stay mmapped, so that freeing them gives the memory back. A
#: 64 MiB threshold was faster still (0.77 s), but a 1.5 GB worker then stalled, paused at 80 % in unmanaged memory
#: (heap fragmentation, most likely), where with 4 MiB it finished (ad-hoc runs at 800 × 600 × 180).
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": 4 * 2**20}

#: memory a worker holds for an all-to-all rechunk's (p2p) shards in flight, outside dask's accounting ("unmanaged"
#: memory that the worker cannot spill): distributed's default of 1 GiB is a quarter of a 4 GB worker
P2P_BUFFER = "256 MiB"


def enable_compile_cache() -> Path | None:
    """Keep XLA's compiled kernels on disk between runs, for this process and the worker processes it starts.

    The folder is ``SELPATH_COMPILE_CACHE`` (``off`` disables it), else ``$XDG_CACHE_HOME/selpath/jax``
    (``~/.cache/selpath/jax``). A demultiplexing run compiles its solver once per band shape, ~4 s on a
    2-core machine (10 % of a 1600×1200 frame); from the cache the same kernels load in ~1 s. Called by the
    command line, not by the library: a program that imports selpath keeps its own JAX configuration.
    """
    setting = os.environ.get("SELPATH_COMPILE_CACHE", "")
    if setting.lower() == "off":
        return None
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    folder = Path(setting) if setting else cache_home / "selpath" / "jax"
    import jax

    settings = {"jax_compilation_cache_dir": str(folder), "jax_persistent_cache_min_compile_time_secs": 0.0}
    for name, value in settings.items():
        jax.config.update(name, value)
        os.environ[name.upper()] = str(value)  # inherited by dask worker processes
    return folder


class _RichCallback(Callback):
    """A rich progress bar over the tasks of a local-scheduler compute."""

    def __init__(self, progress: Progress, description: str):
        super().__init__()
        self._progress, self._description, self._task = progress, description, None

    def _start_state(self, dsk, state):
        total = sum(len(state[k]) for k in ("ready", "waiting", "running", "finished"))
        self._task = self._progress.add_task(self._description, total=total)

    def _posttask(self, key, result, dsk, state, worker_id):
        self._progress.advance(self._task)


@contextmanager
def scheduler_session(scheduler: str, *, n_workers: int | None = None) -> Iterator[Any]:
    """Yield a ``distributed.Client`` for distributed schedulers, else None (local schedulers)."""
    address = os.environ.get("DASK_SCHEDULER_ADDRESS") or (scheduler if scheduler.startswith("tcp://") else None)
    if address:
        with _connected(address) as client:
            yield client
    elif scheduler == "processes":
        with local_cluster(n_workers or min(2, os.cpu_count() or 1)) as client:
            yield client
    else:
        yield None


@contextmanager
def _connected(address: str) -> Iterator[Any]:
    """A ``distributed.Client`` of the scheduler at ``address``; an EnvironmentFault naming it if none answers (within
    distributed's connect timeout, ``distributed.comm.timeouts.connect``, 30 s by default)."""
    from distributed import Client

    try:
        client = Client(address)
    except (OSError, TimeoutError) as exc:  # refused, unreachable or silent: the environment, not a bug
        where = "DASK_SCHEDULER_ADDRESS" if os.environ.get("DASK_SCHEDULER_ADDRESS") else "the workflow's scheduler"
        raise EnvironmentFault(Problem(
            f"no dask scheduler answers at {address} ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})",
            where=where, fix="start it (`dask scheduler`, and workers with `dask worker ADDRESS`), check the host and "
            "port, or run here with `--scheduler threads` (or `scheduler: threads` in the workflow)")) from exc
    with client:
        yield client


@contextmanager
def local_cluster(n_workers: int, *, memory_limit: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` on a fresh ``LocalCluster`` of ``n_workers`` single-threaded worker processes
    (:data:`WORKER_ENV`, :data:`WORKER_MALLOC`), each with ``memory_limit`` (None: distributed's share of the
    machine)."""
    from distributed import Client, LocalCluster

    limit = {} if memory_limit is None else {"memory_limit": memory_limit}
    settings = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_MALLOC.items()}
    settings["distributed.p2p.comm.buffer"] = P2P_BUFFER
    with dask.config.set(settings), LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                                 dashboard_address=None, env=WORKER_ENV, **limit) as cluster, \
            Client(cluster) as client:
        yield client


@contextmanager
def blas_on_one_thread() -> Iterator[None]:
    """The BLAS pool (numpy's OpenBLAS) at one thread while a local dask scheduler computes (threadpoolctl; the limit
    before is restored on exit): dask and XLA own the parallelism, as :data:`WORKER_ENV` says for worker processes.
    Otherwise OpenBLAS wakes a pool per call, whose threads then spin-wait on the cores that the other tasks and XLA's
    own threads need: with them, ``benchmarks/demux_throughput.py``'s K = 128 frame took 85.2–86.1 s store to store,
    with one thread 71.6–74.7 (the solver's host steps, its exact finish and certificates, are small batched numpy),
    and a single thread calling the solver saw its next call's start 1.3 µs/px slower; the tomography demo took the
    same time either way (46.5, 48.8 against 46.3, 47.5 s) and the procam demo 73–78 against 70–71 s (2026-11-27,
    this 2-core VM). XLA's threads are its own (not a BLAS pool) and stay.

    BLAS only: for OpenBLAS built on pthreads (numpy's and scipy's wheels) the limit is process-wide, so set here,
    once around the whole compute from the thread that computes, it reaches every task (tasks that set it
    themselves would race each other); OpenMP limits, and an OpenMP-built OpenBLAS's, are per thread and would not
    reach dask's worker threads, so none is set. Two computes running at once from different threads would restore
    the limit out of order: the engine computes one output at a time."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def compute(collections: Sequence[Any], *, scheduler: str, client: Any = None, progress: bool = True,
            description: str = "computing") -> tuple:
    """Compute dask ``collections`` in one pass under ``scheduler`` (or on ``client``); on a local scheduler with
    BLAS on one thread (:func:`blas_on_one_thread`)."""
    if not collections:
        return ()
    # dask 2026.8's joint optimisation of several collections that share layers can drop a shared key
    # ("Missing dependency …" before anything runs; cf. dask/dask#12127): optimise only single outputs.
    optimize = len(collections) == 1
    if client is not None:
        futures = client.compute(list(collections), optimize_graph=optimize)
        if show_bars(progress):  # on a terminal only: in a log file its text bars are noise (49 kB against 7)
            from distributed import progress as distributed_progress

            distributed_progress(futures, notebook=False)
        return tuple(client.gather(futures))
    local = scheduler if scheduler in ("synchronous", "threads") else "threads"
    with blas_on_one_thread():
        if not progress:
            return dask.compute(*collections, scheduler=local, optimize_graph=optimize)
        # transient: a finished bar gives way to the engine's one line per output (what was written, how long)
        with Progress(*BAR_COLUMNS, TextColumn("tasks"), TimeElapsedColumn(), transient=True,
                      disable=not show_bars(True)) as bar, _RichCallback(bar, description):
            return dask.compute(*collections, scheduler=local, optimize_graph=optimize)


def scheduler_line(scheduler: str, client: Any) -> str:
    """What ran the computation, for the run's log: the local scheduler, or the cluster's address, workers and
    dashboard (``DASK_SCHEDULER_ADDRESS`` wins over the workflow's scheduler, as in :func:`scheduler_session`)."""
    if client is None:
        return f"scheduler: {scheduler} (this process)"
    info = client.scheduler_info()
    workers = len(info.get("workers", {}))
    # a scheduler without a dashboard (no bokeh, or turned off) has no link: say nothing of it
    dashboard = f"; dashboard {client.dashboard_link}" if info.get("services", {}).get("dashboard") else ""
    return f"scheduler: {info.get('address', scheduler)} ({workers} worker{'s' if workers != 1 else ''}{dashboard})"
