"""The ESKF over a whole log: a prepared run filtered forward through the fast path, and smoothed."""

from __future__ import annotations

import numpy as np

from polins.errors import UserInputError
from polins.fusion.config import TIME_TOL_S
from polins.fusion.eskf.filter import ESKF
from polins.fusion.eskf.propagate import advance, interpolate
from polins.fusion.eskf.smoother import rts_smooth
from polins.fusion.inputs import Prepared, output_mask
from polins.fusion.items import records_table
from polins.fusion.result import FusionResult, events_table
from polins.ins.state import solution_table


def fuse_eskf(prep: Prepared) -> FusionResult:
    """Solve a prepared run (:func:`polins.fusion.inputs.prepare`) with the ESKF.

    The IMU gaps' ``"gap"`` items add their variance to the covariance at the sample after
    each gap (docs/faults.md); with ``smooth`` the Rauch-Tung-Striebel smoother runs
    over the stored forward pass, and ``filtered`` holds the causal solution.
    """
    cfg, arrays = prep.config, prep.imu
    t, W, A = arrays.t, arrays.gyro_b, arrays.accel_b
    filt = ESKF(cfg, float(t[0]), arrays.dt, prep.rot_nb0)
    filt.add_items([*prep.items, *arrays.gaps])
    if not filt.ready:
        k_end = int(np.searchsorted(t - t[0], cfg.initial.align_s - TIME_TOL_S, side="left"))
        if k_end >= len(t):
            raise UserInputError(
                f"the IMU log ({t[-1] - t[0]:.3f} s) is shorter than the alignment window "
                f"align_s={cfg.initial.align_s} s; give rot_nb0 or a longer log"
            )
        filt.level([(float(t[k]), W[k], A[k]) for k in range(k_end + 1)])
    run = advance(filt, t, W, A, output_mask(t, cfg.output_rate), full=cfg.output.smooth)
    assert run is not None
    nodes, rows = run
    slices = filt.layout.index
    filtered = solution_table(interpolate(nodes, rows, slices))
    solution = filtered
    if cfg.output.smooth:
        assert nodes.P_pre is not None and nodes.P_post is not None and nodes.Phi is not None
        delta, P_s = rts_smooth(nodes.P_pre, nodes.P_post, nodes.Phi, nodes.dx, nodes.linked)
        solution = solution_table(interpolate(nodes, rows, slices, delta, P_s))
    return FusionResult(
        solution=solution,
        updates=records_table(filt.records),
        events=events_table([*prep.events, *filt.events]),
        config=cfg,
        backend="eskf",
        filtered=filtered if cfg.output.smooth else None,
        info={"n_resets": filt.n_resets},
    )


__all__ = ["fuse_eskf"]
