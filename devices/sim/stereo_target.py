"""A pinhole projector–camera pair filming a planar checkerboard target: what a geometric calibration of the rig
(``selpath.stages.procam.stereo``) is fed, with the truth it must find.

The transport simulator (``selpath.devices.sim.procam_transport``) works in offset space and has no 3-D geometry; a
calibration needs one. Here camera and projector are pinholes without distortion (OpenCV's convention: x right, y
down, z forward; the camera at the origin, the projector at ``R·X + t`` in its own frame), and the target is a
checkerboard of ``squares`` on the plane z = 0 of its own frame, posed by (rvec, tvec) in the camera's. A camera
pixel's light is the board's albedo where its ray meets the board times the projector pixel that lights that point
(the one whose unit cell holds the point's projection), averaged over ``supersample``² sub-pixels, plus ambient
light; the background beyond the board is black. Each pose's geometry is traced once and every pattern is a lookup,
so a stack of Gray codes costs little more than one frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pydantic

from selpath.devices.sim.units import Angle
from selpath.devices.sim.units import PhysicalLength as Length
from selpath.pipeline.yaml_source import load_yaml_model


def rotation(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """R = Rz(roll)·Ry(yaw)·Rx(pitch): roll about the optical axis z, yaw about y (vertical), pitch about x."""
    rz, ry, rx = np.deg2rad([roll_deg, yaw_deg, pitch_deg])
    z = np.array([[np.cos(rz), -np.sin(rz), 0], [np.sin(rz), np.cos(rz), 0], [0, 0, 1]])
    y = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
    x = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
    return z @ y @ x


def intrinsics(focal_px: float, size: tuple[int, int], principal: tuple[float, float] | None = None) -> np.ndarray:
    """K of a pinhole of ``size`` = (width, height) px; the principal point defaults to the image centre."""
    cx, cy = principal if principal is not None else ((size[0] - 1) / 2, (size[1] - 1) / 2)
    return np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class PinholeProcam:
    """Camera and projector intrinsics (pixels, pixel centres at whole numbers) and the projector's pose:
    X_projector = R·X_camera + t [mm]. A rectified pair has R = I and t along x."""

    camera_size: tuple[int, int]  # (width, height) px
    camera_matrix: np.ndarray
    projector_size: tuple[int, int]
    projector_matrix: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


@dataclass(frozen=True)
class Checkerboard:
    """``corners`` = (columns, rows) of inner corners, squares of ``square`` mm, albedos of its light and dark
    squares; the board has one more square than inner corners each way."""

    corners: tuple[int, int] = (9, 6)
    square: float = 25.0
    light: float = 0.85
    dark: float = 0.15

    def object_points(self) -> np.ndarray:
        """Inner corners on the board's plane (z = 0) [mm], row by row, as OpenCV lists them."""
        cols, rows = self.corners
        grid = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).reshape(-1, 2)
        return np.hstack([grid * self.square, np.zeros((grid.shape[0], 1))]).astype(np.float32)

    def albedo(self, xy: np.ndarray) -> np.ndarray:
        """Albedo at board points (…, 2) [mm]: the squares end a square beyond the outer corners, inside a light
        margin one square wide (the quiet zone corner detectors need); 0 off the board."""
        cols, rows = self.corners
        i = np.floor(xy[..., 0] / self.square) + 1
        j = np.floor(xy[..., 1] / self.square) + 1
        squares = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
        board = (i >= -1) & (i <= cols + 1) & (j >= -1) & (j <= rows + 1)
        return np.where(squares, np.where((i + j) % 2 == 0, self.dark, self.light), np.where(board, self.light, 0.0))


