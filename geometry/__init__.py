"""Geometry that the simulator and the processing stages share (DESIGN §1, §8).

- :mod:`selpath.geometry.rig`: the tomography rig's camera models (perspective, orthographic), the light, the lab
  and object frames, the pixel convention, and the capture attrs that declare them.
- :mod:`selpath.geometry.shapes`: convex shapes and solids (polygon, ellipse, prism, ellipsoid) and where lines
  cross them; a polygon's support function and containment.

Nothing here imports the simulator, the devices or the stages: the simulator renders with these models and the
stages invert them, so neither can disagree with the other on a convention.
"""
