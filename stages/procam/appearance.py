"""Appearance capture for graphics (thesis §5.4.8, Fig. 50): a material's scattering profile, measured and rendered.

**The profile.** The thesis assumes subsurface scattering depends only on the distance light travels below the
surface, and takes that dependence from the delay sweep. Here it is fitted: the material's transport as a
function of the distance d between where light enters and where it leaves is modelled as
R(d) = (1 − f)·δ(d) + f·L_w(d), L_w the Laplace (exponential) lobe of width w integrated over unit cells, and f and w
(with an amplitude) are fitted by least squares to the mean delay profile of the material's pixels *through the
sweep's own illumination matrix* (:func:`selpath.stages.procam._illumination.plane_to_ray_illumination`), so the
exposure's
blur and the sweep's finite range are modelled, not fitted away. Standard errors come from the fit's Jacobian.

**The render.** A mesh (``selpath.stages.procam._mesh``: a generated teapot, or a sphere) is rasterised orthographically
and lit by a directional light: the Lambertian image is the irradiance E = max(n·l, 0). The subsurface image
spreads the share f of the irradiance over the surface by R, in screen space: (1 − f)·E + f·(k ⊗ k) ∗ E inside the
silhouette, with k the fitted 1-D lobe in render pixels (``scale`` capture pixels per render pixel). Taking the 2-D
kernel separable, k(x)·k(y), gives it exactly the measured profile as its marginal (it is also the simulator's own
lobe shape); a radial kernel would need the inverse Abel transform of the profile, which noisy data do not bear.
Screen space ignores the surface's curvature and the light that leaves past the silhouette is lost: a stated
approximation, as the thesis's was. A Blinn–Phong highlight is added to both images alike (the thesis added one "as
a post process for better perception"). With f = 0 (R = δ) the two images are identical.
"""

from __future__ import annotations

from typing import Annotated, Literal

import dask
import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Count, Fraction, NonNegative, Positive, StorePath
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import PX_UNITS, TIME_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages.procam._illumination import plane_to_ray_illumination
from selpath.stages.procam._labels import Labels, label_identity, label_map, label_precheck
from selpath.stages.procam._mesh import MESHES, rasterise, rotate
from selpath.stages.procam.materials import profile_frames


def laplace_cells(offsets: np.ndarray, width: float) -> np.ndarray:
    """Mass of the unit Laplace lobe of scale ``width`` in each unit cell [o − ½, o + ½)."""
    def cdf(y):
        return np.where(y < 0, 0.5 * np.exp(np.minimum(y, 0) / width), 1.0 - 0.5 * np.exp(-np.maximum(y, 0) / width))
    return cdf(offsets + 0.5) - cdf(offsets - 0.5)


def profile_model(offsets: np.ndarray, fraction: float, width: float) -> np.ndarray:
    """R on the integer offsets: (1 − f)·δ + f·Laplace(w), cell masses (sums to 1 over all integers)."""
    return (1 - fraction) * (offsets == 0) + fraction * laplace_cells(offsets, width)


SCATTERING_PROFILE = CubeKind(
    name="scattering_profile",
    description="a material's fitted scattering profile R(d) = (1 − f)·δ + f·Laplace(w) (§5.4.8)",
    variables={"profile": Variable(("distance",), units="1",
                                   long_name="scattering profile R(d), mass per unit distance cell"),
               "measured": Variable(("delay",), units="counts", long_name="the material's mean delay profile"),
               "model": Variable(("delay",), False, units="counts", long_name="the fitted profile's delay sweep")},
    coord_units={"distance": PX_UNITS, "delay": TIME_UNITS},
    attrs={"fraction": "the share f of the light that scatters below the surface",
           "width_px": "the Laplace lobe's width w, px"},
)
APPEARANCE_RENDER = CubeKind(
    name="appearance_render",
    description="a mesh rendered with and without a captured subsurface profile (§5.4.8, Fig. 50)",
    variables={"image": Variable(("render", "row", "col"), units="1", long_name="rendered radiance"),
               "mask": Variable(("row", "col"), False, units=None, long_name="the mesh's silhouette")},
)


