"""Archives on object storage (#29 item 3): an S3-compatible server (moto) on 127.0.0.1, stores read lazily from it
by ``load_store`` (threads and a ``processes`` cluster), outputs written to it, credentials only from the
environment, and the integrity checks of local stores (missing chunks, changed content, owners) kept."""

from __future__ import annotations

import logging
import shutil
import textwrap

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import SpecError, StoreError, load_workflow, open_store, run_workflow, to_store
from selpath.pipeline.provenance import read_provenance, store_identity
from tests.conftest import SMALL_WORKFLOW

moto_server = pytest.importorskip("moto.server")
logging.getLogger("werkzeug").setLevel(logging.WARNING)  # the server's access log: one line per request
s3fs = pytest.importorskip("s3fs")


@pytest.fixture(scope="module")
def endpoint():
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture
def s3(endpoint, monkeypatch, request):
    """Credentials and endpoint in the environment (as a user sets them), a fresh bucket per test."""
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
    s3fs.S3FileSystem.clear_instance_cache()
    fs = s3fs.S3FileSystem()
    bucket = request.node.name.lower().replace("_", "-")[:50].strip("-")
    fs.mkdir(bucket)
    yield fs, bucket
    fs.rm(bucket, recursive=True)


def _archive(tmp_path, fs, bucket) -> str:
    """The small workflow's capture, written locally and uploaded: an archive on object storage."""
    (tmp_path / "make.yaml").write_text(SMALL_WORKFLOW)
    run_workflow(load_workflow(tmp_path / "make.yaml"), progress=False)
    fs.put(str(tmp_path / "out" / "capture.zarr"), f"{bucket}/archive/capture.zarr", recursive=True)
    return f"s3://{bucket}/archive/capture.zarr"


def _reprocess(folder, store: str, *, scheduler: str = "threads", output: str = "absorption.zarr",
               workflow: str = "reprocess") -> object:
    folder.mkdir(exist_ok=True)
    (folder / "re.yaml").write_text(textwrap.dedent(f"""\
        workflow: {workflow}
        scheduler: {scheduler}
        steps:
          - {{id: capture, stage: load_store, with: {{store: "{store}"}}}}
          - {{id: absorption, stage: absorption, with: {{capture: $capture, min_signal: 1.0}}}}
        outputs:
          absorption: {{from: absorption, store: "{output}"}}
        """))
    return run_workflow(load_workflow(folder / "re.yaml"), progress=False)


def test_an_archive_on_object_storage_is_reprocessed_as_a_local_one_is(tmp_path, s3):
    fs, bucket = s3
    url = _archive(tmp_path, fs, bucket)
    _reprocess(tmp_path / "local", str(tmp_path / "out" / "capture.zarr"))
    remote = _reprocess(tmp_path / "remote", url)
    assert remote.steps["absorption"].status == "computed"
    xr.testing.assert_identical(open_store(tmp_path / "remote" / "absorption.zarr").load(),
                                open_store(tmp_path / "local" / "absorption.zarr").load())
    # the remote capture was written by a workflow: identified by its provenance, not its URL, so the local and
    # remote runs are the same step, and a rerun reuses it
    assert store_identity(url) == store_identity(tmp_path / "out" / "capture.zarr")
    again = _reprocess(tmp_path / "remote", url)
    assert again.steps["absorption"].status == "reused"


@pytest.mark.slow  # the default job's 8 minutes; a cluster's reading is in test_engine's default tests too
def test_a_processes_cluster_reads_the_same_remote_store(tmp_path, s3):
    fs, bucket = s3
    url = _archive(tmp_path, fs, bucket)
    _reprocess(tmp_path / "threads", url)
    _reprocess(tmp_path / "processes", url, scheduler="processes")
    xr.testing.assert_identical(open_store(tmp_path / "processes" / "absorption.zarr").load(),
                                open_store(tmp_path / "threads" / "absorption.zarr").load())


def test_outputs_land_on_object_storage_and_another_workflows_store_there_is_refused(tmp_path, s3):
    fs, bucket = s3
    url = _archive(tmp_path, fs, bucket)
    out = f"s3://{bucket}/results/absorption.zarr"
    _reprocess(tmp_path / "a", url, output=out)
    written = open_store(out)
    assert read_provenance(out)["workflow"] == "reprocess" and fs.exists(f"{bucket}/results/absorption.zarr/_selpath")
    _reprocess(tmp_path / "local", url)
    xr.testing.assert_identical(written.load(), open_store(tmp_path / "local" / "absorption.zarr").load())
    assert _reprocess(tmp_path / "a", url, output=out).steps["absorption"].status == "reused"
    with pytest.raises(SpecError, match=r"holds output 'absorption' of workflow 'reprocess'"):
        _reprocess(tmp_path / "b", url, output=out, workflow="someone-else")
    fs.pipe(f"{bucket}/notes.zarr/readme.txt", b"a colleague's file")
    with pytest.raises(SpecError, match="holds objects that are not a selpath store"):
        _reprocess(tmp_path / "c", url, output=f"s3://{bucket}/notes.zarr")
    assert fs.cat(f"{bucket}/notes.zarr/readme.txt") == b"a colleague's file"


def test_credentials_in_a_workflow_file_are_refused(tmp_path, s3):
    _, bucket = s3
    for url in (f"s3://key:secret@{bucket}/capture.zarr", f"s3://{bucket}/capture.zarr?X-Amz-Signature=abc"):
        with pytest.raises(SpecError, match="credentials never go in a workflow file"):
            _reprocess(tmp_path / "x", url)


def test_a_remote_store_missing_a_chunk_or_changed_is_caught(tmp_path, s3):
    fs, bucket = s3
    data = xr.Dataset({"image": (("delay", "exposure", "row", "col"), np.ones((2, 1, 3, 4), np.float32),
                                 {"units": "counts"})},
                      coords={"delay": ("delay", [0.0, 17.0], {"units": "us"}),
                              "exposure": ("exposure", [170.0], {"units": "us"})},
                      attrs={"scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0, "saturation_counts": 4095.0,
                             "dark_level_counts": 0.0})
    to_store(data, tmp_path / "foreign.zarr", "plane_to_ray_capture")  # a store no workflow wrote
    fs.put(str(tmp_path / "foreign.zarr"), f"{bucket}/foreign.zarr", recursive=True)
    url = f"s3://{bucket}/foreign.zarr"
    before = store_identity(url)
    assert "objects_sha256" in before
    chunk = sorted(k for k in fs.find(f"{bucket}/foreign.zarr/image") if not k.endswith("zarr.json"))[0]
    fs.pipe(chunk, fs.cat(chunk)[:-1] + b"\0")  # one byte changed: a new ETag, a new identity
    assert store_identity(url) != before
    with pytest.raises(StoreError, match="checksum|crc32c|corrupt"):
        open_store(url).load()
    fs.rm(chunk)
    with pytest.raises(StoreError, match=r"chunks are missing"):
        open_store(url)
    shutil.rmtree(tmp_path / "foreign.zarr")
