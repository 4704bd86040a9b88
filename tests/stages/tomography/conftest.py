"""The σ_s = 1 Monte Carlo capture that the scattering and σ_s-estimate tests share: built once for the package."""

from __future__ import annotations

import pytest

from tests.stages.tomography.scattering_scenes import scattering_capture


@pytest.fixture(scope="package")
def seed0():
    """:func:`scattering_capture` with scattering seed 0: (rays, sinogram, hull, truth, capture)."""
    return scattering_capture(0)
