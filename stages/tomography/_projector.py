"""The parallel-beam system operator R of Eq. 21–23 on the binned (θ, X) grid, matrix-free in JAX.

After alignment and binning every observed ray is a parallel-beam ray (DESIGN §6), so one operator serves
FBP and the optimisation. Conventions (DESIGN §8): the image covers ``[−L, L]²`` on an ``n × n`` grid of
cell centres ``x_m = −L + (m + ½)Δ`` (columns, object x) and ``y_k`` likewise (rows, object y, growing with
the row index); ray (θ, X) is the line ``p·(cos θ, sin θ) = X`` and its value is ∫σ along it.

Two discretisations:

* ``"joseph"`` (default): Joseph's ray-driven projector. A ray is walked along the axis it runs closest
  to (rows when |cos θ| ≥ |sin θ|), one cell per step, and σ is interpolated linearly across the other
  axis; each step has length Δ/|cos θ| (or Δ/|sin θ|). Accurate to O(Δ²) for smooth σ.
* ``"binary"``: the thesis's r_ij of Eq. 22: on each step the ray counts the one cell it hits (nearest),
  with weight Δ so that σ keeps its unit (absorption per length): r_ij ∈ {0, Δ}.

The adjoint is JAX's transpose of the same linear map (``jax.linear_transpose``), so ⟨Rx, y⟩ = ⟨x, Rᵀy⟩
holds to rounding by construction. FBP uses the pixel-driven back-projector :func:`backproject` instead
(the textbook one, linear interpolation in X), which is what scikit-image's ``iradon`` does.

Written by hand because no library in our stack offers a differentiable, batched, masked parallel-beam
projector on an arbitrary (θ, X) grid on CPU (ASTRA needs its own data layout and has no JAX transpose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np


@dataclass(frozen=True)
class Geometry:
    """The (θ, X) sinogram grid and the n × n image grid over [−extent, extent]²."""

    theta_deg: tuple[float, ...]
    x: tuple[float, ...]
    n: int
    extent: float
    method: Literal["joseph", "binary"] = "joseph"

    @classmethod
    def from_grids(cls, theta_deg, x, n: int, extent: float | None = None,
                   method: Literal["joseph", "binary"] = "joseph") -> Geometry:
        x = np.asarray(x, dtype=float)
        extent = float(extent if extent is not None else max(abs(x[0]), abs(x[-1])))
        return cls(tuple(np.asarray(theta_deg, dtype=float).tolist()), tuple(x.tolist()), int(n), extent, method)

    @property
    def cell(self) -> float:
        return 2 * self.extent / self.n

    @property
    def centres(self) -> np.ndarray:
        return -self.extent + (np.arange(self.n) + 0.5) * self.cell

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.theta_deg), len(self.x))

    def _by_axis(self) -> tuple[np.ndarray, np.ndarray]:
        t = np.deg2rad(np.asarray(self.theta_deg))
        rows = np.abs(np.cos(t)) >= np.abs(np.sin(t))
        return np.flatnonzero(rows), np.flatnonzero(~rows)


def _walk(image: jnp.ndarray, along: jnp.ndarray, across: jnp.ndarray, xs: jnp.ndarray, centres: jnp.ndarray,
          cell: float, origin: float, nearest: bool) -> jnp.ndarray:
    """Sum over the steps k of ``image[k, ·]`` sampled at ``(xs − centres[k]·across) / along``.

    ``image``: (n, n) with the walked axis first; ``along``, ``across``: (T,) direction cosines of the
    normal; ``xs``: (X,). Returns (T, X). The position on step k solves along·u + across·c_k = X.
    """
    n = image.shape[1]
    u = (xs[None, None, :] - centres[None, :, None] * across[:, None, None]) / along[:, None, None]  # (T, n, X)
    s = (u - origin) / cell - 0.5  # fractional column index
    weight = cell / jnp.abs(along)[:, None]
    rows = jnp.arange(image.shape[0])[None, :, None]
    if nearest:
        i = jnp.round(s).astype(jnp.int32)
        inside = (i >= 0) & (i < n)
        values = jnp.where(inside, image[rows, jnp.clip(i, 0, n - 1)], 0.0)
        return values.sum(axis=1) * cell
    i0 = jnp.floor(s).astype(jnp.int32)
    w1 = (s - i0).astype(image.dtype)
    v0 = jnp.where((i0 >= 0) & (i0 < n), image[rows, jnp.clip(i0, 0, n - 1)], 0.0)
    v1 = jnp.where((i0 + 1 >= 0) & (i0 + 1 < n), image[rows, jnp.clip(i0 + 1, 0, n - 1)], 0.0)
    return ((1 - w1) * v0 + w1 * v1).sum(axis=1) * weight.astype(image.dtype)


def forward(geometry: Geometry, image: jnp.ndarray) -> jnp.ndarray:
    """R σ: the (θ, X) sinogram of an (n, n) image [(y, x) indexing], or of a (..., n, n) batch."""
    if image.ndim > 2:
        return jax.vmap(lambda im: forward(geometry, im))(image.reshape(-1, *image.shape[-2:])).reshape(
            *image.shape[:-2], *geometry.shape)
    dtype = image.dtype
    t = np.deg2rad(np.asarray(geometry.theta_deg))
    c, s = jnp.asarray(np.cos(t), dtype), jnp.asarray(np.sin(t), dtype)
    xs, centres = jnp.asarray(geometry.x, dtype), jnp.asarray(geometry.centres, dtype)
    by_rows, by_cols = geometry._by_axis()
    nearest = geometry.method == "binary"
    out = jnp.zeros(geometry.shape, dtype)
    origin = -geometry.extent
    if len(by_rows):  # step through rows y_k, interpolate along x: cos θ·x + sin θ·y_k = X
        out = out.at[by_rows].set(_walk(image, c[by_rows], s[by_rows], xs, centres, geometry.cell, origin, nearest),
                                   unique_indices=True)
    if len(by_cols):  # step through columns x_m, interpolate along y
        out = out.at[by_cols].set(_walk(image.T, s[by_cols], c[by_cols], xs, centres, geometry.cell, origin,
                                        nearest), unique_indices=True)
    return out


def adjoint(geometry: Geometry, sinogram: jnp.ndarray) -> jnp.ndarray:
    """Rᵀ y: the exact transpose of :func:`forward` (for one (θ, X) sinogram or a batch)."""
    if sinogram.ndim > 2:
        return jax.vmap(lambda s: adjoint(geometry, s))(sinogram.reshape(-1, *sinogram.shape[-2:])).reshape(
            *sinogram.shape[:-2], geometry.n, geometry.n)
    template = jax.ShapeDtypeStruct((geometry.n, geometry.n), sinogram.dtype)
    (out,) = jax.linear_transpose(lambda im: forward(geometry, im), template)(sinogram)
    return out


def system_matrix(geometry: Geometry, dtype=np.float32):
    """R as a sparse (T·X rays × n·n cells) CSR matrix, row θ_i·X + j for ray (θ_i, X_j), column y·n + x: the
    same weights :func:`forward` applies (Joseph's two interpolation weights per step, or the binary r_ij = Δ),
    built in numpy one angle at a time (``scipy.sparse``; about 2·n nonzeros per ray: 40 M, 0.3 GB in float32, at
    256² and 360 × 256 rays).

    Why: one matrix serves every slice of a volume (the bins are the same (θ, X) grid in each), so R·[σ₁ … σ_S] is
    one sparse–dense product; ``benchmarks/tomo_projector.py`` measures it against the matrix-free walk.
    """
    import scipy.sparse as sparse

    t = np.deg2rad(np.asarray(geometry.theta_deg))
    cos, sin = np.cos(t), np.sin(t)
    xs, centres, n, cell = np.asarray(geometry.x), geometry.centres, geometry.n, geometry.cell
    steps = np.arange(n)[:, None]
    rows, cols, values = [], [], []
    for i in range(len(t)):
        by_rows = abs(cos[i]) >= abs(sin[i])
        along, across = (cos[i], sin[i]) if by_rows else (sin[i], cos[i])
        s = ((xs[None, :] - centres[:, None] * across) / along + geometry.extent) / cell - 0.5  # (steps, X)
        if geometry.method == "binary":
            taps = ((np.round(s).astype(np.int64), np.full(s.shape, cell)),)
        else:
            i0 = np.floor(s).astype(np.int64)
            w1 = s - i0
            taps = ((i0, (1 - w1) * cell / abs(along)), (i0 + 1, w1 * cell / abs(along)))
        ray = i * len(xs) + np.broadcast_to(np.arange(len(xs))[None, :], s.shape)
        step = np.broadcast_to(steps, s.shape)
        for index, weight in taps:
            keep = (index >= 0) & (index < n) & (weight != 0)
            rows.append(ray[keep])
            cols.append(step[keep] * n + index[keep] if by_rows else index[keep] * n + step[keep])
            values.append(weight[keep].astype(dtype))
    shape = (len(t) * len(xs), n * n)
    return sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=shape)


def backproject(geometry: Geometry, sinogram: jnp.ndarray) -> jnp.ndarray:
    """Pixel-driven back-projection Σ_θ q(θ, x cos θ + y sin θ)·Δθ (linear in X; zero off the grid)."""
    t = np.deg2rad(np.asarray(geometry.theta_deg))
    dtype = sinogram.dtype
    centres = jnp.asarray(geometry.centres, dtype)
    yy, xx = jnp.meshgrid(centres, centres, indexing="ij")
    xs = np.asarray(geometry.x)
    step = (xs[-1] - xs[0]) / (len(xs) - 1)

    def one(q, angle):
        proj = xx * jnp.cos(angle) + yy * jnp.sin(angle)
        s = (proj - xs[0]) / step
        i0 = jnp.floor(s).astype(jnp.int32)
        w1 = s - i0
        n = q.shape[0]
        v0 = jnp.where((i0 >= 0) & (i0 < n), q[jnp.clip(i0, 0, n - 1)], 0.0)
        v1 = jnp.where((i0 + 1 >= 0) & (i0 + 1 < n), q[jnp.clip(i0 + 1, 0, n - 1)], 0.0)
        return (1 - w1) * v0 + w1 * v1

    angles = jnp.asarray(t, dtype)
    total = jax.lax.fori_loop(0, len(t), lambda i, acc: acc + one(sinogram[i], angles[i]),
                              jnp.zeros((geometry.n, geometry.n), dtype))
    return total * (np.pi / len(t))


def operator_norm(geometry: Geometry, mask: jnp.ndarray | None = None, *, iterations: int = 30,
                  dtype=jnp.float32) -> jnp.ndarray:
    """‖M R‖₂ by power iteration on RᵀMR (deterministic start), used to balance step sizes."""
    m = jnp.ones(geometry.shape, dtype) if mask is None else mask.astype(dtype)
    v = jnp.ones((geometry.n, geometry.n), dtype) / geometry.n

    def body(_, v):
        w = adjoint(geometry, m * forward(geometry, v))
        return w / jnp.maximum(jnp.linalg.norm(w), jnp.finfo(dtype).tiny)

    v = jax.lax.fori_loop(0, iterations, body, v)
    return jnp.sqrt(jnp.linalg.norm(adjoint(geometry, m * forward(geometry, v))))
