"""The parallel-beam system operator R of Eq. 21–23 on the binned (θ, X) grid: a matrix-free walk in JAX, and the
same weights as a sparse system matrix (:func:`system_matrix`) for batches of slices.

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
projector on an arbitrary (θ, X) grid on CPU (ASTRA needs its own data layout and has no JAX transpose). Only the
walk and :class:`MatrixProjector` are differentiable; :class:`HostProjector` runs through ``jax.pure_callback``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import sparse


@dataclass(frozen=True)
class Geometry:
    """The (θ, X) sinogram grid and the n × n image grid over [−extent, extent]²."""

    theta_deg: tuple[float, ...]
    x: tuple[float, ...]
    n: int
    extent: float
    method: Literal["joseph", "binary"] = "joseph"

    def __post_init__(self):  # tuples of floats: the geometry is a static (hashed) argument of the jitted walk
        for name in ("theta_deg", "x"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))

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


@partial(jax.jit, static_argnums=(4, 5, 6))
def _taps(along: jnp.ndarray, across: jnp.ndarray, xs: jnp.ndarray, centres: jnp.ndarray, cell: float,
          origin: float, nearest: bool) -> tuple[tuple[jnp.ndarray, jnp.ndarray], ...]:
    """The cells each step of each ray reads: ((index, weight), …), each (T, n steps, X), the index along the
    interpolated axis (possibly off the grid) and its weight. ``along``, ``across``: (T,) direction cosines of the
    normal; ``xs``: (X,). The position on step k solves along·u + across·c_k = X. One function for the walk and the
    system matrix, so both round a binary ray's tie the same way."""
    u = (xs[None, None, :] - centres[None, :, None] * across[:, None, None]) / along[:, None, None]  # (T, n, X)
    s = (u - origin) / cell - 0.5  # fractional column index
    if nearest:
        return ((jnp.round(s).astype(jnp.int32), jnp.full_like(s, cell)),)
    i0 = jnp.floor(s).astype(jnp.int32)
    w1 = s - i0
    weight = cell / jnp.abs(along)[:, None, None]
    return (i0, (1 - w1) * weight), (i0 + 1, w1 * weight)


def _walk(image: jnp.ndarray, taps) -> jnp.ndarray:
    """Σ over the steps k and the taps of ``weight · image[k, index]`` (0 off the grid): (T, X) from an (n, n) image
    with the walked axis first."""
    n = image.shape[1]
    rows = jnp.arange(image.shape[0])[None, :, None]
    return sum(jnp.where((i >= 0) & (i < n), image[rows, jnp.clip(i, 0, n - 1)], 0.0) * w.astype(image.dtype)
               for i, w in taps).sum(axis=1)


def _groups(geometry: Geometry, dtype):
    """Per walking axis: (whether it walks the rows, the angles' indices, their taps in ``dtype``)."""
    t = np.deg2rad(np.asarray(geometry.theta_deg))
    c, s = np.cos(t), np.sin(t)
    xs, centres = np.asarray(geometry.x, dtype), np.asarray(geometry.centres, dtype)
    nearest, origin = geometry.method == "binary", -geometry.extent
    by_rows, by_cols = geometry._by_axis()
    # rows: step through y_k, interpolate along x (cos θ·x + sin θ·y_k = X); columns: the other way round (the
    # grids cast on the host and handed to the jitted taps: eager device indexing and casts compile per shape)
    return tuple((rows, index, _taps(np.asarray(along[index], dtype), np.asarray(across[index], dtype), xs, centres,
                                     geometry.cell, origin, nearest))
                 for rows, index, along, across in ((True, by_rows, c, s), (False, by_cols, s, c)) if len(index))


