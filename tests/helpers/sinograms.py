"""Analytic sinograms of disks (their Radon transform in closed form), for the reconstruction tests."""

from __future__ import annotations

import numpy as np
import xarray as xr

L = 1.0


DISKS = (((0.2, -0.1), 0.3, 0.2), ((-0.4, 0.3), 0.2, 0.1), ((0.0, 0.0), 0.8, 0.05))


def disk_radon(theta_deg, x, disks=DISKS):
    n = np.stack([np.cos(np.deg2rad(theta_deg)), np.sin(np.deg2rad(theta_deg))], -1)
    return sum(2 * s * np.sqrt(np.clip(r**2 - (x - n @ np.asarray(c)) ** 2, 0, None)) for c, r, s in disks)


def sinogram(n_theta=90, n_x=64, observed=None, values=None) -> xr.Dataset:
    theta = np.arange(n_theta) * 180.0 / n_theta
    x = np.linspace(-L, L, n_x)
    values = disk_radon(theta[:, None], x[None, :]) if values is None else values
    observed = np.ones(values.shape, bool) if observed is None else observed
    dims = ("slice", "theta", "x")
    return xr.Dataset({"absorption": (dims, values[None]), "observed": (dims, observed[None])},
                      coords={"slice": [0], "theta": ("theta", theta, {"units": "degree"}),
                              "x": ("x", x, {"units": "mm"})}, attrs={"x_extent": L}).chunk({"slice": 1})
