"""A workflow declares its report; `selpath run --report` writes it for any workflow; the summary's numbers are
read from the written stores (checked against the same numbers computed here with numpy)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from typer.testing import CliRunner

from selpath.pipeline import SpecError, load_workflow
from selpath.pipeline.cli import app
from selpath.pipeline.report_spec import summary_fields
from selpath.pipeline.store import open_store

runner = CliRunner()

REPORT = """\
report:
  file: out/small-report.html
  summary:
    - "valid {absorption.flags.share_zero:.3%}, max A {absorption.absorption.max:.6f}, usable
      {absorption.usable_fraction:.4f}, min signal {absorption.min_signal}"
"""


def test_declared_report_fills_its_summary_from_the_stores(small_workflow):
    small_workflow.write_text(small_workflow.read_text() + REPORT)
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "300"})
    assert result.exit_code == 0, result.output
    absorption = open_store(small_workflow.parent / "out" / "absorption.zarr", keep_flags=True)
    flags, a = absorption["flags"].values, absorption["absorption"].values
    expected = (f"valid {(flags == 0).mean():.3%}, max A {np.nanmax(a):.6f}, usable "
                f"{float(absorption['usable_fraction']):.4f}, min signal 1.0")
    page = (small_workflow.parent / "out" / "small-report.html").read_text()
    assert expected in result.output.replace("\n", "") and expected in page


def test_any_workflow_gets_a_report_beside_its_first_output(small_workflow):
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"])
    assert result.exit_code == 0, result.output
    assert (small_workflow.parent / "out" / "small-absorption-report.html").is_file()
    assert not (small_workflow.parent / "small-absorption-report.html").exists()


@pytest.mark.parametrize(("section", "message"), [
    ("  file: out/r.txt\n", r"report.file: report file 'out/r.txt' must end in .html"),
    ("  file: out/absorption.zarr/r.html\n", r"report file .* lies in output 'absorption'"),
    ("  file: r.html\n  figures: [nope]\n", r"report.figures\[0\]: figure 'nope' is not an output"),
    ("  file: r.html\n  summary: ['{capture.x.median}']\n", r"unknown reduction 'median'"),
    ("  file: r.html\n  summary: ['{absorption}']\n", r"is not output.name"),
    ("  file: r.html\n  summary: ['{nope.x}']\n", r"field names 'nope', not an output"),
    ("  file: r.html\n  summary: ['{capture.x:{w}}']\n", r"a format may not hold another field"),
])
def test_a_bad_report_section_is_refused_before_anything_runs(small_workflow, section, message):
    small_workflow.write_text(small_workflow.read_text() + "report:\n" + section)
    with pytest.raises(SpecError, match=message):
        load_workflow(small_workflow)


def test_summary_fields_parse_output_name_and_reduction():
    assert summary_fields("a {x.y:.2f} b {x.z.mean:.1%} {{literal}}") == [("x", "y", None), ("x", "z", "mean")]


def test_a_summary_of_an_array_needs_a_reduction(small_workflow):
    small_workflow.write_text(small_workflow.read_text() + "report:\n  file: out/r.html\n"
                              "  summary: ['{absorption.absorption}']\n")
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "300"})
    assert result.exit_code == 2
    assert re.search(r"variable 'absorption' of output 'absorption' has dims .* needs a reduction",
                     result.output.replace("\n", ""))


@pytest.mark.parametrize(("line", "message"), [
    ("{absorption.min_signal:d}", r"summary line 0 cannot be formatted .*absorption.min_signal = 1.0 \(float\)"),
    ("{absorption.absorption.list}", r"would print [\d,]+ values \(at most 1000\)"),
    ("{absorption.min_signal.mean}", r"'min_signal' is an attr \(float\); an attr takes no reduction but size"),
    ("{absorption.nope}", r"output 'absorption' has no attr or variable 'nope'"),
])
def test_a_summary_that_cannot_be_filled_names_the_line_and_field(small_workflow, line, message):
    small_workflow.write_text(small_workflow.read_text() + f"report:\n  file: out/r.html\n  summary: ['{line}']\n")
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "400"})
    assert result.exit_code == 2, result.output
    assert re.search(message, result.output.replace("\n", "")), result.output


def test_shape_and_size_reductions(small_workflow):
    small_workflow.write_text(small_workflow.read_text() + "report:\n  file: out/r.html\n  summary: "
                              "['{absorption.absorption.shape} {absorption.flags.size} {capture.target.size}']\n")
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "300"})
    assert result.exit_code == 0, result.output
    assert "(8, 3, 48) 1152 1152" in result.output  # 8 angles (0…35 every 5°) × 3 rows × 48 columns


def test_a_default_report_name_never_leaves_the_outputs_folder(small_workflow):
    small_workflow.write_text(small_workflow.read_text().replace("workflow: small-absorption",
                                                                 "workflow: ../../up/there"))
    result = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"])
    assert result.exit_code == 0, result.output
    assert (small_workflow.parent / "out" / "up-there-report.html").is_file()


def test_a_study_table_prints_every_small_variable_with_its_units():
    """`tables:` shows a study's results as the thesis does (Table 1: a row per θ_l, a column per method and
    error); every cell is checked against the store's own values, formatted to 4 significant digits."""
    import xarray as xr

    from selpath.pipeline.report import store_tables

    rmse = np.array([[5.056e-3, 3.459e-3], [6.164e-4, 3.439e-4]])
    study = xr.Dataset(
        {"rmse": (("light_angle", "method"), rmse, {"units": "1/mm"}),
         "observed_fraction": ("light_angle", [0.5469, 0.8906], {"units": "1"}),
         "sigma": (("light_angle", "method", "y", "x"), np.zeros((2, 2, 100, 100)))},  # too large: not a column
        coords={"light_angle": ("light_angle", [0.0, 60.0], {"units": "degree"}), "method": ["fbp", "optimisation"]})
    (table,) = store_tables(study, "study")
    assert table.columns == ["light_angle [degree]", "observed_fraction", "rmse fbp [1/mm]",
                             "rmse optimisation [1/mm]"]
    assert table.rows == [["0", "0.5469", "0.005056", "0.003459"], ["60", "0.8906", "0.0006164", "0.0003439"]]


def test_the_page_explains_figures_settings_and_steps(small_workflow):
    """A page a scientist can read: the settings each step ran with (those the file sets marked), and what the run
    computed or reused with the time each step took."""
    small_workflow.write_text(small_workflow.read_text() + REPORT)
    first = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "300"})
    assert first.exit_code == 0, first.output
    page = (small_workflow.parent / "out" / "small-report.html").read_text()
    assert "<b>min_signal = 1.0</b>" in page and "min_signal_relative = 0.0" in page  # set versus default
    assert re.search(r"<td>absorption</td><td>absorption</td><td>computed</td><td>\d+\.\d s</td>", page)
    second = runner.invoke(app, ["run", str(small_workflow), "--no-progress", "--report"], env={"COLUMNS": "300"})
    page = (small_workflow.parent / "out" / "small-report.html").read_text()
    assert second.exit_code == 0 and "2 step(s) computed" not in page and "0 step(s) computed and\n2 reused" in page
