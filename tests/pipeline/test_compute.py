"""Computing: the command line's compile cache (compiled kernels land in the chosen folder, `off` turns it off), and
the worker processes of a local cluster."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
from selpath.pipeline.compute import enable_compile_cache
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


def test_the_tests_and_the_commands_they_start_keep_their_compiled_kernels():
    """tests/conftest.py points JAX's persistent compilation cache at one folder (pytest's cache by default), every
    kernel kept, for the test processes and every command they start: a started command's JAX has that folder, and
    the kernel it compiles lands there."""
    from pathlib import Path

    if "JAX_COMPILATION_CACHE_DIR" not in os.environ or os.environ.get("SELPATH_TEST_COMPILE_CACHE", "") == "off":
        pytest.skip("no test compile cache (off, no pytest cache, or the user's JAX_COMPILATION_CACHE_DIR)")
    folder = Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    unique = float(int.from_bytes(os.urandom(4), "little"))  # a constant in the kernel: a key no run made before
    script = ("import jax, jax.numpy as jnp; jax.jit(lambda x: x * " + repr(unique) + " + 1.0)(jnp.ones(3))"
              ".block_until_ready(); c = jax.config; "
              "print(c.jax_compilation_cache_dir, c.jax_persistent_cache_min_compile_time_secs)")
    done = subprocess.run([sys.executable, "-c", script], env=os.environ | {"SELPATH_COMPILE_CACHE": "off"},
                          capture_output=True, text=True, check=True)
    where, least = done.stdout.split()
    assert Path(where) == folder and float(least) == 0.0
    assert any(folder.iterdir())


def test_cluster_workers_start_with_the_malloc_settings_and_p2p_buffer():
    """The malloc settings reach the worker processes before they start (glibc reads them at start, so they must go
    through distributed's pre-spawn environment, not ``env``), beside distributed's own trim threshold, and the
    workers see the smaller p2p buffer and their memory limit."""
    from selpath.pipeline.compute import P2P_BUFFER, WORKER_MALLOC, local_cluster

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


BLAS_SCRIPT = """
import json, sys
import dask, numpy
from threadpoolctl import threadpool_info, threadpool_limits
from selpath.pipeline.compute import compute

def blas():
    return {p["filepath"]: p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}

def fail():
    raise RuntimeError("a task failed")

scheduler, workers = sys.argv[1], int(sys.argv[2])
with threadpool_limits(limits=2, user_api="blas"), dask.config.set(num_workers=workers):
    before = blas()
    seen = compute([dask.delayed(blas)()], scheduler=scheduler, progress=False)[0]
    after = blas()
    try:
        compute([dask.delayed(fail)()], scheduler=scheduler, progress=False)
    except RuntimeError:
        pass
    print(json.dumps({"before": before, "seen": seen, "after": after, "after_failure": blas()}))
"""


@pytest.mark.parametrize(("scheduler", "workers"), [("threads", 2), ("threads", 1), ("synchronous", 2)])
def test_a_local_compute_runs_blas_on_one_thread(scheduler, workers):
    """Under the local schedulers the tasks see numpy's BLAS pool at one thread (dask and XLA own the parallelism),
    and the limit in force before the compute is back after it, also when a task fails. In a fresh interpreter whose
    BLAS runs on two threads: what earlier tests of a worker process loaded or limited does not count."""
    import json

    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: BLAS runs on one thread anyway")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", BLAS_SCRIPT, scheduler, str(workers)], env=env, capture_output=True,
                         text=True, check=True)
    pools = json.loads(out.stdout.strip().splitlines()[-1])
    assert pools["before"] and set(pools["before"].values()) == {2}
    assert set(pools["seen"].values()) == {1}
    assert pools["after"] == pools["before"] == pools["after_failure"]
