"""The stage registry: entry points, signatures, duplicates."""

from __future__ import annotations

from importlib.metadata import EntryPoint

import pytest
import xarray as xr

from selpath.pipeline import SelpathError, StageRegistry, stage
from selpath.pipeline.registry import default_registry


def test_builtin_stages_come_through_the_entry_point_group():
    names = default_registry().names()
    assert {"absorption", "normalise_reference", "subtract_dark", "subtract_background", "load_store",
            "simulate_parallel_capture"} <= set(names)
    absorption = default_registry()["absorption"]
    assert absorption.inputs == ("capture", "silhouettes") and absorption.required_inputs == ("capture",)
    assert absorption.params.model_fields["min_signal"].default == 0.0
    assert "[counts]" in absorption.param_docs["min_signal"]


def _fake_entry_points(monkeypatch, tmp_path, module: str, source: str):
    (tmp_path / f"{module}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    fake = [EntryPoint(name="fake", value=module, group="selpath.stages")]
    monkeypatch.setattr("selpath.pipeline.registry.entry_points",
                        lambda group: fake if group == "selpath.stages" else [])


def test_a_plugin_registers_through_the_same_group(monkeypatch, tmp_path):
    _fake_entry_points(monkeypatch, tmp_path, "selpath_fake_plugin", (
        "import xarray as xr\nfrom selpath import stage\n"
        "@stage('brighten')\n"
        "def brighten(frames: xr.DataArray, /, *, gain: float = 2.0) -> xr.DataArray:\n"
        "    return frames * gain\n"))
    registry = StageRegistry.from_entry_points()
    assert registry.names() == ["brighten"]
    assert registry["brighten"].source == "selpath_fake_plugin:brighten"


def test_a_broken_plugin_is_named(monkeypatch, tmp_path):
    _fake_entry_points(monkeypatch, tmp_path, "selpath_broken_plugin", "raise ImportError('missing dependency foo')\n")
    with pytest.raises(SelpathError, match=r"stage plugin 'fake' \(selpath_broken_plugin\) failed to import: "
                                           r"ImportError: missing dependency foo"):
        StageRegistry.from_entry_points()


def test_duplicate_names_are_refused_naming_both():
    @stage("absorption")
    def impostor(capture: xr.Dataset, /) -> xr.Dataset:
        return capture

    registry = StageRegistry(default_registry())
    with pytest.raises(SelpathError, match=r"stage 'absorption' is registered twice: by "
                                           r"selpath.stages.tomography.calibrate:absorption and by .*impostor"):
        registry.add(impostor.__selpath_stage__)


def test_signatures_must_be_explicit_and_typed():
    with pytest.raises(SelpathError, match=r"\*args/\*\*kwargs are not allowed"):
        @stage("loose")
        def loose(data: xr.Dataset, /, **options: float) -> xr.Dataset:
            return data

    with pytest.raises(SelpathError, match=r"parameter 'gain' has no type annotation"):
        @stage("untyped")
        def untyped(data: xr.Dataset, /, *, gain=1.0) -> xr.Dataset:
            return data

    with pytest.raises(SelpathError, match=r"a data input must be annotated xr.Dataset or xr.DataArray"):
        @stage("positional_setting")
        def positional_setting(data: xr.Dataset, gain: float = 1.0) -> xr.Dataset:
            return data

    with pytest.raises(SelpathError, match=r"must be lower_snake_case"):
        stage("Bad-Name")(lambda: None)


def test_every_installed_stage_documents_every_input_and_setting():
    """`selpath stages NAME` and the workflow schema show each parameter's description: none may be blank (a
    grouped numpydoc entry, ``alpha, beta : float``, documents each name)."""
    from selpath.pipeline.registry import _param_docs, default_registry

    blank = [f"{s.name}.{n}" for s in default_registry() for n in (*s.inputs, *s.params.model_fields)
             if not s.param_docs.get(n)]
    assert blank == []
    assert _param_docs("Parameters\n----------\nalpha, beta : float\n    Weights [1].\n") == {
        "alpha": "Weights [1].", "beta": "Weights [1]."}


#: what selpath adds around the thesis's pipeline: stages with no thesis section to cite
NO_THESIS_SECTION = {"import_capture", "load_store"}


def test_every_stage_cites_its_thesis_section():
    """#56: every built-in stage's docstring ends its sections with a numpydoc References section, one line
    ``Thesis §N.N Title; §… .``; one section has one title everywhere, and where the thesis's text is beside the
    repository (``../shared/thesis.md``) each § and title is one of its headings."""
    import inspect
    import re
    from pathlib import Path

    cited, problems = {}, {}
    for s in default_registry():
        if not s.func.__module__.startswith("selpath."):
            continue
        doc = inspect.cleandoc(s.func.__doc__ or "")
        found = re.search(r"\nReferences\n-{10}\nThesis (§.+)\.$", doc)
        if s.name in NO_THESIS_SECTION:
            assert found is None, s.name
            continue
        if found is None:
            problems[s.name] = "no References section citing the thesis at the docstring's end"
            continue
        for part in found.group(1).split("; "):
            number, title = re.fullmatch(r"§([45](?:\.\d+){1,2}) (.+)", part).groups()
            if cited.setdefault(number, title) != title:
                problems[s.name] = f"§{number} titled {title!r} here, {cited[number]!r} elsewhere"
    assert not problems, problems
    thesis = Path(__file__).resolve().parents[3] / "shared" / "thesis.md"
    if thesis.is_file():
        headings = dict(re.findall(r"^###? (\d+(?:\.\d+)+) (.+?)\s*$", thesis.read_text(), re.M))
        assert {n: t for n, t in cited.items() if headings.get(n) != t} == {}


def test_every_stage_documents_what_it_returns():
    """numpydoc: every installed stage's docstring has a Returns section, ``xr.Dataset`` with a description naming
    the cube kind(s) it makes (the reference pages and ``help()`` show it; a renamed kind fails here)."""
    import inspect

    missing = {}
    for s in default_registry():
        doc = "\n" + inspect.cleandoc(s.func.__doc__ or "")
        if "\nReturns\n-------\nxr.Dataset\n    " not in doc or not s.returns:
            missing[s.name] = "no Returns section of xr.Dataset"
        elif not all(f"``{k.name}``" in s.returns for k in s.kinds):
            missing[s.name] = f"its Returns names none of {[k.name for k in s.kinds]}"
    assert not missing, missing
