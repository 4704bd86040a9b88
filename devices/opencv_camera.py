"""A generic camera through OpenCV's ``VideoCapture`` (USB/UVC cameras, GigE through GStreamer, image
sequences such as ``frames/img_%04d.png`` for dry runs).

OpenCV already speaks to most cameras; this class only adds what a sweep needs: a fixed frame shape,
float32 single-channel frames, and a :class:`~selpath.pipeline.errors.DeviceError` naming the source instead of
OpenCV's silent ``(False, None)``.
"""

from __future__ import annotations

import numpy as np

from selpath.pipeline.errors import DeviceError


class OpenCVCamera:
    """:class:`~selpath.devices.protocols.Camera` over ``cv2.VideoCapture(source)``.

    Parameters
    ----------
    source : int or str
        Device index (``0``), a URL, a GStreamer pipeline or an image-sequence pattern.
    width, height : int, optional
        Requested frame size [px]; the camera's answer is checked.
    exposure : float, optional
        Value for ``CAP_PROP_EXPOSURE`` (units depend on the backend).
    discard : int
        Frames read and dropped before each capture (stale frames in the driver's queue).
    keep_first : bool
        The frame read to learn the shape is the first capture (a free-running camera); False: it is dropped and
        every capture reads a new frame (a camera triggered per capture, whose first frame came before the sweep
        set anything).
    """

    def __init__(self, source: int | str, *, width: int | None = None, height: int | None = None,
                 exposure: float | None = None, discard: int = 0, keep_first: bool = True):
        import cv2  # OpenCV when a camera is opened, not when a rig file is read

        self.source, self.discard = str(source), discard
        self._capture = cv2.VideoCapture(source)
        if not self._capture.isOpened():
            raise DeviceError("cannot open the camera", port=self.source,
                              fix="check the index/URL and that no other program uses the camera")
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, width), (cv2.CAP_PROP_FRAME_HEIGHT, height),
                            (cv2.CAP_PROP_EXPOSURE, exposure)):
            if value is not None:
                self._capture.set(prop, value)
        first = self._read("first frame")
        self._shape = first.shape
        self._pending: np.ndarray | None = first if keep_first else None
        if (width and first.shape[1] != width) or (height and first.shape[0] != height):
            raise DeviceError(f"camera delivers {first.shape[1]}×{first.shape[0]} frames, not {width}×{height}",
                              port=self.source, fix="request a size the camera supports")

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    def _read(self, what: str) -> np.ndarray:
        ok, frame = self._capture.read()
        if not ok or frame is None:
            raise DeviceError(f"the camera returned no {what}", port=self.source,
                              fix="check the cable and trigger; run the acquisition again to resume")
        if frame.ndim == 3:
            import cv2

            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        return frame.astype(np.float32)

    def capture(self) -> np.ndarray:
        if self._pending is not None:  # the frame read to learn the shape is the first capture
            frame, self._pending = self._pending, None
            return frame
        for _ in range(self.discard):
            self._read("frame")
        frame = self._read("frame")
        if frame.shape != self._shape:
            raise DeviceError(f"frame shape changed from {self._shape} to {frame.shape}", port=self.source)
        return frame

    def close(self) -> None:
        self._capture.release()
