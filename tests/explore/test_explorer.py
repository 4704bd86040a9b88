"""``selpath explore`` in a real browser (Debian's headless Chromium driven by Playwright): a user's clicks and typed
values, and what the page then draws read back from its named data sources and compared with the accessor's
numbers (themselves tested against the simulator); no console errors; nothing outside the stores is served and
the stores' bytes are unchanged. Without a Chromium (``.ci/run`` installs Debian's) the browser tests skip."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import selpath
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.explore.views import TransportView, column_bin, find_stores
from selpath.stages.procam.acquire import PLANE_TO_RAY_CAPTURE
from selpath.stages.procam.demux import PLANE_TO_RAY_TRANSPORT
from selpath.stages.tomography.sinogram import SINOGRAM

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
OFFSETS = np.arange(-23, 24)
DELAYS, EXPOSURES = np.arange(-170.0, 171.0, 34.0), np.array([34.0, 85.0])
#: the bounding box of a Bokeh figure's plot frame on the page, found by its model's name (through shadow roots)
FRAME_BOX = """(name) => {
  const model = Bokeh.documents[0].get_model_by_name(name);
  const walk = (view) => { if (view.model === model) return view;
    for (const child of (view.child_views ?? [])) { const found = walk(child); if (found) return found; }
    return null; };
  for (const root of Bokeh.index.roots) { const view = walk(root); if (view) {
    const r = view.canvas_view.el.getBoundingClientRect(), b = view.frame.bbox;
    return {left: r.left + b.left, top: r.top + b.top, width: b.width, height: b.height}; } }
  return null; }"""
SOURCE = "(name) => { const d = Bokeh.documents[0].get_model_by_name(name).data; const out = {};" \
         " for (const k of Object.keys(d)) out[k] = Array.from(d[k], v => (v && v.length !== undefined) ?" \
         " Array.from(v, x => Number.isNaN(x) ? null : x) : v); return out; }"


def _scene() -> ProcamScene:
    return ProcamScene.model_validate({
        "scene": "t", "background": {"albedo": 0.3},
        "objects": [{"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.5], "y": [0.2, 0.8]},
                     "albedo": 0.9, "effects": {"subsurface": {"width": "3 px", "fraction": 0.5}}}],
        "rig": {"camera_rows": 24, "camera_cols": 32, "projector_rows": 48, "projector_cols": 32, "bits": None}})


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A transport (the simulator's truth), its capture, a sinogram with unobserved bins, as stores."""
    root = tmp_path_factory.mktemp("explore")
    s = _scene()
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, OFFSETS) for t in tr.tiles(s)], axis=-1)
    attrs = {"scan_speed_px_per_us": s.rig.scan_speed, "line_time_us": s.rig.line_time}
    transport = xr.Dataset({"transport": (("offset", "row", "col"), truth.reshape(len(OFFSETS), 24, 32))},
                           coords={"offset": ("offset", OFFSETS, {"units": "px"})},
                           attrs=attrs | {"sync_offset_us": 0.0, "projector_shape": [48, 32],
                                          "full_scale_counts": 4095.0})
    selpath.to_store(PLANE_TO_RAY_TRANSPORT.label(transport), root / "transport.zarr", "plane_to_ray_transport")
    frames = np.stack([np.stack([tr.render_frame(s, d, e) for e in EXPOSURES]) for d in DELAYS])
    capture = xr.Dataset({"image": (("delay", "exposure", "row", "col"), frames)},
                         coords={"delay": ("delay", DELAYS, {"units": "us"}),
                                 "exposure": ("exposure", EXPOSURES, {"units": "us"})},
                         attrs=attrs | {"saturation_counts": 4095.0, "dark_level_counts": 0.0})
    selpath.to_store(PLANE_TO_RAY_CAPTURE.label(capture), root / "capture.zarr", "plane_to_ray_capture")
    rng = np.random.default_rng(0)
    sinogram = xr.Dataset({"absorption": (("theta", "x"), rng.random((12, 16))),
                           "observed": (("theta", "x"), rng.random((12, 16)) > 0.25)},
                          coords={"theta": ("theta", np.arange(12) * 15.0, {"units": "degree"}),
                                  "x": ("x", np.linspace(-1, 1, 16), {"units": "mm"})},
                          attrs={"camera_model": "orthographic", "light_angle_deg": 45.0, "length_unit": "mm",
                                 "pixel_size": 0.1})
    selpath.to_store(SINOGRAM.label(sinogram), root / "sinogram.zarr", "sinogram")
    return root


def _digest(folder: Path) -> str:
    digest = hashlib.sha256()
    for file in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(file.relative_to(folder).as_posix().encode() + file.read_bytes())
    return digest.hexdigest()


