"""docs/streaming.md's complete loop, as written, on a simulated UGV drive: its heading
against the truth, and its sigma against its error."""

from __future__ import annotations

import numpy as np
import pytest
from test_docs import ROOT, parse_blocks

from polins.evaluation import truth_at
from polins.frames import wrap_angle
from polins.io import read_log

DURATION_S = 30.0
SETTLE_S = 5.0  # levelling (1 s), the yaw acquisition (3 images), the first updates


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """``polins simulate --scenario ugv --imu mems-typical``: 30 s, images at 5 Hz, 1/8."""
    from polins.sim.scenario import simulate_log

    folder = tmp_path_factory.mktemp("stream-ugv")
    simulate_log(folder / "drive", scenario="ugv", duration_s=DURATION_S, image_rate_hz=5.0,
                 downscale=8, imu="mems-typical", seed=11, progress=False)  # fmt: skip
    return folder


def complete_loop() -> str:
    """The page's block that replays a recorded drive through the stream."""
    blocks = [b for b in parse_blocks(ROOT / "docs" / "streaming.md") if b.lang == "python"]
    loops = [b for b in blocks if 'read_log("drive")' in b.code]
    assert len(loops) == 1
    return loops[0].source()


def test_the_pages_loop_on_a_simulated_ugv(drive, monkeypatch):
    monkeypatch.chdir(drive)
    namespace: dict = {"__name__": "__main__"}
    exec(compile(complete_loop(), "docs/streaming.md", "exec"), namespace)
    solution = namespace["solution"]
    truth = read_log(drive / "drive").truth
    assert len(solution) == 301  # 30 s at the default 10 rows per second, both ends
    sol = solution[solution["t"] >= SETTLE_S]
    yaw_true = truth_at(truth, sol["t"].to_numpy())["yaw"].to_numpy()
    err = wrap_angle(sol["yaw"].to_numpy() - yaw_true)
    ratio = err / sol["yaw_std"].to_numpy()
    rms_deg = float(np.degrees(np.sqrt(np.mean(err**2))))
    rms_ratio = float(np.sqrt(np.mean(ratio**2)))
    assert np.isfinite(err).all()
    assert rms_deg <= 0.05, rms_deg
    assert rms_ratio <= 1.3, rms_ratio
    # a ground vehicle with an odometer, as its manifest says
    nav = namespace["nav"]
    assert {"yaw", "nhc", "zupt", "odo"} <= set(nav.drain_updates()["name"])
    assert not nav.counts.get("image-late") and not nav.counts.get("imu-gap"), nav.counts
