"""Sphinx configuration of selpath's documentation site (MyST Markdown, the PyData theme, notebooks run by MyST-NB).

Build it with ``pip install -e ".[docs]"`` then ``python -m sphinx -W -b html docs docs/_build/html`` (what
``.ci/run`` does; ``-W``: a warning fails the build). The stage, kind and workflow pages are written from the code at
every build (:func:`selpath.pipeline.reference.write_pages`, into ``docs/generated/``, which git ignores), and the
notebooks under ``notebooks/`` are copied in and executed (``SELPATH_DOCS_EXECUTE=off`` skips running them, for a
quick look at the text). With ``SELPATH_DOCS_RUNS=FOLDER`` (where ``docs/run_gallery.py`` ran the shipped
workflows) the gallery shows each workflow's time, summary and figures from that run. Nothing is fetched from the
network: no intersphinx, no web fonts, no MathJax.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import selpath
from selpath.pipeline.reference import write_pages

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent

project = "selpath"
author = "the selpath developers"
copyright = "the selpath developers (BSD-3-Clause)"
release = version = selpath.__version__

extensions = ["myst_nb"]
source_suffix = {".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "**.ipynb_checkpoints"]
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3
# the project's own Markdown (format.md, results.md, the changelog) reads well on GitHub too: headings that skip a
# level there are kept, and links to files outside the site stay plain links
suppress_warnings = ["myst.header", "myst.xref_missing"]

html_theme = "pydata_sphinx_theme"
html_title = f"selpath {release}"
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version"],
}
html_show_sourcelink = False
html_context = {"default_mode": "auto"}  # (without it the theme logs a console error on a first visit)

# the notebooks: run at build time, each in its own folder for the stores its workflow writes
nb_execution_mode = "off" if os.environ.get("SELPATH_DOCS_EXECUTE") == "off" else "force"
nb_execution_timeout = 900
nb_execution_raise_on_error = True
nb_merge_streams = True


def _formats() -> dict:
    """The file formats whose reference pages are generated from their models: the simulators' scene files and the
    hardware rig files."""
    from selpath.devices.hardware import HardwareRigConfig
    from selpath.devices.procam_hardware import ProcamHardwareConfig
    from selpath.devices.sim.procam_scene import ProcamScene
    from selpath.devices.sim.scene import Scene

    units = ("Every length, angle, duration and coefficient carries its unit as text (`\"20 mm\"`, `\"45 deg\"`, "
             "`\"0.15 /mm\"`); a bare number where a unit is needed is an error naming the field. ")
    return {
        "scene": ("Tomography scene files", units + "The tomography simulator reads these files "
                  "(`workflows/scenes/*.yaml`; `acquire_tomography` with `rig: sim`, `simulate_capture`); lengths "
                  "are converted to mm, angles to degrees. A scene may instead declare `length_unit: \"1\"` (as an "
                  "import spec may): its lengths are dimensionless numbers in a unit you keep consistent (a "
                  "renderer's scene units), bare or in `1`, its coefficients per that unit (bare or `/1`), and its "
                  "captures record "
                  "`length_unit: \"1\"`. The shipped `gelatin-bin.yaml` is an example.", Scene),
        "procam-scene": ("Projector–camera scene files", units + "The projector–camera simulator reads these files "
                         "(`acquire_plane_to_ray` and the other procam acquisitions with `rig: sim`); the shipped "
                         "`book-candle-mirrorball.yaml` is an example.", ProcamScene),
        "tomography-rig": ("Tomography rig files", "`acquire_tomography` with `rig: hardware` reads this file: the "
                           "rotary stage, the camera and the geometry every capture records "
                           "([devices](../../devices.md)).", HardwareRigConfig),
        "procam-rig": ("Projector–camera rig files", "The procam acquisitions with `rig: hardware` read this file: "
                       "the sync controller, the camera and the scan timing ([devices](../../devices.md)).",
                       ProcamHardwareConfig),
    }


def _generate(app) -> None:
    """Write the generated pages and copy the notebooks in, before Sphinx reads the sources."""
    runs = os.environ.get("SELPATH_DOCS_RUNS")
    write_pages(DOCS / "generated", runs=Path(runs) if runs else None, formats=_formats())
    target = DOCS / "generated" / "notebooks"
    target.mkdir(parents=True, exist_ok=True)
    sources = sorted((ROOT / "notebooks").glob("*.ipynb"))
    for notebook in sources:
        if not (target / notebook.name).is_file() or (target / notebook.name).read_bytes() != notebook.read_bytes():
            shutil.copyfile(notebook, target / notebook.name)
    for stale in set(target.glob("*.ipynb")) - {target / n.name for n in sources}:  # a notebook renamed or removed
        stale.unlink()
    os.environ.setdefault("SELPATH_DEMO", str(DOCS / "_build" / "notebook-runs"))


def setup(app):
    app.connect("builder-inited", _generate)
    return {"parallel_read_safe": True}