def test_the_views_numbers_are_the_accessors(folder):
    """Without a browser: the preview's images are the accessor's on the full store (column bin 1 here), and the
    bin that keeps a full-size transport within the budget is 4."""
    stores = {name: selpath.open_store(path) for name, path in find_stores([folder]).items()}
    assert sorted(stores) == ["capture.zarr", "sinogram.zarr", "transport.zarr"]
    view = TransportView(stores["transport.zarr"], stores["capture.zarr"])
    t = stores["transport.zarr"]
    np.testing.assert_allclose(view.image("ideal frame", delay=-34.0, exposure=85.0),
                               t.selpath.ideal_frame(-34.0, 85.0).values, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(view.image("relit", line=20, width=4), t.selpath.relight(rows=range(20, 24)).values,
                               rtol=1e-5, atol=1e-3)
    for mode, expected in (("epipolar", t.selpath.epipolar(3)), ("non-epipolar", t.selpath.non_epipolar(3))):
        np.testing.assert_allclose(view.image(mode, band=3), expected.values, rtol=1e-5, atol=1e-3)
    assert view.delays() == (-170.0, 170.0) and view.exposures() == [34.0, 85.0]
    assert column_bin(1600, 1200, 253) == 4


def test_a_binned_preview_is_the_bins_mean_of_the_full_views(folder, monkeypatch):
    """Columns binned by 3 (a budget forced small): each view equals the mean over each bin of the full one, NaN
    cells (a rectified transport's edges) counting as 0 in both."""
    import selpath.explore.views as views

    monkeypatch.setattr(views, "PREVIEW_BYTES", 47 * 24 * 32 * 8 // 3 + 1)
    t = selpath.open_store(find_stores([folder])["transport.zarr"]).load()
    t["transport"][:, :4, 2:7] = np.nan
    view = views.TransportView(t)
    assert view.bin == 3 and view.cube.shape == (24, 47, 11)  # 32 columns: ten bins of 3, the last of 2 (padded)
    full = t.selpath.epipolar(2).values
    binned = view.image("epipolar", band=2)
    np.testing.assert_allclose(binned[:, :10], full[:, :30].reshape(24, 10, 3).mean(-1), rtol=1e-5)
    np.testing.assert_allclose(binned[:, 10], full[:, 30:].mean(-1), rtol=1e-5)


@pytest.fixture(scope="module")
def server(folder):
    if CHROMIUM is None:
        pytest.skip("no Chromium here (.ci/run installs Debian's chromium)")
    before = _digest(folder)
    process = subprocess.Popen([sys.executable, "-m", "selpath", "explore", str(folder), "--port", "0"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env={**os.environ, "COLUMNS": "200"})
    lines, url = [], None
    deadline = time.monotonic() + 90
    while url is None and time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            break
        lines.append(line)
        if line.startswith("listening on "):
            url = line.split()[2]
    if url is None:
        process.kill()
        pytest.fail("the explorer did not start:\n" + "".join(lines))
    yield url, "".join(lines)
    process.terminate()
    process.wait(timeout=30)
    assert _digest(folder) == before, "the explorer changed a store's bytes"


@pytest.fixture(scope="module")
def browser(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        yield chromium
        chromium.close()


def _open(browser, url: str, store: str):
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    messages = []
    page.on("console", lambda m: messages.append((m.type, m.text)))
    page.on("pageerror", lambda e: messages.append(("error", str(e))))
    page.goto(f"{url}?store={store}")
    page.wait_for_function("() => window.Bokeh && Bokeh.documents.length > 0 && "
                           "Bokeh.documents[0].get_model_by_name('image-source') !== null", timeout=60_000)
    return page, messages


def _changed(page, name: str, key: str, before) -> dict:
    page.wait_for_function(f"(b) => JSON.stringify(({SOURCE})('{name}')['{key}']) !== JSON.stringify(b)",
                           arg=before, timeout=20_000)
    return page.evaluate(SOURCE, name)


def test_the_startup_says_where_it_listens_and_what_it_opened(server):
    url, log = server
    assert url.startswith("http://127.0.0.1:") and "3 store(s), read-only" in log
    assert "transport.zarr" in log and "(plane_to_ray_transport)" in log


def test_click_a_pixel_then_slide_the_delay_then_relight(server, browser, folder):
    url, _ = server
    page, messages = _open(browser, url, "transport.zarr")
    t = selpath.open_store(folder / "transport.zarr")
    capture = selpath.open_store(folder / "capture.zarr")
    box = page.evaluate(FRAME_BOX, "frame")
    row, col = 9, 5  # on the candle
    before = page.evaluate(SOURCE, "profile-source")["y"]
    before_sweep = page.evaluate(SOURCE, "intensity-source")["ys"]
    page.mouse.click(box["left"] + (col + 0.5) * box["width"] / 32, box["top"] + (row + 0.5) * box["height"] / 24)
    profile = _changed(page, "profile-source", "y", before)
    # the page's sources update one after another: wait for each (under load the second lagged the first)
    sweep = _changed(page, "intensity-source", "ys", before_sweep)
    page.wait_for_function(f"() => JSON.stringify(({SOURCE})('marker-source')) === '{{\"x\":[{col}],\"y\":[{row}]}}'",
                           timeout=20_000)
    assert page.evaluate(SOURCE, "marker-source") == {"x": [col], "y": [row]}, box
    np.testing.assert_allclose(profile["x"], OFFSETS)
    np.testing.assert_allclose(profile["y"], t["transport"].values[:, row, col], rtol=1e-6)
    for k in range(2):
        np.testing.assert_allclose(sweep["ys"][k], capture["image"].values[:, k, row, col], rtol=1e-6)
    # type a delay into the slider's box: the ideal rig's frame at t_d = −68 µs, t_e = 34 µs
    image = page.evaluate(SOURCE, "image-source")["image"]
    page.locator("input").nth(0).fill("-68")
    page.locator("input").nth(0).press("Enter")
    image = _changed(page, "image-source", "image", image)["image"]
    expected = t.selpath.ideal_frame(-68.0, 34.0).values
    np.testing.assert_allclose(np.reshape(image[0], (24, 32)), expected, rtol=1e-5, atol=1e-3)
    # relight: the projector rows 20–23 (line 20, 4 rows lit)
    page.locator("input").nth(2).fill("20")
    page.locator("input").nth(2).press("Enter")
    page.locator("input").nth(3).fill("4")
    page.locator("input").nth(3).press("Enter")
    before = page.evaluate(SOURCE, "image-source")["image"]
    page.get_by_role("button", name="relit").click()
    image = _changed(page, "image-source", "image", before)["image"]
    np.testing.assert_allclose(np.reshape(image[0], (24, 32)), t.selpath.relight(rows=range(20, 24)).values,
                               rtol=1e-5, atol=1e-3)
    assert not [m for m in messages if m[0] == "error"], messages


def test_a_sinogram_shows_its_unobserved_bins(server, browser, folder):
    url, _ = server
    page, messages = _open(browser, url, "sinogram.zarr")
    image = np.array(page.evaluate(SOURCE, "image-source")["image"][0], dtype=float)
    observed = selpath.open_store(folder / "sinogram.zarr")["observed"].values
    assert image.size == observed.size and np.array_equal(np.isnan(image).reshape(observed.shape), ~observed)
    assert not [m for m in messages if m[0] == "error"], messages


@pytest.mark.parametrize("path", ["../../../../etc/passwd", "static/../../../../etc/passwd", "%2e%2e/%2e%2e/etc/passwd",
                                  "transport.zarr/zarr.json", "capture.zarr", "static/..%2f..%2f..%2fetc%2fpasswd"])
def test_nothing_but_the_page_and_its_assets_is_served(server, path):
    url, _ = server
    try:
        with urllib.request.urlopen(url + path, timeout=10) as response:  # noqa: S310 - our own local server
            body = response.read()
            status = response.status
    except urllib.error.HTTPError as exc:
        body, status = exc.read(), exc.code
    assert status in (403, 404) and b"root:" not in body and b"zarr_format" not in body, (status, body[:200])


def test_a_path_without_stores_is_a_clear_error(tmp_path):
    result = subprocess.run([sys.executable, "-m", "selpath", "explore", str(tmp_path / "nowhere")],
                            capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "200"})
    assert result.returncode == 2 and "is neither a selpath store nor a folder" in result.stderr, result.stderr
    (tmp_path / "empty").mkdir()
    result = subprocess.run([sys.executable, "-m", "selpath", "explore", str(tmp_path / "empty")],
                            capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "200"})
    assert result.returncode == 2 and "no selpath store in" in result.stderr, result.stderr


def test_the_page_builds_for_a_notebook_too(folder):
    """``view`` gives the page a notebook displays inline: one view per store kind builds without a server."""
    import panel as pn

    from selpath.explore.explorer import Explorer, view

    page = view(folder)
    assert isinstance(page, pn.viewable.Viewable)
    explorer = Explorer([folder])
    for name in explorer.stores:
        assert isinstance(explorer.panel(name), pn.viewable.Viewable), name
    assert list(explorer.transports) == ["transport.zarr"]  # the preview is built when a transport is first shown
    assert explorer.transports["transport.zarr"].capture is explorer.stores["capture.zarr"]
