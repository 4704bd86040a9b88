"""Chapter 5: synchronised projector–camera light transport.

``acquire`` (delay–exposure and line sweeps, scan calibration frames) → ``calibrate`` (scan speed v_p, sync
offset) → ``demux`` (plane-to-ray T(offset, row, col)) and ``demux_full`` (full T(du, dv, row, col)) → ``relight``
(relighting, epipolar images, the ideal frame) and its stages in ``virtual``; ``figures``.
"""
