"""Scan-speed calibration (§5.3.2): ``calibrate_scan_speed`` counts the illuminated rows of the global-shutter
frames of ``acquire_scan_calibration`` and fits the projector's scan speed v_p and the sync offset t_o by least
squares (optimistix), with standard uncertainties.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import NonNegative
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import TIME_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage


def row_profile_statistics(profile: np.ndarray) -> tuple[float, float]:
    """(illuminated rows, centroid row) of one global-shutter frame's row profile (its column average).

    The profile, less its median (the dark rows: the band must cover under half the
    sensor), is divided by its plateau (the median of the rows above ¾ of the peak, robust to noise where
    the peak is not), so a fully lit row counts 1 and a partly lit row its fraction; rows below 2 % of the
    plateau are dark (clipped read noise would otherwise pull the centroid towards the sensor's middle).
    """
    profile = np.asarray(profile, float) - np.median(profile)
    peak = profile.max()
    if not np.isfinite(peak) or peak <= 0:
        return float("nan"), float("nan")
    plateau = float(np.median(profile[profile >= 0.75 * peak]))
    profile = np.where(profile >= 0.02 * plateau, profile, 0.0)
    rows = np.arange(profile.size)
    return float(profile.sum() / plateau), float((rows * profile).sum() / profile.sum())


_SWEEP = ("delay", "exposure")
SCAN_CALIBRATION = CubeKind(
    name="scan_calibration",
    description="scan speed v_p and sync offset t_o from global-shutter frames of a white target (§5.3.2)",
    variables={
        "count": Variable(_SWEEP, description="illuminated rows counted per frame", units="1",
                          long_name="illuminated camera rows"),
        "centroid": Variable(_SWEEP, description="row centroid of the lit band", units="px",
                             long_name="camera row at the lit band's centroid"),
        "fitted_count": Variable(_SWEEP, False, units="1", long_name="fitted v_p · t_e"),
        "fitted_centroid": Variable(_SWEEP, False, units="px", long_name="fitted band centre"),
        "used": Variable(_SWEEP, required=False, units=None,
                         long_name="frame used in the fit (a band inside the frame)"),
    },
    coord_units={"delay": TIME_UNITS, "exposure": TIME_UNITS},
    attrs={"scan_speed_px_per_us": "fitted v_p, camera rows per µs", "scan_speed_std": "its standard error",
           "sync_offset_us": "fitted t_o, µs", "sync_offset_std": "its standard error"},
)


@stage("calibrate_scan_speed", kind=SCAN_CALIBRATION)
def calibrate_scan_speed(capture: xr.Dataset, /, *, min_rows: NonNegative = 2.0) -> xr.Dataset:
    """Fit the projector scan speed v_p and the sync offset t_o from a global-shutter capture (§5.3.2).

    Model, per frame at commanded delay t_d and exposure t_e: the scan lights v_p · t_e rows during the
    exposure (counted as the row profile's sum over its peak), centred at row v_p · (t_d + t_o + t_e/2 − t_p/2)
    (row s is lit during [s/v_p, s/v_p + t_p]; t_p from the store's ``line_time_us``).
    Both residuals are in rows; the fit is least squares (optimistix Levenberg–Marquardt) and the standard
    uncertainties are s²(JᵀJ)⁻¹ with s² the residual variance.

    Parameters
    ----------
    capture : xr.Dataset
        A ``plane_to_ray_capture`` store of global-shutter frames (``acquire_scan_calibration``): ``image`` over
        (delay, exposure, row, col), delay and exposure [µs]; attr ``line_time_us`` (``scan_speed_px_per_us``: start).
    min_rows : float
        Frames counting fewer illuminated rows are left out (the peak row is not fully exposed there).

    Returns
    -------
    xr.Dataset
        A ``scan_calibration`` cube: each frame's lit-band ``count`` and ``centroid`` [px] over (delay, exposure) with
        the fits' ``fitted_count`` and ``fitted_centroid``; v_p and t_o in attrs (``scan_speed_px_per_us``,
        ``sync_offset_us``) with their standard errors (``scan_speed_std``, ``sync_offset_std``).

    References
    ----------
    Thesis §5.3.2 Hardware.
    """
    # one pass over the frames: the column average of every frame, (delay, exposure, row)
    profiles = capture["image"].mean("col").transpose("delay", "exposure", "row").values
    delays, exposures = capture["delay"].values, capture["exposure"].values
    stats = np.array([[row_profile_statistics(p) for p in row] for row in profiles])
    count, centroid = stats[..., 0], stats[..., 1]
    td, te = np.meshgrid(delays, exposures, indexing="ij")
    use = np.isfinite(count) & (count >= min_rows)
    if use.sum() < 3:
        raise StageError(Problem(f"calibrate_scan_speed: only {int(use.sum())} of {use.size} frames show at least "
                                 f"{min_rows} illuminated rows (counts per frame: {np.round(count, 1).tolist()})",
                                 fix="capture longer exposures, or delays that keep the band on the sensor"))
    line_time = float(capture.attrs["line_time_us"])
    import jax  # the fit's libraries when it runs: reading or validating a workflow imports neither
    import jax.numpy as jnp
    import optimistix as optx

    def residuals(theta, _):
        speed, offset = theta[0] * 1e-2, theta[1] * 1e2  # scaled to O(1) unknowns
        model = jnp.concatenate([speed * t_e, speed * (t_d + offset + t_e / 2 - line_time / 2)])
        return model - data

    nominal = float(capture.attrs.get("scan_speed_px_per_us", 1 / 17))
    with jax.enable_x64(True):  # a two-parameter fit: float64 costs nothing and keeps the covariance honest
        data = jnp.asarray(np.concatenate([count[use], centroid[use]]), jnp.float64)
        t_d, t_e = jnp.asarray(td[use], jnp.float64), jnp.asarray(te[use], jnp.float64)
        start = jnp.array([nominal * 1e2, 0.0], jnp.float64)
        solution = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
                                      start, max_steps=200, throw=False)
        theta = solution.value
        jac = jax.jacfwd(lambda t: residuals(t, None))(theta)
        r = residuals(theta, None)
        dof = max(int(r.size) - 2, 1)
        s2 = float(r @ r) / dof
        cov = s2 * np.linalg.pinv(np.asarray(jac.T @ jac))
        fitted = np.asarray(r) + np.asarray(data)
        converged = bool(solution.result == optx.RESULTS.successful)
    scale = np.array([1e-2, 1e2])
    value = np.asarray(theta) * scale
    std = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
    n = int(use.sum())
    full = np.full(count.shape, np.nan)
    fitted_count, fitted_centroid = full.copy(), full.copy()
    fitted_count[use], fitted_centroid[use] = fitted[:n], fitted[n:]
    coords = {"delay": capture["delay"], "exposure": capture["exposure"]}
    return SCAN_CALIBRATION.label(xr.Dataset(
        {"count": (_SWEEP, count), "centroid": (_SWEEP, centroid), "fitted_count": (_SWEEP, fitted_count),
         "fitted_centroid": (_SWEEP, fitted_centroid), "used": (_SWEEP, use)},
        coords=coords,
        attrs={"scan_speed_px_per_us": float(value[0]),
               "scan_speed_std": float(std[0]), "sync_offset_us": float(value[1]), "sync_offset_std": float(std[1]),
               "residual_rms_px": float(np.sqrt(s2)), "frames_used": n,
               "converged": converged},
    ))