@stage("fit_scattering_profile", kind=SCATTERING_PROFILE, precheck=label_precheck, identity=label_identity)
def fit_scattering_profile(capture: xr.Dataset, /, *, material: str, labels: Labels = "scene",
                           label_image: StorePath = "", classes: tuple[str, ...] | None = None,
                           exposure: Positive | None = None,
                           max_distance: Annotated[int, pydantic.Field(ge=1, le=1000)] = 40) -> xr.Dataset:
    """Fit a material's scattering profile R(d) = (1 − f)·δ + f·Laplace(w) to its mean delay profile (§5.4.8).

    Parameters
    ----------
    capture : xr.Dataset
        A ``plane_to_ray_capture`` (``image`` over delay, exposure, row, col [counts]; attrs
        ``scan_speed_px_per_us``, ``line_time_us``, and ``sync_offset_us`` where calibrated).
    material : str
        The class whose pixels are fitted, as the labels name it.
    labels, label_image, classes
        Where the material's pixels come from, as ``train_material_classifier`` takes them.
    exposure : float or None
        The exposure whose delay sweep is fitted [µs]; None: the capture's only one.
    max_distance : int
        The distances R is reported over [px].

    Returns
    -------
    xr.Dataset
        A ``scattering_profile`` cube: ``profile`` R over distance 0 … ``max_distance`` [1 per px: cell masses, summing
        to 1 over both signs], the material's mean delay profile ``measured`` and the fit's ``model`` over delay
        [counts]; attrs ``fraction`` f and ``width_px`` w with their standard errors, and the fit's RMS residual.

    Raises
    ------
    StageError
        A material with no usable pixel, a capture of several exposures without ``exposure``.

    References
    ----------
    Thesis §5.4.8 Appearance capture for graphics.
    """
    from scipy.optimize import least_squares  # scipy when it fits, not when a workflow is read

    frames, saturated, what = profile_frames(capture, exposure)
    if what["source_kind"] != "plane_to_ray_capture":
        raise StageError(Problem("the profile is fitted to a delay sweep through its illumination matrix",
                                 fix="wire in acquire_plane_to_ray's capture, not a transport"))
    codes, names = label_map(capture, labels, label_image, classes, "capture")
    if material not in names:
        raise StageError(Problem(f"no class {material!r} in the labels ({list(names)})", fix="name one of them"))
    finite = np.isfinite(frames).all("delay")
    mask = (codes == names.index(material) + 1) & ~np.asarray(saturated.values) & np.asarray(finite.values)
    if not mask.any():
        raise StageError(Problem(f"{material!r} has no pixel with a finite, unsaturated sweep",
                                 fix="check the capture"))
    measured = np.asarray(frames.where(xr.DataArray(mask, dims=("row", "col"))).mean(("row", "col")).values,
                          np.float64)
    delays = frames["delay"].values.astype(float)
    missing = [k for k in ("scan_speed_px_per_us", "line_time_us") if k not in capture.attrs]
    if missing:
        raise StageError(Problem(f"the capture lacks attrs {missing}: the sweep's illumination is unknown",
                                 where="capture",
                                 fix="acquire with acquire_plane_to_ray, or add them (docs/format.md)"))
    speed, line_time = float(capture.attrs["scan_speed_px_per_us"]), float(capture.attrs["line_time_us"])
    t_e = what["exposure_us"]
    reach = int(np.ceil(np.abs(delays).max() * speed + (t_e + line_time) / 2 * speed)) + 1
    offsets = np.arange(-reach, reach + 1)
    weights = plane_to_ray_illumination(delays, np.full(delays.shape, t_e), offsets, scan_speed=speed,
                                        line_time=line_time, sync_offset=float(capture.attrs.get("sync_offset_us", 0)))

    def residual(p):
        return p[0] * weights @ profile_model(offsets, p[1], p[2]) - measured

    start = [max(measured.sum() / max(weights.sum(axis=0).max(), 1e-12), 1e-12), 0.5, 3.0]
    fit = least_squares(residual, start, bounds=([0, 0, 0.05], [np.inf, 1, 1000]), x_scale="jac")
    dof = max(measured.size - 3, 1)
    variance = float(fit.fun @ fit.fun) / dof
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * variance
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        std = np.full(3, np.nan)
    amplitude, fraction, width = (float(v) for v in fit.x)
    distance = np.arange(max_distance + 1)
    return SCATTERING_PROFILE.label(xr.Dataset(
        {"profile": ("distance", profile_model(distance, fraction, width)), "measured": ("delay", measured),
         "model": ("delay", measured + fit.fun)},
        coords={"distance": ("distance", distance, {"units": "px", "long_name": "distance d below the surface"}),
                "delay": ("delay", delays, {"units": "us", "long_name": "sync delay t_d"})},
        attrs={"material": material, "fraction": fraction,
               "fraction_std": float(std[1]), "width_px": width, "width_std_px": float(std[2]),
               "amplitude_counts": amplitude, "residual_rms_counts": float(np.sqrt(variance)),
               "pixels": int(mask.sum()),
               "exposure_us": t_e, "scene": capture.attrs.get("scene", "")}))


