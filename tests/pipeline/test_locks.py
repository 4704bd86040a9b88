"""One writer per store: a live owner is named, a dead one's lock is taken over, two runs at once never crash."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import pytest

from selpath.pipeline import StoreError, load_workflow, open_store, run_workflow
from selpath.pipeline.locks import lock_path, store_lock

HOLD = textwrap.dedent("""\
    import sys, time
    from selpath.pipeline.locks import store_lock
    with store_lock(sys.argv[1], purpose="holding it for a test"):
        print("locked", flush=True)
        time.sleep(60)
    """)


@pytest.fixture
def holder(tmp_path):
    """Another process holding the lock of tmp_path/out/capture.zarr."""
    store = tmp_path / "out" / "capture.zarr"
    process = subprocess.Popen([sys.executable, "-c", HOLD, str(store)], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "locked"
    yield store, process
    process.kill()
    process.wait()


def test_a_store_locked_by_a_live_process_is_refused_naming_it(holder, small_workflow):
    store, process = holder
    expected = (rf"capture.zarr: another selpath process {process.pid} on {socket.gethostname()} \(holding it for a "
                r"test, since .*\) is writing this store \(fix: wait for it to finish or stop it")
    with pytest.raises(StoreError, match=expected):
        run_workflow(load_workflow(small_workflow), progress=False)
    assert not (small_workflow.parent / "out" / "absorption.zarr").exists()  # nothing ran


def test_the_lock_of_a_dead_process_is_taken_over(holder, small_workflow):
    store, process = holder
    process.kill()
    process.wait()
    assert json.loads(lock_path(store).read_text())["pid"] == process.pid  # its lock file is still there
    run_workflow(load_workflow(small_workflow), progress=False)
    assert open_store(store)["target"].shape == (8, 3, 48)
    assert not lock_path(store).exists()  # released (and removed) at the end of the run


def test_a_lock_is_reentrant_within_a_process(tmp_path):
    store = tmp_path / "s.zarr"
    with store_lock(store, purpose="outer"):
        with store_lock(store, purpose="inner"):
            assert json.loads(lock_path(store).read_text())["purpose"] == "outer"
        assert lock_path(store).exists()
    assert not lock_path(store).exists()


def test_two_runs_of_one_workflow_at_once_never_crash_or_corrupt(small_workflow):
    """The reported race: two `selpath run` into one folder crashed with tracebacks and once left the capture
    unreadable. Now one of them runs, the other finds the lock (clear error) or finds everything done."""
    command = [sys.executable, "-m", "selpath", "run", str(small_workflow), "--no-progress"]
    env = {**os.environ, "COLUMNS": "200"}
    runs = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            for _ in range(2)]
    time.sleep(0.05)
    results = [(p.wait(timeout=240), p.stdout.read(), p.stderr.read()) for p in runs]
    for code, out, err in results:
        assert "Traceback" not in out + err, out + err
        assert code == 0 or (code == 2 and "is writing this store" in err), (code, out, err)
    assert any(code == 0 for code, _, _ in results)
    second = run_workflow(load_workflow(small_workflow), progress=False)
    assert second.computed() == []  # whatever ran finished both outputs completely
    assert open_store(small_workflow.parent / "out" / "absorption.zarr")["absorption"].notnull().any()