@partial(jax.jit, static_argnums=0)
def forward(geometry: Geometry, image: jnp.ndarray) -> jnp.ndarray:
    """R σ: the (θ, X) sinogram of an (n, n) image [(y, x) indexing], or of a (..., n, n) batch (one compiled walk
    per geometry, shape and dtype)."""
    if image.ndim > 2:
        return jax.vmap(lambda im: forward(geometry, im))(image.reshape(-1, *image.shape[-2:])).reshape(
            *image.shape[:-2], *geometry.shape)
    out = jnp.zeros(geometry.shape, image.dtype)
    for by_rows, index, taps in _groups(geometry, image.dtype):
        out = out.at[index].set(_walk(image if by_rows else image.T, taps), unique_indices=True)
    return out


@partial(jax.jit, static_argnums=0)
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
    taken from the walk's own taps (``scipy.sparse``; about 2·n nonzeros per ray: 40 M, 0.3 GB in float32, at
    256² and 360 × 256 rays).

    Why: one matrix serves every slice of a volume (the bins are the same (θ, X) grid in each), so R·[σ₁ … σ_S] is
    one sparse–dense product; ``benchmarks/tomo_projector.py`` measures it against the matrix-free walk.
    """
    import scipy.sparse

    n, count = geometry.n, len(geometry.x)
    rows, cols, values = [], [], []
    with jax.enable_x64(np.dtype(dtype) == np.float64):
        for by_rows, index, taps in _groups(geometry, np.dtype(dtype)):
            shape = (len(index), n, count)
            ray = np.broadcast_to(index[:, None, None] * count + np.arange(count)[None, None, :], shape)
            step = np.broadcast_to(np.arange(n)[None, :, None], shape)
            for where, weight in taps:
                where, weight = np.asarray(where), np.asarray(weight)
                keep = (where >= 0) & (where < n) & (weight != 0)
                rows.append(ray[keep])
                cols.append(step[keep] * n + where[keep] if by_rows else where[keep] * n + step[keep])
                values.append(weight[keep])
    return scipy.sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(len(geometry.theta_deg) * count, n * n))


def backproject(geometry: Geometry, sinogram: jnp.ndarray) -> jnp.ndarray:
    """Pixel-driven back-projection Σ_θ q(θ, x cos θ + y sin θ)·Δθ (linear in X; zero off the grid) of one (θ, X)
    sinogram, (n, n), or of a (S, θ, X) batch, (S, n, n): one compiled loop per geometry, shape and dtype."""
    if sinogram.ndim == 2:
        return _backproject(geometry, sinogram[None])[0]
    return _backproject(geometry, sinogram)


def _bin_position(geometry: Geometry, angle, dtype):
    """Each cell centre's fractional X bin index at θ = ``angle`` [rad], (n, n) [(y, x) indexing]."""
    centres = jnp.asarray(geometry.centres, dtype)
    xs = np.asarray(geometry.x)
    step = (xs[-1] - xs[0]) / (len(xs) - 1)
    return (centres[None, :] * jnp.cos(angle) + centres[:, None] * jnp.sin(angle) - xs[0]) / step


@partial(jax.jit, static_argnums=0)
def _backproject(geometry: Geometry, sinogram: jnp.ndarray) -> jnp.ndarray:
    dtype, count = sinogram.dtype, sinogram.shape[-1]
    angles = jnp.asarray(np.deg2rad(np.asarray(geometry.theta_deg)), dtype)

    def add(i, total):
        s = _bin_position(geometry, angles[i], dtype)
        i0 = jnp.floor(s).astype(jnp.int32)
        w1 = s - i0
        q = sinogram[:, i]  # (S, X)
        v0 = jnp.where((i0 >= 0) & (i0 < count), jnp.take(q, jnp.clip(i0, 0, count - 1), axis=1), 0.0)
        v1 = jnp.where((i0 >= -1) & (i0 < count - 1), jnp.take(q, jnp.clip(i0 + 1, 0, count - 1), axis=1), 0.0)
        return total + (1 - w1) * v0 + w1 * v1

    total = jax.lax.fori_loop(0, len(geometry.theta_deg), add,
                              jnp.zeros((sinogram.shape[0], geometry.n, geometry.n), dtype))
    return total * (np.pi / len(geometry.theta_deg))


