"""The navigation loop on realistic skies (``polins simulate --sky realistic``): the images'
errors are correlated from image to image, and the default heading-bias state keeps the fused
heading honest (docs/filter.md §5.7)."""

import numpy as np
import pytest

from polins.evaluation import solution_errors
from polins.fusion.config import FuseConfig
from polins.io import read_log
from polins.loop.offline import run_log
from polins.sim.scenario import simulate_log


def _heading_z(log, **options):
    """Heading error / sigma after the first 5 s of the loop's ESKF solution."""
    config = FuseConfig.from_log(log).replace(**options)
    result = run_log(log, config=config, workers=1, progress=False)
    sol = result.solution
    err = solution_errors(sol, log.truth)
    keep = (sol["t"] > 5.0).to_numpy() & np.isfinite(sol["yaw_std"].to_numpy())
    return err["yaw_err"].to_numpy()[keep] / sol["yaw_std"].to_numpy()[keep]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_fused_heading_is_honest_on_realistic_skies(tmp_path, seed):
    # 120 s of the README's MEMS UGV flow under a realistic sky: the images' sigmas cover
    # their errors, which are shared by consecutive images; without the bias state the filter
    # averages them down (RMS(err/sigma) 3.8-5.9 over 300 s), with the defaults it does not
    sim = simulate_log(tmp_path, scenario="ugv", imu="mems-typical", duration_s=120.0,
                       seed=seed, sky="realistic", progress=False)  # fmt: skip
    log = read_log(sim.manifest)
    z_default = _heading_z(log)
    z_off = _heading_z(log, heading_bias_std="off")
    rms_default = float(np.sqrt(np.mean(z_default**2)))
    rms_off = float(np.sqrt(np.mean(z_off**2)))
    assert rms_off > 1.5, rms_off
    assert 0.3 < rms_default < 1.3, rms_default
    assert np.mean(np.abs(z_default) <= 3.0) >= 0.985
