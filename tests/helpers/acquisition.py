"""The tomography acquisition's workflow on a small simulated scene (a capture store written frame by frame), for
the tests of acquisition, stores and import."""

from __future__ import annotations

from pathlib import Path

SCENE = """\
scene: tiny-bin
object:
  shape: {kind: cylinder, radius: 10 mm}
  height: 20 mm
  medium: {sigma: 0.01 /mm}
  inclusions:
    - {shape: {kind: polygon, vertices: [[2 mm, 1 mm], [6 mm, 1 mm], [6 mm, 3 mm], [2 mm, 3 mm]]}, sigma: 0.2 /mm}
light: {kind: beam, angle: 45 deg, distance: 100 mm}
camera: {model: perspective, rows: 6, cols: 48, distance: 80 mm, fov: 20 deg}
sensor: {frame_interval: FRAME}
effects:
  noise: {read_std: 2.0, gain: 1.0, seed: 7}
"""


WORKFLOW = """\
workflow: kill-and-resume
scheduler: synchronous
steps:
  - id: capture
    stage: acquire_tomography
    with: {rig: sim, scene: scene.yaml, angles: {start: 0, stop: 360, step: 15}, store: capture.zarr,
           progress: false}
"""


def make_workflow(folder: Path, frame_interval: str = "0 s") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.yaml").write_text(SCENE.replace("FRAME", frame_interval))
    (folder / "workflow.yaml").write_text(WORKFLOW)
    return folder / "workflow.yaml"
