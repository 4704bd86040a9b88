"""Computing: the command line's compile cache (compiled kernels land in the chosen folder, `off` turns it off), and
the worker processes of a local cluster."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
from pipeline.compute import enable_compile_cache
folder = enable_compile_cache()
import jax, jax.numpy as jnp
jax.jit(lambda x: jnp.cumsum(x * 2.0 + 1.0))(jnp.ones(7)).block_until_ready()
print(folder)
"""


@pytest.mark.parametrize("setting", ["folder", "off"])
def test_compile_cache_writes_to_its_folder_or_nowhere(tmp_path, setting):
    folder = tmp_path / "cache"
    env = os.environ | {"SELPATH_COMPILE_CACHE": str(folder) if setting == "folder" else "off",
                        "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True)
    if setting == "folder":
        assert out.stdout.strip() == str(folder) and any(folder.iterdir())  # the kernel is cached there
    else:
        assert out.stdout.strip() == "None" and not folder.exists()
    assert not (tmp_path / "xdg").exists()  # never the default folder when one is named or it is off


def test_cluster_workers_start_with_the_malloc_settings_and_p2p_buffer():
    """The malloc settings reach the worker processes before they start (glibc reads them at start, so they must go
    through distributed's pre-spawn environment, not ``env``), beside distributed's own trim threshold, and the
    workers see the smaller p2p buffer and their memory limit."""
    from pipeline.compute import P2P_BUFFER, WORKER_MALLOC, local_cluster

    def settings():
        import dask

        return ({k: v for k, v in os.environ.items() if k.startswith("MALLOC_")},
                dask.config.get("distributed.p2p.comm.buffer"))

    def limit(dask_worker):
        return dask_worker.memory_manager.memory_limit

    with local_cluster(1, memory_limit="1GB") as client:
        ((environ, buffer),) = client.run(settings).values()
        (memory,) = client.run(limit).values()
    assert environ["MALLOC_MMAP_THRESHOLD_"] == str(WORKER_MALLOC["MALLOC_MMAP_THRESHOLD_"])
    assert "MALLOC_TRIM_THRESHOLD_" in environ
    assert buffer == P2P_BUFFER and memory == 10**9


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


@pytest.mark.parametrize(("scheduler", "workers", "inside"), [("threads", 2, 1), ("threads", 1, 2),
                                                               ("synchronous", 2, 2)])
def test_the_threaded_scheduler_runs_blas_on_one_thread_per_task(scheduler, workers, inside):
    """Under the threaded scheduler with several threads, the tasks see BLAS pools of one thread (dask owns the
    parallelism); with one thread, or the synchronous scheduler, BLAS keeps its own; and the limits in force
    before the compute are back after it, also when a task fails."""
    import dask
    from threadpoolctl import threadpool_limits

    from pipeline.compute import compute

    if not _blas_threads():
        pytest.skip("numpy reports no BLAS pool to threadpoolctl")
    with threadpool_limits(limits=2, user_api="blas"), dask.config.set(num_workers=workers):
        if set(_blas_threads()) != {2}:
            pytest.skip("this machine's BLAS runs on one thread at most")
        seen = compute([dask.delayed(_blas_threads)()], scheduler=scheduler, progress=False)[0]
        assert set(seen) == {inside}
        assert set(_blas_threads()) == {2}

        def fail():
            raise RuntimeError("a task failed")

        with pytest.raises(RuntimeError, match="a task failed"):
            compute([dask.delayed(fail)()], scheduler=scheduler, progress=False)
        assert set(_blas_threads()) == {2}
