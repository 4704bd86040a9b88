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


def _generate(app) -> None:
    """Write the generated pages and copy the notebooks in, before Sphinx reads the sources."""
    runs = os.environ.get("SELPATH_DOCS_RUNS")
    write_pages(DOCS / "generated", runs=Path(runs) if runs else None)
    target = DOCS / "generated" / "notebooks"
    target.mkdir(parents=True, exist_ok=True)
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        if not (target / notebook.name).is_file() or (target / notebook.name).read_bytes() != notebook.read_bytes():
            shutil.copyfile(notebook, target / notebook.name)
    os.environ.setdefault("SELPATH_DEMO", str(DOCS / "_build" / "notebook-runs"))


def setup(app):
    app.connect("builder-inited", _generate)
    return {"parallel_read_safe": True}
