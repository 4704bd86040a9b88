"""The projector–camera simulator's ground truth: each pixel's transport as a sum of separable *lobes* in offset
space, weight · k_u(du) · k_v(dv) (du in projector columns from the pixel's direct correspondence, dv = projector row
− camera row), one or more per effect its object names (``selpath.devices.sim.procam_scene``); kernels integrated
over each unit offset cell, so a lobe's mass on the integer grid is exactly its weight. Pixels are handled in row
tiles (:class:`Tile`); only the named effects' code runs. :mod:`selpath.devices.sim.procam_transport` forms images
from these lobes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from selpath.devices.sim.procam_scene import Effects, ProcamRig, ProcamScene


@dataclass(frozen=True)
class Lobe:
    """One separable lobe for a set of pixels (``index`` into the tile's flattened pixels)."""

    index: np.ndarray
    weight: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    width_u: np.ndarray
    width_v: np.ndarray
    shape_u: str  # "hat" | "gauss" | "exp"
    shape_v: str
    #: (low, high, share): the share of the vertical kernel's mass at |dv − centre| in [low, high] that is absorbed
    #: (an absorber below the surface, :class:`~selpath.devices.sim.procam_scene.Absorber`); None: nothing absorbed
    absorbed_v: tuple[float, float, float] | None = None


def _cdf(y: np.ndarray, width: np.ndarray, shape: str) -> np.ndarray:
    """The distribution function of a unit lobe (``gauss``: standard deviation ``width``; ``exp``: Laplace scale)."""
    if shape == "gauss":
        from scipy.special import ndtr  # scipy when a scene renders, not when its file is read

        return ndtr(y / width)
    if shape == "exp":
        return np.where(y < 0, 0.5 * np.exp(np.minimum(y, 0) / width), 1.0 - 0.5 * np.exp(-np.maximum(y, 0) / width))
    raise ValueError(f"unknown lobe shape {shape!r}")


def cell_kernel(offsets: np.ndarray, centre: np.ndarray, width: np.ndarray, shape: str,
                absorbed: tuple[float, float, float] | None = None) -> np.ndarray:
    """Mass of a unit lobe in each unit offset cell [o − ½, o + ½); broadcasts ``offsets`` against centre/width.

    ``hat`` is the linear interpolation of a delta at ``centre`` (width ignored); ``gauss`` has standard
    deviation ``width``; ``exp`` is the Laplace density with scale ``width``. Each sums to 1 over all
    integers. ``absorbed`` = (low, high, share) removes that share of the mass at distances |x| in [low, high] from
    the centre (both sides), cell by cell: what an absorbing layer below the surface takes.
    """
    x = offsets - centre
    if shape == "hat":
        if absorbed is not None:
            raise ValueError("a hat (direct) lobe has no mass below the surface to absorb")
        return np.clip(1.0 - np.abs(x), 0.0, None)
    mass = _cdf(x + 0.5, width, shape) - _cdf(x - 0.5, width, shape)
    if absorbed is not None:
        low, high, share = absorbed
        for a, b in ((low, high), (-high, -low)):  # the cell's overlap with each side of the band
            top, bottom = np.minimum(x + 0.5, b), np.maximum(x - 0.5, a)
            mass = mass - share * np.where(top > bottom, _cdf(top, width, shape) - _cdf(bottom, width, shape), 0.0)
    return mass


def lobe_reach(width: np.ndarray, shape: str) -> int:
    """Half-width of the offset window that holds a lobe's mass to below 1e-9."""
    if shape == "hat" or width.size == 0:
        return 1
    factor = 6.5 if shape == "gauss" else 21.0  # Laplace tail: exp(−21) ≈ 8e-10
    return int(np.ceil(factor * float(width.max()))) + 1


# -- the tile of pixels ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Tile:
    """Pixels rows[r0:r1] × all columns, with fractional coordinates and the object each shows."""

    rows: np.ndarray  # (P,) camera row of each pixel
    cols: np.ndarray
    fx: np.ndarray  # fractions of width / height, pixel centres
    fy: np.ndarray
    aspect: float  # width / height: fraction-x times aspect is in height units
    label: np.ndarray  # −1 background, else index into scene.objects
    shape: tuple[int, int]

    @classmethod
    def of(cls, scene: ProcamScene, r0: int, r1: int) -> Tile:
        rig = scene.rig
        rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(rig.camera_cols), indexing="ij")
        rows, cols = rr.ravel(), cc.ravel()
        fx, fy = (cols + 0.5) / rig.camera_cols, (rows + 0.5) / rig.camera_rows
        aspect = rig.camera_cols / rig.camera_rows
        label = np.full(rows.shape, -1)
        for i, obj in enumerate(scene.objects):
            region = obj.region
            inside = region.mask(fx, fy) if region.kind == "rectangle" else region.mask(fx, fy, aspect)
            label[inside] = i
        return cls(rows, cols, fx, fy, aspect, label, (r1 - r0, rig.camera_cols))


