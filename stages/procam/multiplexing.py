"""Illumination multiplexing and SNR (thesis §5.3.1, §5.4.3; its future work: Hadamard codes, §6.2).

n line intensities x [counts a line gives when lit alone for one capture] are measured in n captures under a
*code* A (captures × lines: how much of each line's light each capture gets) and decoded by x̂ = A⁻¹·y, without a
prior. Simplex is A = I (one line per capture); the thesis's multiplexing widens each capture's line (l_w = 50 px
over 10-px steps: a box of 5 lines, here cyclic) and lengthens its exposure (850 against 170 µs: A = 5·box);
Harwit & Sloane's S-matrix lights (n + 1)/2 lines per capture. The stage's demultiplexing adds a smoothness
prior, which this study leaves out: it measures what the codes themselves give.

**Noise model** (the simulator's, ``devices.sim.procam_scene`` ``noise``): a capture of mean signal s counts has
shot noise of variance g·s (g counts per photo-electron; Poisson in electrons) and read noise of variance r²,
independent between captures (quantisation adds 1/12 count², included in r² here). The decoded lines then have

    Var(x̂) = diag(A⁻¹ · diag(g·A·x + r²) · A⁻ᵀ)

and SNR_j = x_j / √Var(x̂_j). Multiplexing gains where read noise dominates (for the S-matrix, (n + 1)/(2√n) as
g → 0) and loses where shot noise does (√((n + 1)/(2n)) as r → 0): more light per capture brings its own noise.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pydantic
import scipy.linalg
import xarray as xr

from pipeline.constraints import Count, Index, NonNegative, Positive
from pipeline.errors import Problem, StageError
from pipeline.registry import stage


def s_matrix(n: int) -> np.ndarray:
    """Harwit & Sloane's S-matrix of order n (n + 1 a power of 2): the normalised Sylvester–Hadamard matrix of
    order n + 1 without its first row and column, −1 → 1 (lit) and +1 → 0, so each capture lights (n + 1)/2 lines."""
    if n < 1 or (n + 1) & n:
        raise ValueError(f"an S-matrix from a Sylvester–Hadamard matrix needs n + 1 a power of 2; n = {n}")
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


@stage("multiplexing_gain_study")
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
    return xr.Dataset(
        {"predicted_gain_db": (dims, gain_db["predicted"], {"units": "dB", "long_name": "SNR gain over simplex, "
                                                            "noise model"}),
         "measured_gain_db": (dims, gain_db["measured"], {"units": "dB", "long_name": "SNR gain over simplex, "
                                                          "simulated"}),
         "light_per_capture": ("code", [float(c.sum(axis=1).mean()) for c in codes.values()],
                               {"units": "1", "long_name": "light per capture, in single-line captures"})},
        coords={"signal": ("signal", np.asarray(signals, float), {"units": "counts",
                                                                  "long_name": "signal of one line alone"}),
                "code": ("code", list(codes))},
        attrs={"selpath_kind": "multiplexing_study", "lines": lines, "gain_counts_per_electron": gain,
               "read_std_counts": read_std, "trials": trials, "seed": seed})