def any_nearest(geometry: Geometry, flagged: np.ndarray) -> np.ndarray:
    """Per cell, whether at some θ its nearest X bin is ``flagged`` (or off the grid): (n, n) from one (θ, X) mask,
    (S, n, n) from a (S, θ, X) batch. Bin positions are computed in float64 whatever the data's dtype, so ties
    round as ``np.rint`` does."""
    flagged = np.asarray(flagged, bool)
    with jax.enable_x64(True):
        out = np.asarray(_any_nearest(geometry, jnp.asarray(flagged.reshape(-1, *flagged.shape[-2:]))))
    return out.reshape(*flagged.shape[:-2], geometry.n, geometry.n)


@partial(jax.jit, static_argnums=0)
def _any_nearest(geometry: Geometry, flagged: jnp.ndarray) -> jnp.ndarray:
    count = flagged.shape[-1]
    angles = jnp.asarray(np.deg2rad(np.asarray(geometry.theta_deg)), jnp.float64)

    def step(i, seen):
        j = jnp.rint(_bin_position(geometry, angles[i], jnp.float64)).astype(jnp.int32)
        off = (j < 0) | (j >= count)
        return seen | off | jnp.take(flagged[:, i], jnp.clip(j, 0, count - 1), axis=1)

    return jax.lax.fori_loop(0, len(geometry.theta_deg), step,
                             jnp.zeros((flagged.shape[0], geometry.n, geometry.n), bool))


class WalkProjector(NamedTuple):
    """R and Rᵀ by the matrix-free walk (:func:`forward`, :func:`adjoint`): no memory beyond one product's
    temporaries, ~0.36 s a forward–adjoint pair at 256²/360 (batches help little)."""

    def forward(self, geometry: Geometry, images: jnp.ndarray) -> jnp.ndarray:
        return forward(geometry, images)

    def adjoint(self, geometry: Geometry, sinograms: jnp.ndarray) -> jnp.ndarray:
        return adjoint(geometry, sinograms)


class MatrixProjector(NamedTuple):
    """R and Rᵀ as JAX sparse matrices (:func:`system_matrix`): a batch of S slices (S, n, n) is one sparse–dense
    product, ~4 ms a forward–adjoint pair per slice at 256²/360 in batches of 32 (100× the walk), no faster than the
    walk for one slice (:class:`HostProjector` is); 2 × 8 bytes a nonzero. A pytree: pass it to jitted functions as
    an argument (closed over, XLA constant-folds its indices for minutes)."""

    rays: sparse.BCSR  # R, (T·X, n²)
    cells: sparse.BCSR  # Rᵀ, (n², T·X)

    @classmethod
    def build(cls, geometry: Geometry, dtype=np.float32) -> MatrixProjector:
        matrix = system_matrix(geometry, dtype)
        return cls(sparse.BCSR.from_scipy_sparse(matrix), sparse.BCSR.from_scipy_sparse(matrix.T.tocsr()))

    @staticmethod
    def nbytes(geometry: Geometry, dtype=np.float32) -> int:
        """An upper bound on R and Rᵀ's memory: two taps per step of every ray, each a value and an int32 index,
        twice. Building them takes about four times this at its peak (the taps, COO lists, the transpose)."""
        return 2 * 2 * geometry.n * len(geometry.theta_deg) * len(geometry.x) * (np.dtype(dtype).itemsize + 4)

    def forward(self, geometry: Geometry, images: jnp.ndarray) -> jnp.ndarray:
        columns = images.reshape(-1, geometry.n * geometry.n).T
        return (self.rays @ columns).T.reshape(*images.shape[:-2], *geometry.shape)

    def adjoint(self, geometry: Geometry, sinograms: jnp.ndarray) -> jnp.ndarray:
        columns = sinograms.reshape(-1, sinograms.shape[-2] * sinograms.shape[-1]).T
        return (self.cells @ columns).T.reshape(*sinograms.shape[:-2], geometry.n, geometry.n)