def _surfaces(scene: ProcamScene, tile: Tile):
    """(index, albedo, disparity, effects) for the background and each object present in the tile."""
    for i, surface in [(-1, scene.background), *enumerate(scene.objects)]:
        index = np.flatnonzero(tile.label == i)
        if index.size:
            yield index, surface.albedo, surface.disparity, surface.effects


# -- effects: each returns the lobes of its pixels; only named effects are called -----------------------


def _full(index: np.ndarray, value: float) -> np.ndarray:
    return np.full(index.shape, float(value))


def direct_lobes(index, albedo, effects: Effects, tile: Tile, rig: ProcamRig) -> list[Lobe]:
    share = 1.0 - (effects.subsurface.fraction if effects.subsurface else 0.0)
    zero = _full(index, 0.0)
    return [Lobe(index, _full(index, albedo * share), zero, zero, zero, zero, "hat", "hat")]


def subsurface_lobes(index, albedo, effects: Effects, tile: Tile, rig: ProcamRig) -> list[Lobe]:
    spec = effects.subsurface
    zero, width = _full(index, 0.0), _full(index, spec.width)
    absorbed = spec.absorber.absorbed_offsets() if spec.absorber is not None else None
    return [Lobe(index, _full(index, albedo * spec.fraction), zero, zero, width, width, "exp", "exp", absorbed)]


def diffuse_interreflection_lobes(index, albedo, effects: Effects, tile: Tile, rig: ProcamRig) -> list[Lobe]:
    spec = effects.diffuse_interreflection
    d = tile.fx[index] - spec.corner_x
    weight = spec.strength * albedo * np.exp(-np.abs(d) / spec.falloff)
    du = -2.0 * d * rig.projector_cols  # light from the facing page, mirrored across the corner
    return [Lobe(index, weight, du, _full(index, 0.0), np.maximum(2.0, np.abs(du) / 2), _full(index, spec.width_v),
                 "gauss", "exp")]


def specular_interreflection_lobes(index, albedo, effects: Effects, tile: Tile, rig: ProcamRig) -> list[Lobe]:
    spec = effects.specular_interreflection
    x = (tile.fx[index] - spec.centre[0]) * tile.aspect
    y = tile.fy[index] - spec.centre[1]
    pool = np.exp(-(x**2 + y**2) / (2 * (spec.reach / 2) ** 2)) * (np.hypot(x, y) < spec.reach)
    weight = spec.strength * albedo * pool
    if spec.facets is not None:
        weight = weight * ((np.cos(2 * np.pi * x / spec.facets) * np.cos(2 * np.pi * y / spec.facets)) > 0.5)
    du = spec.displacement[0] + spec.gain * x / tile.aspect * rig.projector_cols
    dv = spec.displacement[1] + spec.gain * y * rig.camera_rows
    width = _full(index, spec.width)
    keep = weight > 0
    return [Lobe(index[keep], weight[keep], du[keep], dv[keep], width[keep], width[keep], "gauss", "gauss")]


def refraction_lobes(index, albedo, effects: Effects, tile: Tile, rig: ProcamRig) -> list[Lobe]:
    spec = effects.refraction
    du = -2.0 * (tile.fx[index] - spec.centre[0]) * rig.projector_cols  # entering high, leaving low (Fig. 46)
    dv = -2.0 * (tile.fy[index] - spec.centre[1]) * rig.camera_rows
    width = _full(index, spec.width)
    return [Lobe(index, _full(index, spec.transmittance), du, dv, width, width, "gauss", "gauss")]


#: effect name → lobe builder (a constant table; tests wrap entries to count calls)
EFFECTS: dict[str, Callable[..., list[Lobe]]] = {
    "subsurface": subsurface_lobes,
    "diffuse_interreflection": diffuse_interreflection_lobes,
    "specular_interreflection": specular_interreflection_lobes,
    "refraction": refraction_lobes,
}


def tile_lobes(scene: ProcamScene, tile: Tile,
               effects: dict[str, Callable] | None = None) -> tuple[list[Lobe], np.ndarray]:
    """The lobes of every pixel in ``tile`` and each pixel's direct correspondence column u_d."""
    table = EFFECTS if effects is None else effects
    rig = scene.rig
    u_direct = np.zeros(tile.rows.shape, dtype=np.int64)
    lobes: list[Lobe] = []
    for index, albedo, disparity, named in _surfaces(scene, tile):
        u_direct[index] = np.round(tile.fx[index] * rig.projector_cols - 0.5 + disparity).astype(np.int64)
        if albedo > 0:
            lobes += direct_lobes(index, albedo, named, tile, rig)
        for name in named.names():
            lobes += table[name](index, albedo, named, tile, rig)
    lobes = [lobe for lobe in lobes if lobe.index.size]
    if rig.misalignment is not None:  # every path of a pixel arrives δ(s, c) rows off its epipolar row
        delta = rig.misalignment.offset(tile.cols, rig.camera_cols)
        lobes = [dataclasses.replace(lobe, dv=lobe.dv + delta[lobe.index]) for lobe in lobes]
    return lobes, u_direct
