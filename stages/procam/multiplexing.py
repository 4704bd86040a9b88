"""Illumination multiplexing and SNR (thesis §5.3.1, §5.4.3; its future work: Hadamard codes, §6.2).

n line intensities x [counts a line gives when lit alone for one capture] are measured in n captures under a
*code* A (captures × lines: how much of each line's light each capture gets) and decoded by x̂ = A⁻¹·y, without a
prior. Simplex is A = I (one line per capture); the thesis's multiplexing widens each capture's line (l_w = 50 px
over 10-px steps: a box of 5 lines, here cyclic) and lengthens its exposure (850 against 170 µs: A = 5·box);
Harwit & Sloane's S-matrix lights (n + 1)/2 lines per capture. The stage's demultiplexing adds a smoothness
prior, which this study leaves out: it measures what the codes themselves give.

**Noise model** (the simulator's, ``selpath.devices.sim.procam_scene`` ``noise``): a capture of mean signal s counts has
shot noise of variance g·s (g counts per photo-electron; Poisson in electrons) and read noise of variance r²,
independent between captures (quantisation adds 1/12 count², included in r² here). The decoded lines then have

    Var(x̂) = diag(A⁻¹ · diag(g·A·x + r²) · A⁻ᵀ)

and SNR_j = x_j / √Var(x̂_j). Multiplexing gains where read noise dominates (for the S-matrix, (n + 1)/(2√n) as
g → 0) and loses where shot noise does (√((n + 1)/(2n)) as r → 0): more light per capture brings its own noise.

:func:`line_relighting_snr` measures the same trade on the simulated rig (Fig. 42): a line relit from a
demultiplexed delay–exposure stack (decoded *with* the smoothness and sparsity prior, so no closed form predicts
it) against the same line projected alone, at one scan's exposure and at many, each against the simulator's
noiseless render of that line. :func:`full_relighting_snr` does the same for full transport (Fig. 43): the scene
relit under a checkerboard and floodlit from a simplex and a multiplexed line sweep at the same capture count.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import xarray as xr

from selpath.devices.patterns import checkerboard
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.devices.sim.procam_transport import on_camera_rows, render_frame, seen_rows
from selpath.pipeline.constraints import Count, Fraction, Index, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.procam._scene_truth import simulated_scene
from selpath.stages.procam.acquire_patterns import exposure_window
from selpath.stages.procam.relight import relight, relight_full


def s_matrix(n: int) -> np.ndarray:
    """Harwit & Sloane's S-matrix of order n (n + 1 a power of 2): the normalised Sylvester–Hadamard matrix of
    order n + 1 without its first row and column, −1 → 1 (lit) and +1 → 0, so each capture lights (n + 1)/2 lines."""
    if n < 1 or (n + 1) & n:
        raise ValueError(f"an S-matrix from a Sylvester–Hadamard matrix needs n + 1 a power of 2; n = {n}")
    import scipy.linalg  # scipy when a code is made, not when a workflow is read

    return (scipy.linalg.hadamard(n + 1)[1:, 1:] < 0).astype(float)


def box_code(n: int, width: int) -> np.ndarray:
    """The thesis's wider lines as a cyclic code: capture i lights lines i … i + width − 1 (mod n). Invertible when
    gcd(n, width) = 1 (a circulant's DFT of a box vanishes otherwise)."""
    if np.gcd(n, width) != 1:
        raise ValueError(f"a cyclic box of {width} lines over {n} is singular (gcd {np.gcd(n, width)}); choose "
                         "coprime sizes")
    return np.array([np.roll(np.r_[np.ones(width), np.zeros(n - width)], i) for i in range(n)])


def predicted_variance(code: np.ndarray, x: np.ndarray, *, gain: float, read_std: float) -> np.ndarray:
    """Var(x̂) of every line under the noise model (module doc), for decoding by the code's inverse."""
    inverse = np.linalg.inv(code)
    noise = gain * (code @ x) + read_std**2
    return np.einsum("ji,i,ji->j", inverse, noise, inverse)


def measured_variance(code: np.ndarray, x: np.ndarray, *, gain: float, read_std: float, trials: int,
                      rng: np.random.Generator) -> np.ndarray:
    """Var(x̂) of every line over ``trials`` simulated measurements: Poisson photo-electrons times the gain, Gaussian
    read noise, decoded by the code's inverse (independently of :func:`predicted_variance`)."""
    mean = code @ x
    electrons = rng.poisson(np.broadcast_to(mean / gain, (trials, mean.size))) if gain > 0 else mean
    y = electrons * gain + rng.normal(0.0, read_std, (trials, mean.size))
    decoded = np.linalg.solve(code, y.T).T
    return ((decoded - x) ** 2).mean(axis=0)


_FRAME = ("row", "col")
MULTIPLEXING_STUDY = CubeKind(
    name="multiplexing_study",
    description="SNR gain of multiplexed line codes over simplex: noise model and simulation (§5.4.3)",
    variables={"predicted_gain_db": Variable(("signal", "code"), units="dB",
                                             long_name="SNR gain over simplex, noise model"),
               "measured_gain_db": Variable(("signal", "code"), units="dB",
                                            long_name="SNR gain over simplex, simulated"),
               "light_per_capture": Variable(("code",), False, units="1",
                                             long_name="light per capture, in single-line captures")},
    coord_units={"signal": frozenset({"counts"})},
)
LINE_RELIGHTING_SNR = CubeKind(
    name="line_relighting_snr",
    description="a line relit from a demultiplexed stack against the line projected alone, SNR (Fig. 42)",
    variables={"image": Variable(("method", *_FRAME), units="counts",
                                 long_name="the line's image (counts of one scan)"),
               "truth": Variable(_FRAME, units="counts", long_name="the line's image without noise"),
               "snr_db": Variable(("method",), units="dB", long_name="SNR on the lit pixels, measured"),
               "predicted_snr_db": Variable(("method",), False, units="dB",
                                            long_name="SNR on the lit pixels, noise model"),
               "saturated_fraction": Variable(("method",), False, units="1", long_name="lit pixels saturated"),
               "captures": Variable(("method",), False, units="1", long_name="captures"),
               "scans": Variable(("method",), False, units="1", long_name="scans per exposure")},
    attrs={"line_rows": "the line's camera rows [first, stop)",
           "lit_fraction": "lit pixels: truth at least this fraction of its maximum"},
)
RELIGHTING_SNR = CubeKind(
    name="relighting_snr",
    description="the scene relit from full transport under a checkerboard and floodlit, SNR (Fig. 43)",
    variables={"image": Variable(("pattern", *_FRAME), units="counts", long_name="relit from the transport"),
               "truth": Variable(("pattern", *_FRAME), units="counts", long_name="the pattern's image without noise"),
               "snr_db": Variable(("pattern",), units="dB", long_name="SNR on the lit pixels, measured")},
    attrs={"square_px": "checkerboard square, projector px",
           "lit_fraction": "lit pixels: truth at least this fraction of its maximum"},
)


@stage("multiplexing_gain_study", kind=MULTIPLEXING_STUDY)
def multiplexing_gain_study(*, lines: Count = 31,
                            signals: Annotated[tuple[Positive, ...], pydantic.Field(min_length=1)] = (
                                1.0, 10.0, 100.0, 1e3, 1e4, 1e5),
                            gain: NonNegative = 1.0, read_std: NonNegative = 10.0, box_width: Count = 5,
                            box_exposure: Positive = 5.0, trials: Count = 4000, seed: Index = 0) -> xr.Dataset:
    """SNR gain of multiplexed line codes over simplex, predicted by the noise model and measured by simulation.

    For each signal level (every line equally bright) and code (the thesis's box of ``box_width`` lines, and the
    S-matrix), the gain in dB of the decoded lines' SNR over simplex at the same capture count, from the closed
    form (module doc) and from ``trials`` simulated measurements. Shows where multiplexing stops helping: the gain
    falls below 0 dB once shot noise dominates.

    Parameters
    ----------
    lines : int
        Lines n (captures per measurement) [1]; n + 1 a power of 2 for the S-matrix (3, 7, 15, 31, 63, …), and
        coprime to box_width.
    signals : tuple of float
        Each line's signal when lit alone for one capture [counts].
    gain : float
        Counts per photo-electron g [counts]; 0: no shot noise.
    read_std : float
        Read noise per capture [counts].
    box_width : int
        Lines per capture of the thesis's code (l_w = 50 px over 10-px steps: 5).
    box_exposure : float
        Exposure of the box code's captures relative to simplex's [1] (the thesis: t_e = 850 against 170 µs, 5).
    trials : int
        Simulated measurements per signal level and code.
    seed : int
        Seed of the simulated noise.

    Returns
    -------
    xr.Dataset
        A ``multiplexing_study`` cube: ``predicted_gain_db`` and ``measured_gain_db`` [dB] of multiplexed codes over
        simplex, over (signal, code).

    References
    ----------
    Thesis §5.3.1 Illumination multiplexing; §5.4.3 Improving SNR by Multiplexing.
    """
    try:
        s = s_matrix(lines)
        codes = {"simplex": np.eye(lines), f"box{box_width}": box_exposure * box_code(lines, box_width),
                 "s_matrix": s}
    except ValueError as exc:
        raise StageError(Problem(str(exc), fix="lines = 2^k − 1 (e.g. 31) and a box_width coprime to it")) from None
    rng = np.random.default_rng(seed)
    predicted = np.zeros((len(signals), len(codes)))
    measured = np.zeros((len(signals), len(codes)))
    for i, signal in enumerate(signals):
        x = np.full(lines, float(signal))
        for j, code in enumerate(codes.values()):
            predicted[i, j] = predicted_variance(code, x, gain=gain, read_std=read_std).mean()
            measured[i, j] = measured_variance(code, x, gain=gain, read_std=read_std, trials=trials, rng=rng).mean()
    # SNR gain over simplex: the ratio of noise standard deviations, in dB (20·log10 of the amplitude ratio)
    gain_db = {name: 10 * np.log10(values[:, :1] / values) for name, values in (("predicted", predicted),
                                                                                  ("measured", measured))}
    dims = ("signal", "code")
    return MULTIPLEXING_STUDY.label(xr.Dataset(
        {"predicted_gain_db": (dims, gain_db["predicted"]), "measured_gain_db": (dims, gain_db["measured"]),
         "light_per_capture": ("code", [float(c.sum(axis=1).mean()) for c in codes.values()])},
        coords={"signal": ("signal", np.asarray(signals, float), {"units": "counts",
                                                                  "long_name": "signal of one line alone"}),
                "code": ("code", list(codes))},
        attrs={"lines": lines, "gain_counts_per_electron": gain, "read_std_counts": read_std, "trials": trials,
               "seed": seed}))


def noiseless(scene: ProcamScene) -> ProcamScene:
    """``scene`` on a rig without noise, dark level, quantisation or saturation: the signal itself."""
    return scene.with_rig(noise=None, bits=None, dark_level=0.0, saturation_level=np.inf)


def snr_db(estimate: np.ndarray, truth: np.ndarray) -> float:
    """10·log10(Σ truth² / Σ (estimate − truth)²) [dB]; +inf for an exact estimate."""
    error = float(np.sum((estimate - truth) ** 2))
    return float(10 * np.log10(np.sum(truth**2) / error)) if error > 0 else np.inf


def line_pattern(scene: ProcamScene, first: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """The projector pattern lighting camera rows [first, stop) (rows rectified as the simulator does) and the
    camera-row profile it gives (the virtual pattern to relight with)."""
    band = np.zeros(scene.rig.camera_rows)
    band[first:stop] = 1.0
    return projector_pattern(scene, np.repeat(band[:, None], scene.rig.projector_cols, axis=1)), band


@stage("line_relighting_snr", kind=LINE_RELIGHTING_SNR)
def line_relighting_snr(capture: xr.Dataset, transport: xr.Dataset, /, *, line: Fraction = 0.5,
                        line_rows: Count = 10, scans: Annotated[tuple[Count, ...], pydantic.Field(min_length=1)] = (
                            1, 50), lit_fraction: Fraction = 0.05) -> xr.Dataset:
    """A line relit from a demultiplexed stack against the line projected alone (Fig. 42), SNR against the truth.

    The simulator renders the truth (the line's image without noise, global shutter over the whole scan) and the
    single-line captures (global shutter, ``scans`` repeated scans per exposure: the thesis's 16 ms and 800 ms are
    1 and 50 frames of a 60 Hz projector); the relit image is ``relight(transport, line)``. SNR [dB] is
    10·log10(Σ truth² / Σ error²) over the *lit* pixels (truth ≥ ``lit_fraction`` of its maximum), where
    noise, not the camera's clipping at 0, sets the error. The single-line captures' SNR is also predicted from
    the rig's noise model: Var = (g·k·x + r² + q)/k² per pixel for k scans (q = 1/12 count² when the rig
    quantises); the demultiplexed image has no such prediction (the prior makes it nonlinear), only a
    measurement. Multiplexing wins where read noise dominates the single short capture (a dim scene); on a
    bright one the demultiplexing's resolution (about t_e·v_p rows) limits it instead.

    Parameters
    ----------
    capture : xr.Dataset
        The ``plane_to_ray_capture`` of the simulated rig the transport was demultiplexed from (its
        ``simulated_scene`` attr is the scene and rig to render the truth with).
    transport : xr.Dataset
        Its ``plane_to_ray_transport`` (``demux_plane_to_ray``).
    line : float
        The line's centre, as a fraction of the image height [1].
    line_rows : int
        The line's width in camera rows [px] (the thesis's single line; about t_e·v_p of the sweep's shortest
        exposure is what the stack resolves).
    scans : tuple of int
        Exposures of the single-line captures, in projector scans (frames) [1].
    lit_fraction : float
        Pixels whose true value is at least this fraction of the brightest count as lit [1].

    Returns
    -------
    xr.Dataset
        A ``line_relighting_snr`` cube: the relit line ``image`` over (method, row, col) and its ``truth`` (row, col)
        [counts], ``snr_db`` per method and, where the noise model predicts it, ``predicted_snr_db``.

    References
    ----------
    Thesis §5.4.3 Improving SNR by Multiplexing.
    """
    require_variables(transport, ("transport",), "line_relighting_snr")
    scene = simulated_scene(capture, "capture")
    rig = scene.rig
    rows = rig.camera_rows
    if (transport.sizes.get("row"), transport.sizes.get("col")) != (rows, rig.camera_cols):
        raise StageError(Problem(f"the transport is {transport.sizes.get('row')} × {transport.sizes.get('col')} px; "
                                 f"the capture's rig renders {rows} × {rig.camera_cols}", where="transport",
                                 fix="wire in the transport demultiplexed from this capture"))
    if line_rows > rows:
        raise StageError(Problem(f"line_rows is {line_rows}; the camera has {rows} rows", fix="a narrower line"))
    first = int(np.clip(round(line * (rows - 1)) - line_rows // 2, 0, rows - line_rows))
    pattern, row_pattern = line_pattern(scene, first, first + line_rows)
    delay, exposure = exposure_window(scene, "floodlit")
    truth = render_frame(noiseless(scene), delay, exposure, pattern, shutter="global").astype(float)
    if not truth.max() > 0:
        raise StageError(Problem(f"the line (camera rows {first}–{first + line_rows - 1}) lights nothing the camera "
                                 "sees", fix="move the line onto the scene"))
    lit = truth >= lit_fraction * truth.max()
    noise = rig.noise
    g = (noise.gain or 0.0) if noise is not None else 0.0
    r2 = (noise.read_std**2 if noise is not None else 0.0) + (1 / 12 if rig.bits is not None else 0.0)
    images = {"multiplexed (demultiplexed)": relight(transport["transport"], row_pattern).values.astype(float)}
    predicted, saturated, captures = [np.nan], [np.nan], [capture["image"].size // (rows * rig.camera_cols)]
    for k in scans:
        raw = render_frame(scene, delay, exposure, pattern, shutter="global", scans=k)
        images[f"single line, {k} scan{'s' if k > 1 else ''}"] = (raw.astype(float) - rig.dark_level) / k
        variance = (g * k * truth + r2) / k**2
        predicted.append(float(10 * np.log10(np.sum(truth[lit] ** 2) / np.sum(variance[lit])))
                         if np.sum(variance[lit]) > 0 else np.inf)
        saturated.append(float(np.mean(raw[lit] >= rig.saturation_level)))
        captures.append(1)
    measured = [snr_db(image[lit], truth[lit]) for image in images.values()]
    method = ("method", list(images))
    return LINE_RELIGHTING_SNR.label(xr.Dataset(
        {"image": (("method", "row", "col"), np.stack(list(images.values())).astype(np.float32)),
         "truth": (("row", "col"), truth.astype(np.float32)), "snr_db": ("method", measured),
         "predicted_snr_db": ("method", predicted), "saturated_fraction": ("method", saturated),
         "captures": ("method", captures), "scans": ("method", [np.nan, *map(float, scans)])},
        coords={"method": method, "row": ("row", np.arange(rows), {"units": "px"}),
                "col": ("col", np.arange(rig.camera_cols), {"units": "px"})},
        attrs={"line_rows": [first, first + line_rows],
               "lit_fraction": lit_fraction, "lit_pixels": int(lit.sum()), "intensity_counts": rig.intensity,
               "gain_counts_per_electron": g, "read_std_counts": noise.read_std if noise is not None else 0.0,
               "scene": scene.scene}))


def projector_pattern(scene: ProcamScene, on_camera: np.ndarray) -> np.ndarray:
    """A projector pattern whose rows, rectified onto camera rows, are ``on_camera`` (camera rows × projector
    columns): projector row p shows the first camera row that sees it (or the nearest above)."""
    rig = scene.rig
    seen = seen_rows(rig)
    first = np.searchsorted(seen, np.arange(rig.projector_rows), side="left").clip(0, rig.camera_rows - 1)
    pattern = on_camera[first]
    if not np.array_equal(on_camera_rows(rig, pattern), on_camera):
        raise StageError(Problem("camera rows that see the same projector row ask for different pattern rows",
                                 fix="a pattern constant over the camera rows of each projector row"))
    return pattern


@stage("full_relighting_snr", kind=RELIGHTING_SNR)
def full_relighting_snr(capture: xr.Dataset, transport: xr.Dataset, /, *, square_px: Count | None = None,
                        lit_fraction: Fraction = 0.05) -> xr.Dataset:
    """The scene relit from full transport under a checkerboard and floodlit, SNR against the truth (Fig. 43).

    Relit with :func:`selpath.stages.procam.relight.relight_full`; the truth is the simulator's noiseless render of the
    same projector patterns (global shutter over the whole scan). The checkerboard's squares are whole u-cells
    starting on a cell edge, so a transport recovered exactly relights exactly: what remains is noise and the
    demultiplexing's bias. SNR [dB] as in :func:`line_relighting_snr`, over each image's lit pixels. Run it on a
    simplex sweep (lines one cell wide, the shortest exposure) and a multiplexed one (wider lines, longer
    exposure, the same captures) to measure what multiplexing buys.

    Parameters
    ----------
    capture : xr.Dataset
        The ``full_transport_capture`` of the simulated rig the transport was demultiplexed from.
    transport : xr.Dataset
        Its ``full_transport`` (``demux_full``).
    square_px : int or None
        Checkerboard square [projector px], a whole number of u-cells; None: four u-cells.
    lit_fraction : float
        Pixels whose true value is at least this fraction of the brightest count as lit [1].

    Returns
    -------
    xr.Dataset
        A ``relighting_snr`` cube: the relit ``image`` and its ``truth`` [counts] over (pattern, row, col), and
        ``snr_db`` per pattern.

    References
    ----------
    Thesis §5.4.3 Improving SNR by Multiplexing.
    """
    require_variables(transport, ("transport", "u_direct"), "full_relighting_snr")
    scene = simulated_scene(capture, "capture")
    rig = scene.rig
    rows, cols = rig.camera_rows, rig.camera_cols
    step, cells = float(transport.attrs["cell_width_px"]), np.asarray(transport.attrs["cells_px"], float)
    square = max(1, round(4 * step)) if square_px is None else square_px
    phase = (cells[0] - step / 2) % step
    if not (np.isclose(square % step, 0) or np.isclose(square % step, step)) or not (
            np.isclose(phase, 0) or np.isclose(phase, step)):
        raise StageError(Problem(f"squares of {square} px on u-cells of {step:g} px starting at column "
                                 f"{cells[0] - step / 2:g} would split cells", fix="square_px a multiple of the "
                                 "cell width, on a sweep whose first line's left edge is a multiple of it"))
    square_rows = max(1, round(square * cols / rig.projector_cols))
    board = checkerboard((rows, rig.projector_cols), (square_rows, square))
    delay, exposure = exposure_window(scene, "floodlit")
    clean = noiseless(scene)
    images, truths = {}, {}
    for name, on_camera in (("checkerboard", board), ("floodlit", np.ones_like(board))):
        images[name] = relight_full(transport, on_camera).values.astype(float)
        pattern = None if name == "floodlit" else projector_pattern(scene, on_camera)
        truths[name] = render_frame(clean, delay, exposure, pattern, shutter="global").astype(float)
    lit = {n: truths[n] >= lit_fraction * truths[n].max() for n in truths}
    measured = [snr_db(images[n][lit[n]], truths[n][lit[n]]) for n in images]
    frame = ("row", "col")
    exposures = [float(e) for e in np.atleast_1d(capture["exposure"].values)]
    return RELIGHTING_SNR.label(xr.Dataset(
        {"image": (("pattern", *frame), np.stack(list(images.values())).astype(np.float32)),
         "truth": (("pattern", *frame), np.stack(list(truths.values())).astype(np.float32)),
         "snr_db": ("pattern", measured)},
        coords={"pattern": ("pattern", list(images))},
        attrs={"square_px": int(square), "square_rows": int(square_rows),
               "cell_width_px": step, "line_width_px": float(capture.attrs.get("line_width_px", np.nan)),
               "exposures_us": exposures, "captures": int(capture["image"].size // (rows * cols)),
               "lit_fraction": lit_fraction, "intensity_counts": rig.intensity, "scene": scene.scene}))