@jax.tree_util.register_pytree_node_class
class HostProjector:
    """R and Rᵀ as scipy CSR matrices multiplied on the host (:func:`system_matrix`), each split into row blocks that
    ``threads`` threads multiply at once (scipy's sparse products release the GIL), reached from jitted code through
    ``jax.pure_callback``: ~26 ms a forward–adjoint pair for one slice at 256²/360 on 2 cores (14× the walk, where
    JAX's BCSR matrix–vector product is no faster than the walk), ~5 ms per slice in batches of 32 (BCSR: 4 ms).
    A pytree with no leaves whose identity is its static part: jitted functions that take it compile once per
    instance (keep one per geometry)."""

    def __init__(self, matrix, threads: int | None = None):
        import os
        from concurrent.futures import ThreadPoolExecutor

        threads = threads or len(os.sched_getaffinity(0)) or 1  # the cores this process may use
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="selpath-projector")

        def blocks(m):
            edges = np.linspace(0, m.shape[0], threads + 1).astype(int)
            return [m[a:b] for a, b in zip(edges[:-1], edges[1:], strict=True)]

        self._rays, self._cells = blocks(matrix), blocks(matrix.T.tocsr())

    @classmethod
    def build(cls, geometry: Geometry, dtype=np.float32, threads: int | None = None) -> HostProjector:
        return cls(system_matrix(geometry, dtype), threads)

    def tree_flatten(self):
        return (), self

    @classmethod
    def tree_unflatten(cls, aux, children):
        return aux

    def _product(self, blocks, values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        values = np.asarray(values)
        columns = np.ascontiguousarray(values.reshape(-1, values.shape[-2] * values.shape[-1]).T)
        out = np.vstack(list(self._pool.map(lambda block: block @ columns, blocks)))
        return out.T.reshape(*values.shape[:-2], *shape).astype(values.dtype, copy=False)

    def forward(self, geometry: Geometry, images: jnp.ndarray) -> jnp.ndarray:
        out = jax.ShapeDtypeStruct((*images.shape[:-2], *geometry.shape), images.dtype)
        return jax.pure_callback(lambda x: self._product(self._rays, x, geometry.shape), out, images,
                                 vmap_method="broadcast_all")

    def adjoint(self, geometry: Geometry, sinograms: jnp.ndarray) -> jnp.ndarray:
        out = jax.ShapeDtypeStruct((*sinograms.shape[:-2], geometry.n, geometry.n), sinograms.dtype)
        return jax.pure_callback(lambda y: self._product(self._cells, y, (geometry.n, geometry.n)), out, sinograms,
                                 vmap_method="broadcast_all")


def operator_norm(geometry: Geometry, mask: jnp.ndarray | None = None, *, iterations: int = 30,
                  dtype=jnp.float32,
                  projector: WalkProjector | MatrixProjector | HostProjector = WalkProjector(),  # noqa: B008 (no state)
                  ) -> jnp.ndarray:
    """‖M R‖₂ by power iteration on RᵀMR (deterministic start), used to balance step sizes; for a batch of masks
    (S, T, X), one norm per slice (S,)."""
    m = jnp.ones(geometry.shape, dtype) if mask is None else mask.astype(dtype)
    cells = (-2, -1)
    v = jnp.ones((*m.shape[:-2], geometry.n, geometry.n), dtype) / geometry.n

    def normal(v):
        return projector.adjoint(geometry, m * projector.forward(geometry, v))

    def body(_, v):
        w = normal(v)
        size = jnp.sqrt(jnp.sum(w * w, axis=cells, keepdims=True))
        return w / jnp.maximum(size, jnp.finfo(dtype).tiny)

    v = jax.lax.fori_loop(0, iterations, body, v)
    w = normal(v)
    return jnp.sqrt(jnp.sqrt(jnp.sum(w * w, axis=cells)))
