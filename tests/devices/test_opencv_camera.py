"""The OpenCV camera driver, run on an image sequence (OpenCV's own CAP_IMAGES backend)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from selpath.devices.opencv_camera import OpenCVCamera
from selpath.pipeline.errors import DeviceError


def test_frames_come_back_in_order_as_float32_grey(tmp_path):
    frames = [np.full((12, 16, 3), 10 * (i + 1), np.uint8) for i in range(3)]
    for i, frame in enumerate(frames):
        frame[0, 0] = (0, 0, 255)  # a red pixel: BGR -> grey uses OpenCV's weights
        cv2.imwrite(str(tmp_path / f"img_{i:03d}.png"), frame)
    camera = OpenCVCamera(str(tmp_path / "img_%03d.png"))
    assert camera.shape == (12, 16)
    got = [camera.capture() for _ in range(3)]
    assert all(g.dtype == np.float32 for g in got)
    assert [float(g[5, 5]) for g in got] == [10.0, 20.0, 30.0]
    assert got[0][0, 0] == pytest.approx(0.299 * 255, abs=1)
    with pytest.raises(DeviceError, match=r"the camera returned no frame .*resume"):
        camera.capture()  # the sequence is exhausted, like a camera that stopped delivering
    camera.close()


def test_a_camera_that_cannot_open_is_named(tmp_path):
    with pytest.raises(DeviceError, match=r"port .*nothing_%03d.png: cannot open the camera"):
        OpenCVCamera(str(tmp_path / "nothing_%03d.png"))