def board_poses(count: int, *, distance: float = 600.0, tilt_deg: float = 25.0, seed: int = 0,
                board: Checkerboard = Checkerboard()) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` (rvec, tvec) board poses in the camera's frame: the board's centre near the optical axis at about
    ``distance`` mm, tilted up to ``tilt_deg`` about both in-plane axes (a calibration needs varied tilts)."""
    import cv2  # OpenCV's Rodrigues when poses are made, not when a scene file is read

    rng = np.random.default_rng(seed)
    cols, rows = board.corners
    centre = np.array([(cols - 1) * board.square / 2, (rows - 1) * board.square / 2, 0.0])
    poses = []
    for _ in range(count):
        r = rotation(roll_deg=rng.uniform(-10, 10), pitch_deg=rng.uniform(-tilt_deg, tilt_deg),
                     yaw_deg=rng.uniform(-tilt_deg, tilt_deg))
        where = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), distance * rng.uniform(0.85, 1.15)])
        poses.append((cv2.Rodrigues(r)[0].ravel(), where - r @ centre))
    return poses


@dataclass(frozen=True)
class TracedPose:
    """Per camera sub-pixel: the board's albedo and the projector pixel lighting the point (−1: none)."""

    albedo: np.ndarray  # (h·s, w·s)
    projector_index: np.ndarray  # flat projector pixel, −1 where no projector pixel lights the point
    supersample: int


def trace(rig: PinholeProcam, board: Checkerboard, pose: tuple[np.ndarray, np.ndarray], supersample: int = 3
          ) -> TracedPose:
    """Trace every camera sub-pixel to the board and on to the projector."""
    import cv2

    width, height = rig.camera_size
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    u = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    rays = np.linalg.solve(rig.camera_matrix, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)]))  # z = 1
    r = cv2.Rodrigues(np.asarray(pose[0], float))[0]
    t = np.asarray(pose[1], float)
    normal = r[:, 2]  # the board's z axis in the camera's frame
    depth = (normal @ t) / (normal @ rays)
    points = rays * depth  # camera frame, (3, N)
    xy = (r.T @ (points - t[:, None]))[:2].T
    albedo = np.where(depth > 0, board.albedo(xy), 0.0)
    projected = rig.projector_matrix @ (rig.rotation @ points + rig.translation[:, None])
    pu, pv = projected[0] / projected[2], projected[1] / projected[2]
    col, row = np.floor(pu + 0.5).astype(np.int64), np.floor(pv + 0.5).astype(np.int64)
    pw, ph = rig.projector_size
    inside = (projected[2] > 0) & (col >= 0) & (col < pw) & (row >= 0) & (row < ph) & (albedo > 0)
    index = np.where(inside, row * pw + col, -1)
    shape = (height * supersample, width * supersample)
    return TracedPose(albedo.reshape(shape), index.reshape(shape), supersample)


def render(traced: TracedPose, pattern: np.ndarray, *, intensity: float = 1000.0, ambient: float = 20.0
           ) -> np.ndarray:
    """The camera frame [counts, float32] of a traced pose under ``pattern`` (projector rows × cols in [0, 1])."""
    flat = np.asarray(pattern, float).ravel()
    lit = np.where(traced.projector_index >= 0, flat[np.maximum(traced.projector_index, 0)], 0.0)
    signal = intensity * traced.albedo * lit + ambient * traced.albedo
    s = traced.supersample
    h, w = signal.shape[0] // s, signal.shape[1] // s
    return signal.reshape(h, s, w, s).mean(axis=(1, 3)).astype(np.float32)


# -- a scene file for the simulated target ------------------------------------------------------------------------

class _Model(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, validate_default=True)


class PinholeSpec(_Model):
    width: int = pydantic.Field(gt=0, description="px")
    height: int = pydantic.Field(gt=0, description="px")
    focal_px: float = pydantic.Field(gt=0, description="focal length in pixels")
    principal_px: tuple[float, float] | None = pydantic.Field(None, description="(x, y); default: the image centre")

    def matrix(self) -> np.ndarray:
        return intrinsics(self.focal_px, (self.width, self.height), self.principal_px)


class ProjectorPose(_Model):
    """Where the projector sits and how it is turned, relative to the camera: its centre ``baseline`` along the
    camera's x axis, its axes turned by ``roll`` (about the optical axis: what tilts its rows), ``pitch`` and
    ``yaw`` (``toe_in`` is added to yaw so that it looks at the target ``toe_in_distance`` ahead)."""

    baseline: Length = "100 mm"
    roll: Angle = "0 deg"
    pitch: Angle = "0 deg"
    yaw: Angle = "0 deg"
    toe_in_distance: Length | None = pydantic.Field("600 mm", description="null: parallel axes")


class TargetPoses(_Model):
    count: int = pydantic.Field(10, ge=3, description="board poses (a calibration needs at least 3)")
    distance: Length = "600 mm"
    tilt: Angle = "25 deg"
    seed: int = 0


class TargetNoise(_Model):
    gain: float | None = pydantic.Field(1.0, gt=0, description="counts per photo-electron (shot); null: none")
    read_std: float = pydantic.Field(2.0, ge=0, description="counts")
    seed: int = 0


class StereoTargetScene(_Model):
    """A checkerboard target filmed by a pinhole projector–camera pair at several poses (``docs/devices.md``)."""

    scene: str
    description: str = ""
    camera: PinholeSpec
    projector: PinholeSpec
    pose: ProjectorPose = ProjectorPose()
    board_corners: tuple[int, int] = pydantic.Field((9, 6), description="inner corners (columns, rows)")
    board_square: Length = "25 mm"
    poses: TargetPoses = TargetPoses()
    intensity: float = pydantic.Field(1000.0, gt=0, description="counts of a white-lit light square")
    ambient: float = pydantic.Field(20.0, ge=0, description="counts of unprojected light on a light square")
    noise: TargetNoise | None = TargetNoise()
    saturation_level: float = pydantic.Field(4095.0, gt=0)

    def rig(self) -> PinholeProcam:
        p = self.pose
        yaw = p.yaw + (np.rad2deg(np.arctan2(p.baseline, p.toe_in_distance)) if p.toe_in_distance else 0.0)
        r = rotation(roll_deg=p.roll, pitch_deg=p.pitch, yaw_deg=yaw)
        centre = np.array([p.baseline, 0.0, 0.0])
        return PinholeProcam((self.camera.width, self.camera.height), self.camera.matrix(),
                             (self.projector.width, self.projector.height), self.projector.matrix(), r, -r @ centre)

    def board(self) -> Checkerboard:
        return Checkerboard(corners=self.board_corners, square=self.board_square)

    def target_poses(self) -> list[tuple[np.ndarray, np.ndarray]]:
        q = self.poses
        return board_poses(q.count, distance=q.distance, tilt_deg=q.tilt, seed=q.seed, board=self.board())

    def frame(self, traced: TracedPose, pattern: np.ndarray, key: tuple[int, int]) -> np.ndarray:
        """A camera frame with the sensor's noise (seeded by ``key`` = (pose, pattern): reproducible) and clipping."""
        signal = render(traced, pattern, intensity=self.intensity, ambient=self.ambient).astype(np.float64)
        if self.noise is not None:
            rng = np.random.default_rng([self.noise.seed, *key])
            if self.noise.gain is not None:
                signal = rng.poisson(np.clip(signal, 0, None) / self.noise.gain) * self.noise.gain
            signal = signal + rng.normal(0.0, self.noise.read_std, signal.shape)
        return np.clip(np.round(signal), 0, self.saturation_level).astype(np.float32)


def load_stereo_target(path) -> StereoTargetScene:
    return load_yaml_model(path, StereoTargetScene, what="stereo target scene")


def capture_target(scene: StereoTargetScene, store, *, progress: bool = True, log=lambda _: None):
    """Film the target at every pose under white, black and the projector's Gray codes into a
    ``stereo_target_capture`` store (pose, pattern, row, col), frame by frame and resumably (the store is locked
    while it is written; a rerun captures only the missing frames)."""
    import dask.array as da
    import xarray as xr
    from rich.progress import Progress, TextColumn, TimeElapsedColumn

    from selpath.devices.patterns import gray_code_levels
    from selpath.pipeline.capture_store import create_capture, missing_frames, write_frame
    from selpath.pipeline.locks import store_lock
    from selpath.pipeline.progress import BAR_COLUMNS, show_bars
    from selpath.pipeline.store import open_store

    rig, board = scene.rig(), scene.board()
    poses = scene.target_poses()
    levels, column_bits, row_bits = gray_code_levels((scene.projector.height, scene.projector.width))
    shape = (len(poses), len(levels), scene.camera.height, scene.camera.width)
    template = xr.Dataset(
        {"image": (("pose", "pattern", "row", "col"),
                   da.zeros(shape, dtype=np.float32, chunks=(1, 1, shape[2], shape[3])), {"units": "counts"})},
        coords={"pose": ("pose", np.arange(len(poses)), {"units": "1", "long_name": "board pose number"}),
                "pattern": ("pattern", np.arange(len(levels)),
                            {"units": "1", "long_name": "pattern number: white, black, column bits, row bits"})},
        attrs={"selpath_kind": "stereo_target_capture", "column_bits": column_bits, "row_bits": row_bits,
               "projector_shape": [scene.projector.height, scene.projector.width],
               "board_corners": list(scene.board_corners), "board_square_mm": float(scene.board_square),
               "saturation_counts": scene.saturation_level, "dark_level_counts": 0.0, "rig": "simulated",
               "simulated_scene": scene.model_dump(mode="json")})
    with store_lock(store, purpose="stereo_target_capture"):
        create_capture(store, template, "stereo_target_capture")
        todo = missing_frames(store)["image"]
        log(f"   capturing {len(todo)} target frame(s) into {store}")
        by_pose: dict[int, list[int]] = {}
        for frame in todo:
            by_pose.setdefault(int(frame["pose"]), []).append(int(frame["pattern"]))
        with Progress(*BAR_COLUMNS, TextColumn("frames"), TimeElapsedColumn(), disable=not show_bars(progress),
                      transient=True) as bar:
            task = bar.add_task("capture", total=len(todo))
            for pose, patterns in sorted(by_pose.items()):
                traced = trace(rig, board, poses[pose])
                for i in patterns:
                    write_frame(store, "image", {"pose": pose, "pattern": i},
                                scene.frame(traced, levels[i] / 255.0, (pose, i)))
                    bar.update(task, advance=1, description=f"capture: pose {pose}, pattern {i}")
    return open_store(store)
