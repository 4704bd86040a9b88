"""The documentation site (docs/, Sphinx with MyST): every registered stage, cube kind and shipped workflow has a
page generated from the code, each setting's row saying what the registry says, and the check .ci/docs runs on the
built site (every page in headless Chromium) catches what it must. .ci/docs itself builds the site with warnings as
errors, its notebooks executed and every shipped workflow run for the gallery."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from selpath import workflows
from selpath.pipeline.constraints import describe
from selpath.pipeline.reference import _cell, markdown, write_pages
from selpath.pipeline.registry import default_registry

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def pages(tmp_path_factory):
    folder = tmp_path_factory.mktemp("generated")
    return folder, write_pages(folder)


def test_every_stage_kind_and_shipped_workflow_has_its_page(pages):
    folder, written = pages
    registry = default_registry()
    assert {p.stem for p in (folder / "stages").glob("*.md")} == set(registry.names()) | {"index"}
    assert {p.stem for p in (folder / "kinds").glob("*.md")} == set(registry.kinds) | {"index"}
    assert {p.stem for p in (folder / "workflows").glob("*.md")} == set(workflows.names()) | {"index"}
    assert len(written) == len(registry.names()) + len(registry.kinds) + len(workflows.names()) + 3
    index = (folder / "stages" / "index.md").read_text()
    assert all(f"[`{name}`]({name}.md)" in index for name in registry.names())


def test_pages_of_what_no_longer_exists_are_removed(tmp_path):
    """A stage, kind or workflow gone since the last build (renamed, a plugin uninstalled) leaves no page behind:
    Sphinx would read it and warn that no toctree holds it. A file of another kind is left alone."""
    write_pages(tmp_path)
    (tmp_path / "stages" / "renamed_stage.md").write_text("# old")
    (tmp_path / "workflows" / "old-workflow.md").write_text("# old")
    (tmp_path / "workflows" / "figures" / "old-workflow").mkdir(parents=True)
    (tmp_path / "stages" / "notes.txt").write_text("kept")
    written = write_pages(tmp_path)
    assert not (tmp_path / "stages" / "renamed_stage.md").exists()
    assert not (tmp_path / "workflows" / "old-workflow.md").exists()
    assert not (tmp_path / "workflows" / "figures" / "old-workflow").exists()
    assert (tmp_path / "stages" / "notes.txt").exists()
    assert set(written) == set(tmp_path.rglob("*.md"))


def test_a_stage_page_says_what_the_registry_says(pages):
    """Every setting of classify_materials is a row with its type and range, its default and its description, as
    `selpath stages classify_materials` prints them; the Parameters section is not repeated below."""
    folder, _ = pages
    stage = default_registry()["classify_materials"]
    page = (folder / "stages" / "classify_materials.md").read_text()
    for name, field in stage.params.model_fields.items():
        default = "required" if field.is_required() else f"`{field.default!r}`"
        row = next(line for line in page.splitlines() if line.startswith(f"| `{name}` |"))
        assert f"| {_cell(describe(field))} | {default} |" in row, row
        assert markdown(" ".join(field.description.split()))[:40] in row
    assert "| `labels` | 'scene' \\| 'image' \\| None | `None` |" in page
    assert "| `profiles` | required |" in page and "[`material_classification`]" in page
    assert "----------" not in page and "Parameters" not in page


def test_a_workflow_page_cites_the_thesis_and_links_each_step_to_its_stage(pages):
    folder, _ = pages
    page = (folder / "workflows" / "procam-vein.md").read_text()
    assert "**Thesis** §5.4.7, Fig. 49" in page
    assert "| `choice` | [`choose_delay`](../stages/choose_delay.md) |" in page
    assert workflows.path("procam-vein").read_text().rstrip() in page


def test_docstring_markup_becomes_markdown():
    assert markdown(":func:`~selpath.a.b` and :class:`x.Y` and ``z``") == "`b` and `x.Y` and `z`"


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium here (.ci/run installs Debian's chromium)")
def test_the_site_check_names_console_errors_and_requests_off_the_machine(tmp_path, monkeypatch):
    """docs/check_site.py, which .ci/docs runs on the built site: a clean page passes; a page whose script throws, one
    that logs an error and one that asks for a file off the machine are each named with what went wrong."""
    sys.path.insert(0, str(ROOT / "docs"))
    try:
        from check_site import problems
    finally:
        sys.path.remove(str(ROOT / "docs"))
    (tmp_path / "clean.html").write_text("<html><body><p>fine</p></body></html>")
    (tmp_path / "throws.html").write_text("<html><body><script>undefined_name()</script></body></html>")
    (tmp_path / "logs.html").write_text("<html><body><script>console.error('broken')</script></body></html>")
    (tmp_path / "fetches.html").write_text("<html><head><link rel=stylesheet href='https://example.invalid/a.css'>"
                                           "</head><body></body></html>")
    (tmp_path / "_static").mkdir()
    (tmp_path / "_static" / "macros.html").write_text("<script>undefined_name()</script>")  # not a page: skipped
    monkeypatch.chdir(tmp_path.parent)  # as .ci/docs gives it: a path relative to the working folder
    found = problems(Path(tmp_path.name), CHROMIUM)
    assert set(found) == {"throws.html", "logs.html", "fetches.html"}, found
    assert "undefined_name" in " ".join(found["throws.html"]) and "broken" in " ".join(found["logs.html"])
    assert "request off the machine: https://example.invalid/a.css" in found["fetches.html"]


def test_the_site_check_names_every_broken_link_between_pages_and_follows_none_off_the_site(tmp_path):
    """docs/check_site.py's link check (offline: nothing fetched): a link to a page or anchor that exists passes, a
    missing page, a missing anchor (on another page or its own) and a file outside the site are named; links off
    the site are counted, not followed."""
    sys.path.insert(0, str(ROOT / "docs"))
    try:
        from check_site import broken_links
    finally:
        sys.path.remove(str(ROOT / "docs"))
    (tmp_path / "sub").mkdir()
    (tmp_path / "index.html").write_text(
        "<html><body><h1 id='top'>x</h1><a href='sub/page.html#here'>ok</a> <a href='#top'>ok</a>"
        "<a href='sub/'>ok, a folder's index</a><a href='https://example.invalid/'>off</a>"
        "<a href='mailto:a@b.invalid'>off</a><a href='sub/gone.html'>gone</a><a href='#nowhere'>own</a></body></html>")
    (tmp_path / "sub" / "index.html").write_text("<html><body><img src='../_static/logo.png'></body></html>")
    (tmp_path / "sub" / "page.html").write_text(
        "<html><body><section id='here'><a name='old'></a><a href='../index.html#missing'>x</a>"
        "<a href='../index.html#top'>ok</a><a href='#old'>ok</a><a href='../../outside.html'>out</a></section>"
        "</body></html>")
    (tmp_path.parent / "outside.html").write_text("<html></html>")
    found, outside = broken_links(tmp_path)
    assert found == {
        "index.html": ["link sub/gone.html: no such file", "link #nowhere: no anchor #nowhere there"],
        "sub/index.html": ["link ../_static/logo.png: no such file"],
        "sub/page.html": ["link ../index.html#missing: no anchor #missing there",
                          "link ../../outside.html: no such file"],
    }, found
    assert outside == 2


def test_the_project_files_agree_with_the_package():
    """CITATION.cff (validated against the CFF 1.2.0 schema with cffconvert 2.0 when written) names the package's
    version and licence; LICENSE is the BSD-3-Clause text pyproject.toml declares."""
    import tomllib

    import yaml

    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert citation["cff-version"] == "1.2.0" and citation["title"].startswith("selpath")
    assert str(citation["version"]) == project["version"] and citation["license"] == project["license"]["text"]
    assert all(ref["authors"] and ref["title"] for ref in citation["references"])
    assert "Redistribution and use in source and binary forms" in (ROOT / "LICENSE").read_text()


def test_a_file_format_page_gives_every_field_its_unit_and_every_model_its_section():
    """The tomography scene file's page (docs/conf.py generates it from the model selpath.devices.sim.scene.Scene):
    every model reachable from Scene has its section, a length field its units and example, a default its canonical
    unit."""
    import typing

    import pydantic

    from selpath.devices.sim.scene import Scene
    from selpath.pipeline.reference import model_page

    page = model_page("Scene files", "intro", Scene)
    reachable, stack = set(), [Scene]
    while stack:  # every model class a field's annotation names, however nested (brute force over the annotations)
        model = stack.pop()
        if model in reachable:
            continue
        reachable.add(model)
        for field in model.model_fields.values():
            todo = [field.annotation]
            while todo:
                a = todo.pop()
                if isinstance(a, type) and issubclass(a, pydantic.BaseModel):
                    stack.append(a)
                todo.extend(typing.get_args(a))
    assert {line[3:] for line in page.splitlines() if line.startswith("## ")} == {m.__name__ for m in reachable}
    light = page[page.index("## Light"):].split("## ", 2)[1]
    assert "| `distance` | a length (`20 mm`; m, cm, mm, um) > 0 | required |" in light
    assert "| `height` | a length (`20 mm`; m, cm, mm, um) | `0 mm` |" in light
    assert "[SceneObject](#sceneobject)" in page and "| `sensor` | [Sensor](#sensor) | its defaults |" in page
