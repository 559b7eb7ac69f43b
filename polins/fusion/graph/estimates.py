"""The graph's keyframe estimates in polins conventions (navigation-frame errors, the ESKF's block order).

The solvers (:mod:`polins.fusion.graph.solvers`, :mod:`polins.fusion.graph.incremental`)
fill an :class:`Estimates`; :mod:`polins.fusion.graph.output` turns it into the solution
table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from polins.fusion.graph.factors import bias_from_polins, pose_cov_nav_from_body
from polins.fusion.graph.imu import scale_keys
from polins.fusion.measurement import N_ERROR

FloatArray = NDArray[np.float64]

# The ESKF's error order (att, vel, pos, bg, ba) from GTSAM's blocks (pose_n: att, pos;
# velocity; bias: ba, bg), an index into block_diag(pose, velocity, bias).
ESKF_FROM_GTSAM = np.r_[0:3, 6:9, 3:6, 12:15, 9:12]


@dataclass
class Estimates:
    """Keyframe estimates in polins conventions, filled by the solvers.

    ``cov`` is in the ESKF's error-state order (navigation-frame attitude error); a new
    error block gets its own array here and its slice of ``cov`` (package docstring). The
    sensor-error variables of :class:`~polins.fusion.graph.states.GraphStates` are ``extra``
    and the rows and columns of ``cov`` after the first 15.
    """

    mat_nb: FloatArray  # (K, 3, 3)
    vel_n: FloatArray  # (K, 3)
    pos_n: FloatArray  # (K, 3) local ENU [m]
    bias: FloatArray  # (K, 6): bg, ba
    cov: FloatArray  # (K, 15, 15)
    yaw_known: NDArray[np.bool_]  # (K,) a yaw/sun factor was in the graph when reported
    extra: FloatArray  # (K, n) GraphStates' variables
    scale: FloatArray  # (K, 6) scale factors sg, sa [-] (NaN without them)
    scale_cov: FloatArray  # (K, 6, 6) their covariance

    @classmethod
    def empty(cls, k: int, n_extra: int = 0) -> Estimates:
        """Estimates of ``k`` keyframes (and ``n_extra`` GraphStates values), all NaN."""

        def nan(*shape: int) -> FloatArray:
            return np.full((k, *shape), np.nan)

        n = N_ERROR + n_extra
        return cls(nan(3, 3), nan(3), nan(3), nan(6), nan(n, n), np.zeros(k, bool), nan(n_extra),
                   nan(6), nan(6, 6))  # fmt: skip

    def store(
        self,
        k: int,
        pose: gtsam.Pose3,
        vel: FloatArray,
        bias: gtsam.imuBias.ConstantBias,
        cov_pose_b: FloatArray,
        cov_vel: FloatArray,
        cov_bias: FloatArray,
        yaw_known: bool,
        extra: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """Keyframe ``k`` from GTSAM values and marginal covariances (block diagonal in
        pose / velocity / bias; GTSAM's bias tangent is accelerometer, then gyro); ``extra``
        the GraphStates' values and covariance (:meth:`GraphStates.read`)."""
        mat_nb = pose.rotation().matrix()
        self.mat_nb[k] = mat_nb
        self.pos_n[k] = pose.translation()
        self.vel_n[k] = vel
        self.bias[k] = np.concatenate([bias.gyroscope(), bias.accelerometer()])
        cov = np.zeros((N_ERROR, N_ERROR))  # GTSAM's blocks: pose, velocity, bias
        cov[:6, :6] = pose_cov_nav_from_body(mat_nb, cov_pose_b)
        cov[6:9, 6:9] = cov_vel
        cov[9:, 9:] = cov_bias
        self.cov[k] = 0.0
        self.cov[k, :N_ERROR, :N_ERROR] = cov[np.ix_(ESKF_FROM_GTSAM, ESKF_FROM_GTSAM)]
        self.yaw_known[k] = yaw_known
        if extra is not None:
            self.extra[k] = extra[0]
            self.cov[k, N_ERROR:, N_ERROR:] = extra[1]

    def store_scale(self, k: int, value: Any, marginal: Any) -> None:
        """The scale factors at keyframe ``k`` from a solver's ``value(key)`` and
        ``marginal(key)`` (``sg`` and ``sa`` independent blocks)."""
        key_g, key_a = scale_keys(k)
        self.scale[k] = np.concatenate([value(key_g), value(key_a)])
        self.scale_cov[k] = 0.0
        self.scale_cov[k, :3, :3] = marginal(key_g)
        self.scale_cov[k, 3:, 3:] = marginal(key_a)

    def values(self, k: int) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias]:
        """Keyframe ``k`` as GTSAM values."""
        state = gtsam.NavState(gtsam.Rot3(self.mat_nb[k]), self.pos_n[k], self.vel_n[k])
        return state, bias_from_polins(self.bias[k])