def shade(covered: np.ndarray, normal: np.ndarray, light: np.ndarray, fraction: float, width_px: float, *,
          specular: float, shininess: float) -> tuple[np.ndarray, np.ndarray]:
    """The Lambertian and the subsurface image of a rasterised surface (module doc), albedo 1."""
    from scipy.ndimage import convolve1d

    light = light / np.linalg.norm(light)
    irradiance = np.clip(normal @ light, 0, None) * covered
    halfway = light + np.array([0.0, 0.0, 1.0])
    halfway /= np.linalg.norm(halfway)
    highlight = specular * np.clip(normal @ halfway, 0, None) ** shininess * covered
    if fraction > 0:
        reach = int(np.ceil(21 * width_px)) + 1
        kernel = laplace_cells(np.arange(-reach, reach + 1), width_px)
        spread = convolve1d(convolve1d(irradiance, kernel, axis=0, mode="constant"), kernel, axis=1, mode="constant")
        scattered = (1 - fraction) * irradiance + fraction * spread * covered
    else:
        scattered = irradiance
    return irradiance + highlight, scattered + highlight


@stage("render_appearance", kind=APPEARANCE_RENDER)
def render_appearance(profile: xr.Dataset, /, *, mesh: Literal["teapot", "sphere"] = "teapot",
                      size: tuple[Count, Count] = (240, 320),
                      light: tuple[float, float, float] = (-0.7, 0.5, 0.5),
                      yaw: Annotated[float, pydantic.Field(ge=-180, le=180)] = 30.0,
                      pitch: Annotated[float, pydantic.Field(ge=-90, le=90)] = 20.0,
                      scale: Positive = 1.0, specular: NonNegative = 0.15, shininess: Positive = 40.0,
                      fraction: Fraction | None = None) -> xr.Dataset:
    """Render a mesh under a directional light with and without the captured subsurface scattering (§5.4.8, Fig. 50).

    Parameters
    ----------
    profile : xr.Dataset
        A ``scattering_profile`` (``fit_scattering_profile``): attrs ``fraction`` and ``width_px``.
    mesh : str
        ``teapot`` (generated from surfaces of revolution and tubes) or ``sphere``.
    size : [rows, cols]
        The render's size [px].
    light : [x, y, z]
        Direction towards the light (x right, y up, z towards the viewer); need not be unit length.
    yaw, pitch : float
        The mesh turned about the vertical axis, then tilted towards the viewer [degree].
    scale : float
        Capture pixels per render pixel: the lobe's width in the render is width_px / scale [1].
    specular, shininess : float
        The Blinn–Phong highlight added to both images: its strength [1] and exponent [1].
    fraction : float or None
        Replace the fitted share f (0: R = δ, the Lambertian render); None: the profile's.

    Returns
    -------
    xr.Dataset
        An ``appearance_render`` cube: ``image`` over (render, row, col) [1: irradiance of a white surface, plus the
        highlight]: ``lambertian`` and ``subsurface``, and the silhouette ``mask``. Lazy: rendered when computed.

    References
    ----------
    Thesis §5.4.8 Appearance capture for graphics.
    """
    if not {"fraction", "width_px"} <= set(profile.attrs):
        raise StageError(Problem("the profile has no fitted fraction and width_px", where="profile",
                                 fix="wire in the output of fit_scattering_profile"))
    direction = np.asarray(light, float)
    if not np.isfinite(direction).all() or np.linalg.norm(direction) == 0:
        raise StageError(Problem(f"light {light} has no direction", fix="give a non-zero [x, y, z]"))
    f = float(profile.attrs["fraction"]) if fraction is None else fraction
    width = float(profile.attrs["width_px"]) / scale
    shape = (int(size[0]), int(size[1]))

    def render():
        vertices, faces = MESHES[mesh]()
        covered, normal = rasterise(rotate(vertices, yaw, pitch), faces, shape)
        return np.stack([*shade(covered, normal, direction, f, width, specular=specular, shininess=shininess),
                         covered.astype(float)])

    import dask.array as da  # on computing, not on reading a workflow

    stack = da.from_delayed(dask.delayed(render)(), shape=(3, *shape), dtype=float)
    return APPEARANCE_RENDER.label(xr.Dataset(
        {"image": (("render", "row", "col"), stack[:2]), "mask": (("row", "col"), stack[2] > 0)},
        coords={"render": ("render", ["lambertian", "subsurface"])},
        attrs={"mesh": mesh, "fraction": f, "width_render_px": width,
               "material": profile.attrs.get("material", ""), "light": list(map(float, direction))}))
