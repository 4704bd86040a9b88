"""Projector–camera stages build graphs and compute nothing (DESIGN §3): demultiplexing, relighting and every
figure stage, on dask-backed captures, under a dask scheduler that fails on the first compute."""

from __future__ import annotations

import pytest

from selpath.stages.procam.demux import demux_plane_to_ray
from selpath.stages.procam.demux_full import demux_full
from selpath.stages.procam.figures import delay_profile_figure, epipolar_figure, relighting_figure
from selpath.stages.procam.full_figures import profile_2d_figure, relighting_full_figure
from selpath.stages.procam.relight import checkerboard_relight, epipolar_image, non_epipolar_image, relight
from tests.helpers import full_transport, procam


@pytest.fixture(scope="module")
def plane_capture():
    return procam.capture_of(procam.scene()).chunk({"row": 8})


@pytest.fixture(scope="module")
def full_capture():
    return full_transport.full_capture(full_transport.scene()).chunk({"row": 8})


def test_plane_to_ray_demultiplexing_relighting_and_figures_stay_lazy(plane_capture, no_compute):
    transport = demux_plane_to_ray(plane_capture, max_iter=5)
    assert transport["transport"].chunks is not None
    relight(transport["transport"], [1.0] * plane_capture.sizes["row"])
    epipolar_image(transport["transport"], 2)
    non_epipolar_image(transport["transport"])
    delay_profile_figure(plane_capture, transport, pixels={"a": (0.3, 0.5)})
    relighting_figure(transport)
    epipolar_figure(plane_capture, transport, half_width=2)
    assert no_compute.count == 0


def test_full_demultiplexing_relighting_and_figures_stay_lazy(full_capture, no_compute):
    transport = demux_full(full_capture, offsets=full_transport.GRID, max_iter=5)
    assert transport["transport"].chunks is not None
    checkerboard_relight(transport, 4, 24)
    profile_2d_figure(transport, pixels={"a": (0.3, 0.5)})
    relighting_full_figure(transport)
    assert no_compute.count == 0
