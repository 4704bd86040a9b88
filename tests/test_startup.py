"""What starting selpath imports (#57): ``import selpath`` and ``selpath --version``/``--help`` import no labelled-array
or solver library; the ``.selpath`` accessor is there whenever xarray is, whichever came first; ``validate`` imports
only the modules of the stages a workflow names (the manifest), and a manifest that lies costs time, never a wrong
answer. Each check runs in a fresh interpreter (what is imported is the assertion; times are in
benchmarks/cli_startup.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap

import pytest

from selpath import workflows
from selpath.pipeline import manifest
from selpath.pipeline.registry import ENTRY_POINT_GROUP, default_registry

# (pydantic is not among them: typer imports it to render a command's help)
HEAVY = ("xarray", "dask", "zarr", "jax", "numpy", "scipy", "matplotlib", "sklearn", "cv2")


def _python(code: str, **env: str) -> dict:
    """Run ``code`` in a fresh interpreter; it prints one JSON line, returned."""
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          env={**os.environ, **env}, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _heavy_imported() -> str:
    return f"sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))"


def _cli(argv: list[str], **env: str) -> dict:
    """``selpath *argv`` in a fresh interpreter: its output, exit code, the heavy libraries and the stage modules
    (not packages: those are light, as tested here) it imported."""
    return _python(f"""
        import contextlib, io, json, sys
        sys.argv = ["selpath", *{argv!r}]
        from selpath.pipeline.cli import main
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                main()
            except SystemExit as exit:
                code = exit.code
        print(json.dumps({{"heavy": {_heavy_imported()}, "out": out.getvalue(), "code": code,
                           "stages": sorted(m for m, module in sys.modules.items() if m.startswith("selpath.stages.")
                                            and not hasattr(module, "__path__"))}}))
        """, **env)


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["validate", "--help"], ["nonsense"]])
def test_the_command_line_answers_without_heavy_imports(argv):
    seen = _cli(argv)
    assert seen["heavy"] == []
    if argv == ["--version"]:
        from selpath import __version__

        assert seen["out"].strip() == f"selpath {__version__}" and seen["code"] == 0
    elif argv == ["nonsense"]:
        assert seen["code"] == 2 and "nonsense" in seen["out"]
    else:
        assert seen["code"] == 0 and "validate" in seen["out"]


@pytest.mark.parametrize("order", ["selpath first", "xarray first", "a stage module first"])
def test_the_accessor_is_there_whenever_xarray_is(order):
    first = {"selpath first": "import selpath", "xarray first": "import xarray, selpath",
             "a stage module first": "import selpath.stages.tomography.calibrate"}[order]
    seen = _python(f"""
        import json, sys
        {first}
        heavy = {_heavy_imported()}
        import numpy as np, xarray as xr
        T = xr.Dataset({{"transport": (("offset", "row", "col"), np.ones((3, 4, 5)))}}, coords={{"offset": [-1, 0, 1]}})
        print(json.dumps({{"heavy": heavy, "pixel": T.selpath.pixel(x=0.5, y=1.0),
                           "array": type(T.transport.selpath).__name__}}))
        """)
    assert seen["pixel"] == [3, 2] and seen["array"] == "SelpathArray"
    if order == "selpath first":
        assert seen["heavy"] == []


def test_every_lazy_name_resolves():
    """lazy_loader's EAGER_IMPORT imports every name the stubs list (``selpath/__init__.pyi`` …) at once: a name
    listed but missing fails here, not in a user's notebook (or an editor's completion)."""
    seen = _python("""
        import json, selpath, selpath.pipeline, selpath.stages
        names = {m.__name__: [n for n in m.__all__ if getattr(m, n, None) is None] for m in
                 (selpath, selpath.pipeline, selpath.stages)}
        print(json.dumps({"missing": names, "dir": set(selpath.__all__) <= set(dir(selpath)),
                          "run": callable(selpath.run), "stage": selpath.stage.__module__}))
        """, EAGER_IMPORT="1")
    assert seen["missing"] == {"selpath": [], "selpath.pipeline": [], "selpath.stages": []}
    assert seen["dir"] and seen["run"] and seen["stage"] == "selpath.pipeline.registry"


def _validate_imports(path) -> dict:
    return _python(f"""
        import json, sys
        from selpath.pipeline.spec import load_workflow
        workflow = load_workflow({str(path)!r})
        print(json.dumps({{"modules": sorted(m for m in sys.modules if m.startswith("selpath.stages.")),
                           "stages": sorted(s.stage.name for s in workflow.steps.values()),
                           "heavy": {_heavy_imported()}, "dask_array": "dask.array" in sys.modules}}))
        """)


def test_validation_imports_only_the_stages_a_workflow_names(tmp_path, monkeypatch):
    monkeypatch.setenv("SELPATH_MANIFEST_CACHE", str(tmp_path / "manifests"))
    shipped = workflows.path("tomography-sim")
    # validated from a copy: outputs already written beside the shipped file (a run in this checkout) are opened to
    # check that they are selpath stores, which imports the store library
    (tmp_path / "scenes").symlink_to(shipped.parent / "scenes")  # the workflow's scene files, where it looks for them
    path = tmp_path / shipped.name
    path.write_text(shipped.read_text())
    cold = _validate_imports(path)  # no manifest yet: every installed stage module, and the manifest is written
    assert "selpath.stages.procam.demux" in cold["modules"]
    assert list((tmp_path / "manifests").glob(f"{ENTRY_POINT_GROUP}-*.json"))
    warm = _validate_imports(path)
    assert warm["stages"] == cold["stages"]
    assert "selpath.stages.procam.demux" not in warm["modules"]
    assert "selpath.stages.tomography.reconstruct" in warm["modules"]
    assert not any(m.startswith("selpath.stages.procam.") for m in warm["modules"])
    # its stages import their solvers (JAX), matplotlib, scikit-image, the store library and dask.array when they
    # compute, draw and write, not to be validated (xarray, and the dask it brings, stay: stages are written on it)
    assert set(warm["heavy"]) <= {"xarray", "dask", "numpy"} and not warm["dask_array"], warm["heavy"]
    # an output that declares a kind another module declares: checked against the manifest's kinds, none imported
    text = path.read_text().replace("absorption: {from: absorption, store: out/gelatin-bin/absorption.zarr}",
                                    "absorption: {from: absorption, store: out/absorption.zarr, kind: absorption}")
    typed = tmp_path / "typed.yaml"
    typed.write_text(text.replace("kind: absorption}", "kind: delay_profiles}"))  # known (procam), if not apt
    declared = _validate_imports(typed)
    assert not any(m.startswith("selpath.stages.procam.") for m in declared["modules"]), declared["modules"]
    typed.write_text(text.replace("kind: absorption}", "kind: delay_profile}"))
    with pytest.raises(AssertionError, match="did you mean 'delay_profiles'"):
        _validate_imports(typed)


def test_validating_the_shipped_workflows_imports_no_solver(tmp_path, monkeypatch):
    """The demultiplexer's stages take their defaults from a module without JAX; the stages and acquisition devices
    import JAX, scipy, scikit-image, OpenCV, the store library and dask.array when they compute or acquire. So reading
    every shipped workflow imports none of them (benchmarks/cli_startup.py times it). ``procam-materials-apply`` is
    read last: it fails, for it reads a classifier store not made here, and its ``load_store`` step imports the store
    library (zarr) to open the store it reads, so zarr is allowed there alone. The workflows are read from a copy,
    where no output of an earlier run lies."""
    from selpath.pipeline.registry import index

    monkeypatch.setenv("SELPATH_MANIFEST_CACHE", str(tmp_path / "manifests"))
    manifest.write(ENTRY_POINT_GROUP, index(default_registry()))
    names = [n for n in workflows.names() if n != "procam-materials-apply"]
    names.append("procam-materials-apply")  # last
    copy = tmp_path / "workflows"
    shutil.copytree(workflows.folder(), copy, ignore=shutil.ignore_patterns("out", "__pycache__", "*.py"))
    seen = _python(f"""
        import json, sys
        from selpath.pipeline.errors import SpecError
        from selpath.pipeline.spec import load_workflow
        stages, failed, folder = set(), [], {str(copy)!r}
        for name in {names!r}:
            try:
                stages |= {{s.stage.name for s in load_workflow(f"{{folder}}/{{name}}.yaml").steps.values()}}
            except SpecError:  # a workflow that reads a store the user makes first
                failed.append(name)
            heavy = {{m.split(".")[0] for m in sys.modules}} & {{"jax", "zarr", "scipy", "skimage", "cv2",
                                                            "matplotlib", "sklearn", "optimistix"}}
            if heavy or "dask.array" in sys.modules:
                break
        print(json.dumps({{"heavy": sorted(heavy), "dask_array": "dask.array" in sys.modules, "last": name,
                           "stages": sorted(stages), "failed": failed}}))
        """)
    assert {"demux_plane_to_ray", "acquire_plane_to_ray", "calibrate_procam_stereo", "bin_sinogram",
            "reconstruct_tv", "reconstruct_scattering", "estimate_scattering"} <= set(seen["stages"])
    assert seen["failed"] == ["procam-materials-apply"]
    assert (seen["heavy"] == [] or seen["heavy"] == ["zarr"] and seen["last"] == "procam-materials-apply"
            ) and not seen["dask_array"], seen


def test_the_demux_defaults_are_the_solvers(monkeypatch):
    """One set of numbers: the stages' defaults (read without JAX) are the solver's class defaults."""
    import inspect

    from selpath.stages.procam import _demux_settings as defaults
    from selpath.stages.procam.demux import demux_plane_to_ray
    from selpath.stages.procam.solver import DemuxADMM

    signature = inspect.signature(demux_plane_to_ray).parameters
    for name in ("tol", "gap_tol", "finish_rounds", "dual_steps", "max_iter", "polish_iter", "polish_rounds"):
        assert signature[name].default == getattr(DemuxADMM, f"DEFAULT_{name.upper()}") == getattr(defaults,
                                                                                              name.upper())
        assert DemuxADMM.__dataclass_fields__[name].default == signature[name].default
    assert DemuxADMM.DEFAULT_MAX_GAP == defaults.MAX_GAP and DemuxADMM().max_gap == defaults.MAX_GAP


def test_a_manifest_that_lies_costs_time_never_an_answer(tmp_path, monkeypatch, small_workflow):
    """A manifest naming the wrong module, or missing a stage: the full registry is consulted and the workflow
    validates as it would have; an unknown stage still gets its did-you-mean."""
    monkeypatch.setenv("SELPATH_MANIFEST_CACHE", str(tmp_path))
    registry = default_registry()
    wrong = {s.name: {"module": "selpath.stages.io", "summary": "", "kinds": []} for s in registry}
    manifest.write(ENTRY_POINT_GROUP, {"stages": wrong, "kinds": {}})  # every stage said to be in the wrong module
    assert manifest.read(ENTRY_POINT_GROUP)["stages"]["absorption"]["module"] == "selpath.stages.io"
    from selpath.pipeline.spec import load_workflow

    workflow = load_workflow(small_workflow)
    assert workflow.steps["absorption"].stage is registry["absorption"]
    calibrate = {"module": "selpath.stages.tomography.calibrate", "summary": "", "kinds": []}
    manifest.write(ENTRY_POINT_GROUP, {"stages": {"absorption": calibrate}, "kinds": {}})  # the other stage missing
    assert load_workflow(small_workflow).steps["capture"].stage is registry["simulate_parallel_capture"]
    text = small_workflow.read_text().replace("stage: absorption", "stage: absorptoin")
    with pytest.raises(Exception, match="did you mean 'absorption'"):
        load_workflow(text, source="typo.yaml")


def test_the_manifest_key_changes_when_a_stage_module_changes(tmp_path, monkeypatch):
    """Editing a stage module (its size or time) gives a new key, so its manifest is made again."""
    module = tmp_path / "selpath_key_probe.py"
    module.write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))

    class Point:
        name, value, dist = "probe", "selpath_key_probe", None

    monkeypatch.setattr(manifest, "entry_points", lambda group: [Point()])
    before = manifest.key("probe-group")
    assert manifest.key("probe-group") == before
    module.write_text("X = 22\n")
    assert manifest.key("probe-group") != before
    monkeypatch.setenv("SELPATH_MANIFEST_CACHE", "off")
    manifest.write("probe-group", {"stages": {}, "kinds": {}})
    assert manifest.read("probe-group") is None


@pytest.mark.parametrize("argv", [["stages"], ["kinds"]])
def test_listing_stages_and_kinds_imports_none_of_them(argv):
    """With the installation's manifest kept, ``selpath stages`` and ``selpath kinds`` list every stage and kind from
    it: the same names, summaries and makers as the registry, and no stage module, xarray or JAX imported."""
    from selpath.pipeline.registry import index

    registry = default_registry()
    manifest.write(ENTRY_POINT_GROUP, index(registry))
    seen = _cli(argv, COLUMNS="400")
    assert seen["heavy"] == [] and seen["stages"] == []
    if argv == ["stages"]:  # piped: one plain line a stage
        lines = [line.split("\t") for line in seen["out"].splitlines()]
        assert [line[0] for line in lines] == registry.names()
        assert lines[0][2] == index(registry)["stages"][lines[0][0]]["summary"]
    elif argv == ["kinds"]:
        rows = {line.split("\t")[0]: line.split("\t")[1:] for line in seen["out"].splitlines()}
        assert rows == {name: [", ".join(sorted(registry.makers(name))), kind.description]
                        for name, kind in registry.kinds.items()}


@pytest.mark.slow  # the default job's 8 minutes (three commands, one importing every stage)
def test_a_name_the_manifest_lacks_is_asked_of_every_stage():
    """A manifest is a hint: a stage name it lacks is looked up among every installed stage before it is called
    unknown (with the nearest names), and one the registry has is shown even when the manifest lacks it."""
    from selpath.pipeline.registry import index

    registry = default_registry()
    manifest.write(ENTRY_POINT_GROUP, index(registry))
    typo = _cli(["stages", "absorptoin"])
    assert typo["code"] == 2 and "did you mean 'absorption'?" in typo["out"]
    partial = index(registry)
    del partial["stages"]["absorption"], partial["kinds"]["absorption"]
    manifest.write(ENTRY_POINT_GROUP, partial)
    for argv in (["stages", "absorption"], ["kinds", "absorption"]):
        shown = _cli(argv, COLUMNS="200")
        assert shown["code"] == 0 and "absorption" in shown["out"] and "unknown" not in shown["out"], shown["out"]
    manifest.write(ENTRY_POINT_GROUP, index(registry))


def test_the_accessor_hook_survives_a_probe_and_a_shared_loader(tmp_path):
    """``importlib.util.find_spec("xarray")`` before the import leaves the hook in place; a loader that loads many
    modules (a zip importer) runs the callback for xarray alone, after xarray has run, and loads the others as it
    would have."""
    import zipfile

    probed = _python("""
        import importlib.util, json, selpath
        importlib.util.find_spec("xarray")
        import xarray as xr
        print(json.dumps({"accessor": hasattr(xr.Dataset, "selpath")}))
        """)
    assert probed["accessor"]
    archive = tmp_path / "lib.zip"
    with zipfile.ZipFile(archive, "w") as zipped:  # a stand-in xarray that imports a sibling from the same zip
        zipped.writestr("xarray.py", "import sibling\nclass Dataset: pass\nclass DataArray: pass\n"
                                     "def register_dataset_accessor(name):\n"
                                     "    return lambda cls: setattr(Dataset, name, cls) or cls\n"
                                     "register_dataarray_accessor = register_dataset_accessor\n")
        zipped.writestr("sibling.py", "VALUE = 1\n")
    zipped_run = _python(f"""
        import json, sys
        sys.path.insert(0, {str(archive)!r})
        import selpath, xarray, sibling
        print(json.dumps({{"accessor": hasattr(xarray.Dataset, "selpath"), "sibling": sibling.VALUE}}))
        """)
    assert zipped_run == {"accessor": True, "sibling": 1}


def test_import_selpath_keeps_its_subpackages_as_attributes():
    """``import selpath`` then ``selpath.pipeline.open_store`` or ``selpath.pipeline.integrity`` (docs/format.md), as
    before the names became lazy; still nothing heavy until one is used."""
    seen = _python(f"""
        import json, sys, selpath
        heavy = {_heavy_imported()}
        names = [selpath.pipeline.open_store.__module__, selpath.pipeline.integrity.__name__,
                 selpath.stages.tomography.__name__, selpath.pipeline.errors.StageError.__name__]
        print(json.dumps({{"heavy": heavy, "names": names, "all": "pipeline" in selpath.__all__}}))
        """)
    assert seen["heavy"] == [] and not seen["all"]
    assert seen["names"] == ["selpath.pipeline.store", "selpath.pipeline.integrity", "selpath.stages.tomography",
                             "StageError"]


def test_no_home_or_a_malformed_manifest_is_no_cache(tmp_path, monkeypatch):
    """Without a home folder (no HOME, no passwd entry) there is no cache and validation still works; a manifest
    edited by hand into another shape is not read."""
    from pathlib import Path

    monkeypatch.delenv("SELPATH_MANIFEST_CACHE")
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setattr(Path, "home", classmethod(lambda cls: (_ for _ in ()).throw(RuntimeError("no home"))))
    assert manifest.folder() is None and manifest.read(ENTRY_POINT_GROUP) is None
    manifest.write(ENTRY_POINT_GROUP, {"stages": {}, "kinds": {}})  # nothing happens
    from selpath.pipeline.registry import registry_for

    assert "absorption" in registry_for(["absorption"])
    monkeypatch.setenv("SELPATH_MANIFEST_CACHE", str(tmp_path))
    manifest.write(ENTRY_POINT_GROUP, {"stages": {"x": {"module": "m", "summary": "", "kinds": []}}, "kinds": {}})
    assert manifest.read(ENTRY_POINT_GROUP) is not None
    (path,) = tmp_path.glob("*.json")
    path.write_text(json.dumps({"stages": {"x": {"module": 3}}, "kinds": {}}))
    assert manifest.read(ENTRY_POINT_GROUP) is None
