"""Initial values of the batch graph from the filter's solution (a warm start).

Gauss-Newton from dead reckoning needs 5-7 iterations on a MEMS drive (the zero-bias
dead reckoning is km off within minutes); from the ESKF's estimates, which the batch
solver computes anyway to gate the standstill detector's factors
(:func:`polins.fusion.graph.causal_gate`), 2-3. The preintegration is linearized there too
(bias, transport rate): the ESKF's estimate is within its sigmas of the smoothed one, and
the preintegration's first-order bias correction and the transport rate then differ from
those at the smoothed estimate by far less than a sigma.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pandas as pd
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from polins.fusion.graph.imu import scale_keys
from polins.fusion.graph.problem import Problem
from polins.ins.state import block_columns

FloatArray = NDArray[np.float64]

QUAT = ["qx", "qy", "qz", "qw"]  # scipy's order (scalar last)


def aligned_attitude(sol: pd.DataFrame) -> Rotation | None:
    """The solution's attitudes with the rows before the yaw alignment (``yaw`` NaN) turned
    about the vertical by the alignment's yaw step (their yaw is the filter's guess); None
    if the yaw never aligned."""
    rot = Rotation.from_quat(sol[QUAT].to_numpy(dtype=float))
    aligned = np.isfinite(sol["yaw"].to_numpy(dtype=float))
    if not aligned.any():
        return None
    first = int(np.argmax(aligned))
    if first == 0:
        return rot
    step = (rot[first] * rot[first - 1].inv()).as_euler("ZYX")[0]
    turned = Rotation.from_rotvec([0.0, 0.0, step]) * rot[:first]
    return Rotation.concatenate([turned, rot[first:]])


def filter_values(prob: Problem, sol: pd.DataFrame) -> gtsam.Values | None:
    """Values of every key of the batch graph from the filter's solution table ``sol``
    (:func:`polins.ins.state.solution_table`) interpolated to the keyframes (attitude by
    slerp, the rest linearly, held at the ends); variables without a column keep their
    guess. None if the table cannot serve (fewer than two rows, no yaw alignment)."""
    t = sol["t"].to_numpy(dtype=float)
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        return None
    rot = aligned_attitude(sol)
    if rot is None:
        return None
    t_key = np.clip(prob.t_key, t[0], t[-1])
    mat_nb = Slerp(t, rot)(t_key).as_matrix()

    def column(names: tuple[str, ...] | list[str], default: FloatArray) -> FloatArray:
        if not all(n in sol.columns for n in names):
            return np.broadcast_to(default, (len(t_key), len(default)))
        return np.stack([np.interp(t_key, t, sol[n].to_numpy(dtype=float)) for n in names], -1)

    vel = column(["ve", "vn", "vu"], np.zeros(3))
    geo = column(["lat_deg", "lon_deg", "alt_m"], np.zeros(3))
    pos = prob.local_position(np.radians(geo[:, 0]), np.radians(geo[:, 1]), geo[:, 2])
    bias = np.concatenate([column(block_columns("ba", 3), np.zeros(3)),
                           column(block_columns("bg", 3), np.zeros(3))], axis=-1)  # fmt: skip
    extra = np.tile(prob.states.guess, (len(t_key), 1))
    for name, sl in prob.states.index.items():
        extra[:, sl] = column(block_columns(name, sl.stop - sl.start), prob.states.guess[sl])
    scale = [column(block_columns(n, 3), np.zeros(3)) for n in ("sg", "sa")]
    finite = [mat_nb, vel, pos, bias, extra, *scale]
    if not all(np.isfinite(a).all() for a in finite):
        return None
    first = extra[0].copy()  # a constant takes the filter's last estimate (the whole log's)
    for var in prob.states.variables:
        if not var.per_keyframe:
            first[prob.states.slices[var]] = extra[-1, prob.states.slices[var]]
    values = gtsam.Values()
    for k in range(len(t_key)):
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(mat_nb[k]), pos[k]))
        values.insert(V(k), vel[k])
        values.insert(B(k), gtsam.imuBias.ConstantBias(bias[k, :3], bias[k, 3:]))
        values.insert(prob.states.initial(k, extra[k] if k else first))
        if prob.scale_jac is not None:
            for key, s in zip(scale_keys(k), scale, strict=True):
                values.insert(key, np.array(s[k], dtype=float))
    return values
