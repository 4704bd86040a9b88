"""§4.4.1 as a stage, and every shipped workflow validates."""

from __future__ import annotations

import pytest

from selpath import workflows
from selpath.pipeline.spec import load_workflow
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.studies import light_angle_study

#: those that read another's output (workflows.AFTER) validate only once it exists: test_cli covers them
WORKFLOWS = [workflows.path(name) for name in workflows.names() if name not in workflows.AFTER]


def test_light_angle_study_shows_the_thesis_trend():
    """Table 1's trend at a small size: at θ_l = 30° (both sides missing) the optimisation beats FBP and
    does better than at 120° (centre missing, past (180° − 32°)/2 = 74°)."""
    study = light_angle_study(scene=workflows.scene("phantom-cylinder"), light_angles=(30.0, 120.0),
                              n_theta=45, n_x=48, angles=AngleSweep(step=4.0), max_iter=100,
                              tv_weight=1e-4).compute()

    def rmse(angle, method):  # (``method`` is also a keyword of .sel: select with a dict)
        return float(study["rmse"].sel({"light_angle": angle, "method": method}))

    assert rmse(30, "optimisation") < rmse(30, "fbp")
    assert rmse(30, "optimisation") < rmse(120, "optimisation")
    assert float(study["observed_fraction"].sel(light_angle=30)) > float(
        study["observed_fraction"].sel(light_angle=120))


@pytest.mark.parametrize("path", WORKFLOWS, ids=[p.name for p in WORKFLOWS])
def test_shipped_workflows_validate(path):
    assert load_workflow(path).steps
