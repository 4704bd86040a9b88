"""Tomography figure stages build graphs and compute nothing until the workflow computes them; drawn, each is an
RGBA image of the size it declares (the standard width). Importing them leaves matplotlib's backend and pyplot's
figures alone."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from selpath.stages._figures import DPI, SIZE_IN
from selpath.stages.tomography.figures import capture_figure, coverage_figure, sinogram_figure
from selpath.stages.tomography.reconstruct import fbp, reconstruct_tv
from selpath.stages.tomography.reconstruction_figures import convergence_figure, reconstruction_figure
from tests.helpers.sinograms import sinogram
from tests.helpers.tomography import lazy_chain


def test_figure_stages_stay_lazy_and_draw_rgba_images(no_compute):
    cap, _, sino, cover = lazy_chain()
    data = sinogram(12, 16)
    recon, optimised = fbp(data), reconstruct_tv(data, max_iter=3)
    figures = [capture_figure(cap), sinogram_figure(sino), coverage_figure(cover),
               reconstruction_figure(recon, optimised), convergence_figure(optimised)]
    assert no_compute.count == 0
    for figure in figures:
        declared = figure["image"].shape
        image = figure["image"].compute(scheduler="synchronous")
        assert image.shape == declared and declared[1:] == (int(SIZE_IN[0] * DPI), 4) and image.dtype == np.uint8
        assert len(np.unique(image.values.reshape(-1, 4), axis=0)) > 10  # something was drawn


def test_importing_the_figure_stages_keeps_the_backend_and_pyplot_state():
    code = ("import matplotlib; matplotlib.use('svg'); import matplotlib.pyplot as plt\n"
            "import selpath.stages.tomography.figures, selpath.stages.tomography.reconstruction_figures\n"
            "import selpath.stages.procam.figures\n"
            "import selpath.stages._figures as f\n"
            "f.rgba(f.panels(1, 2)[0])\n"
            "print(matplotlib.get_backend(), len(plt.get_fignums()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["svg", "0"]
