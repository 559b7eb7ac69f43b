"""GTSAM factor-graph backend: IMU preintegration with sun-vector and yaw factors.

The optional second backend of ``polins.fuse(..., backend="graph")`` (``pip install
"polins[graph]"``), described in docs/filter.md §9. It estimates the same error blocks as
the ESKF (``att, vel, pos, bg, ba``) from the same inputs and
:class:`~polins.fusion.config.FuseConfig`, as a nonlinear least-squares problem over
keyframe states, and returns the same solution table
(:func:`polins.ins.state.solution_table`). Modules: :mod:`~polins.fusion.graph.factors`,
:mod:`~polins.fusion.graph.problem`, :mod:`~polins.fusion.graph.solvers` (batch),
:mod:`~polins.fusion.graph.incremental`, :mod:`~polins.fusion.graph.batched`,
:mod:`~polins.fusion.graph.windows`, :mod:`~polins.fusion.graph.estimates`,
:mod:`~polins.fusion.graph.start`, :mod:`~polins.fusion.graph.output`.

Graph
-----
Keyframe ``k`` holds ``X(k)`` (``gtsam.Pose3``: attitude ``rot_nb`` and position in local
ENU metres), ``V(k)`` (ENU velocity [m/s]) and ``B(k)`` (``imuBias.ConstantBias``:
accelerometer, then gyro bias). Keyframes sit at the first and last IMU sample, the
measurement, ``stationary``, non-holonomic and odometer epochs, and at most
``max_keyframe_dt_s`` apart. Implementation notes beyond docs/filter.md §9:

* ``CombinedImuFactor`` (Forster et al., IEEE TRO 2017), gravity ``MakeSharedU`` (WGS-84
  normal gravity at the start). Each integration step uses the mean of the linearly
  varying samples with the specific force rotated to the start of the step (GTSAM's
  velocity update is first order: without this a turn leaves mm/s-level velocity errors);
  the change of normal gravity along the drive is taken out of the accelerometer (GTSAM's
  gravity is constant). With Earth rate the Earth rate is ``omegaCoriolis`` and the
  transport rate ``C_bn omega_en_n`` at the current estimate is removed from the gyro.
* Sun vector: C++ ``AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b)``, error
  ``B(sun_n)^T R_nb sun_b`` in the tangent basis ``B`` of the ephemeris direction
  (``tests/test_graph.py`` pins these semantics); isotropic ``sun_std``. With the fit's 2x2
  covariance, or a sensor-error variable, a ``CustomFactor`` on the shared sun model in the
  tangent basis of the measured direction (:mod:`~polins.fusion.graph.states`).
* Sensor-error variables (:mod:`~polins.fusion.graph.states`): the odometer scale ``so``,
  the site rotation ``site_rot_n``, the no-clock sun azimuth and rate, the heading bias;
  their factors are whitened by the item's own ``R`` (``GraphStates.model``, the gates'
  linearization too). No clock: no yaw acquisition, the levelled yaw is the reference.
* Yaw and non-holonomic: ``gtsam.CustomFactor`` on the shared models
  (:func:`polins.fusion.items.item_model`), error ``h(x) - z = -residual``, Jacobian
  ``H_theta R_nb`` (GTSAM perturbs ``R exp(w_b)``, the ESKF ``exp(dtheta_n) R``).
  Zero velocity: C++ ``PriorFactorVector`` on ``V(k)``.
* Self-alignment (``rot_nb0=None``): a levelling factor (mean specific force over
  ``align_s`` at rest equals ``C_bn (0, 0, g) + b_a``, horizontal components, sigma
  ``VRW / sqrt(align_s)``: the ESKF's tilt covariance and its correlation with the
  accelerometer bias) and a 1 rad yaw prior.
* Yaw acquisition (docs/filter.md §7.1): the initial yaw is the consensus of the first
  headings on the dead-reckoned keyframes (:class:`~polins.fusion.graph.problem.Problem`,
  with the functions of :mod:`polins.fusion.acquisition`); it also re-acquires a given
  ``rot_nb0`` whose yaw the headings contradict.
* Rotation-proportional gyro noise: each keyframe interval has its own preintegration
  parameters, gyro density ``ARW^2 + m^2 mean|w|^2 tau`` (the misalignment,
  :func:`~polins.fusion.graph.factors.gyro_noise_density`). Inside an IMU gap longer than
  ``max_gap_s`` the densities also carry the gap's variance.
* Scale factors (``FuseConfig.use_scale_factors``): ``sg, sa`` per keyframe (keys ``g<k>``,
  ``a<k>``, ``Vector3``), the IMU model's turn-on sigmas as priors, linked as constants
  (:func:`~polins.fusion.graph.imu.scale_factor_links`; one key for the run would sit in
  every clique's separator, and ISAM2 would back-substitute the whole tree at every
  keyframe). The IMU factor is the ``CombinedImuFactor`` wrapped in a ``CustomFactor`` that
  corrects its increments by ``J_s s`` (:mod:`polins.fusion.graph.imu`).

Error blocks
------------
The ESKF's named blocks map to graph variables: ``att`` and ``pos`` to ``X(k)``, ``vel``
to ``V(k)``, ``bg`` and ``ba`` to ``B(k)``; covariances are converted to the ESKF's
navigation-frame errors (:func:`~polins.fusion.graph.factors.pose_cov_nav_from_body`). A
new block (scale factors ``sg, sa``, misalignment, odometer scale, a measurement bias, a
sun-azimuth offset) becomes a new variable with its own key per keyframe (or one key for
a constant), a prior with its turn-on sigma, a random-walk ``BetweenFactor`` between
keyframes, and a ``CustomFactor`` wherever ``CombinedImuFactor`` or a measurement factor
lacks it (an IMU error such as a scale factor: a factor on ``X, V, B`` and the block that
corrects the preintegrated increments to first order in the block, as GTSAM does for the
bias); :class:`~polins.fusion.graph.estimates.Estimates` gets its array and its slice of
the covariance, and :func:`~polins.fusion.graph.output.nav_state` its entry in
``errors`` and ``sigma``. The measurement-side blocks (``so``, ``site_rot_n``,
``sun_azimuth_n`` / ``sun_azimuth_rate``, ``heading_bias``) are
:class:`~polins.fusion.graph.states.GraphStates`: ``Estimates.extra`` and the rows of
``cov`` after the 15, read and seeded by the solvers through it. The scale factors
(``sg, sa``) are ``Estimates.scale`` and ``scale_cov`` (:mod:`polins.fusion.graph.imu`).

Solvers
-------
``"batch"``: Gauss-Newton over the whole log (a smoother, like ESKF + RTS), see
:func:`~polins.fusion.graph.solvers.gauss_newton_qr` for why neither Levenberg-Marquardt
(``optimizer="levenberg-marquardt"``, slower) nor Cholesky; it starts from the ESKF's
solution on the same inputs (:mod:`~polins.fusion.graph.start`); sigmas from the
QR-eliminated Bayes tree, every variable's in one pass
(:func:`~polins.fusion.graph.solvers.marginal_covariances`). Outliers are gated on the
post-fit residuals (``r^T (R - H P H^T)^-1 r`` against the chi-square quantile
``gate_prob``), each round those at least half the largest exceedance within 30 s
(``solvers.GATE_SPAN_S``), and the graph is re-solved without them. Its Python factors are
evaluated by type in numpy before each linearization (:mod:`~polins.fusion.graph.batched`);
a log longer than ``windows.WINDOW_S`` is solved in overlapping windows, each with the
past as its prior (:mod:`~polins.fusion.graph.windows`).
``"isam2"``: incremental ``gtsam.ISAM2`` as used online: each keyframe is reported as
estimated when it was added (causal, like the filter); gating on the predicted residual
with the previous keyframe's covariance. ``"fixed_lag"``:
``gtsam.IncrementalFixedLagSmoother``; each keyframe is reported when it leaves the
``lag_s`` window (smoothed with ``lag_s`` of future data).

Output rows are IMU samples (``output_rate_hz``, as the ESKF) or the keyframes
(``graph_output="keyframes"``), see :mod:`~polins.fusion.graph.output`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

try:
    import gtsam  # noqa: F401  (the check for the optional extra)
except ImportError as exc:  # tests simulate a missing gtsam
    raise ImportError(
        'the graph backend (backend="graph") needs GTSAM >= 4.3: pip install "polins[graph]"'
    ) from exc

from polins.fusion.config import TIME_TOL_S
from polins.fusion.eskf.batch import fuse_eskf
from polins.fusion.graph.factors import (
    bias_from_polins,
    gyro_noise_density,
    levelling_factor,
    non_holonomic_factor,
    pose_cov_body_from_nav,
    pose_cov_nav_from_body,
    preintegration_params,
    sun_factor,
    yaw_factor,
    zero_velocity_factor,
)
from polins.fusion.graph.imu import ImuSegments, imu_segments
from polins.fusion.graph.incremental import solve_incremental
from polins.fusion.graph.output import interpolate, keyframe_output
from polins.fusion.graph.problem import Problem, keyframe_times
from polins.fusion.graph.solvers import (
    gauss_newton_qr,
    marginal_covariance_qr,
    marginal_covariances,
    solve_batch,
)
from polins.fusion.graph.start import filter_values
from polins.fusion.inputs import Prepared, output_mask
from polins.fusion.items import UpdateRecord, records_table
from polins.fusion.result import FusionResult, events_table
from polins.ins.state import solution_table


def causal_gate(
    prep: Prepared, prob: Problem, upd: pd.DataFrame | None = None
) -> dict[int, tuple[float, str]]:
    """The ESKF's verdicts on the standstill detector's zero-velocity and zero-rate factors
    (``prob.detected``): index into ``prob.meas`` -> (NIS, reason) of those the ESKF's
    gate rejected, found by kind and time (both place the detector's updates at the same
    epochs, :func:`polins.fusion.vehicle.vehicle_items`). ``upd``: the ESKF's update table
    of ``prep`` if already run."""
    if upd is None:
        upd = fuse_eskf(prep).updates
    rejected = upd[~upd["accepted"].to_numpy(dtype=bool)]
    by_kind = {
        kind: (g["t"].to_numpy(dtype=float), g["nis"].to_numpy(dtype=float), list(g["reason"]))
        for kind, g in rejected.groupby("name", sort=False)
    }
    out = {}
    for i in sorted(prob.detected):
        item = prob.meas[i].item
        if item.kind not in by_kind:
            continue
        t_gone, nis, reason = by_kind[item.kind]
        j = int(np.searchsorted(t_gone, item.t - TIME_TOL_S))
        if j < len(t_gone) and abs(t_gone[j] - item.t) <= TIME_TOL_S:
            out[i] = (float(nis[j]), str(reason[j]))
    return out


def fuse_graph(prep: Prepared, progress: bool = False) -> FusionResult:
    """Solve a prepared run (:func:`polins.fusion.inputs.prepare`) in a GTSAM factor graph.

    ``polins.fusion.api.run_fusion`` calls this for ``backend="graph"``: the IMU samples,
    the measurement items (factors by the shared rules of :mod:`polins.fusion.items`), the
    IMU gaps (keyframes at their ends, their variance in the preintegration noise) and the
    resolved configuration come from the one preparation the ESKF solves too.

    Returns
    -------
    FusionResult
        ``solution``: the solution table (:func:`polins.ins.state.solution_table`);
        ``updates``: one row per yaw/sun measurement (``t, name, dim, nis, accepted,
        reason``; the batch solver's NIS is post-fit); ``events``: the preparation's and
        a re-acquired yaw (docs/faults.md); ``info``: the solver, iterations, keyframes,
        timings [s].

    ``progress``: a tqdm line while solving (the batch solver's stages, the incremental
    solvers' keyframes).
    """
    t_start = time.perf_counter()
    config, arrays, items = prep.config, prep.imu, prep.items
    spans = zip(arrays.gap_spans, arrays.gaps, strict=True)
    gaps = [(t_a, t_b, g.inflation) for (t_a, t_b), g in spans if g.inflation is not None]
    prob = Problem(config, config.tilt_coupling, arrays.t, arrays.gyro_b, arrays.accel_b,
                   items, prep.rot_nb0, gaps)  # fmt: skip
    records = [
        UpdateRecord(it.t, it.kind, 0, math.nan, False, it.reason or "invalid measurement")
        for it in items
        if not it.valid
    ]
    records += prob.held
    records += [
        UpdateRecord(it.t, it.kind, 0, math.nan, False, "outside the IMU time span")
        for it in prob.outside
    ]
    info: dict[str, Any] = {}
    t_built = time.perf_counter()
    with tqdm(desc=f"graph {config.graph.solver}", disable=not progress, bar_format=BAR) as bar:
        if config.graph.solver == "batch":
            bar.set_postfix_str("ESKF (causal gate, initial values)")
            eskf = fuse_eskf(prep)
            causal = causal_gate(prep, prob, eskf.updates) if prob.detected else {}
            start = filter_values(prob, eskf.solution)
            est = solve_batch(prob, records, info, causal, bar.set_postfix_str, start)
        else:
            est = solve_incremental(prob, records, info, progress=bar)
    t_solved = time.perf_counter()
    if config.graph.graph_output == "keyframes":
        state = keyframe_output(prob, est)
    else:
        state = interpolate(prob, est, arrays.t[output_mask(arrays.t, config.output_rate)])
    info.update(
        solver=config.graph.solver,
        n_keyframes=len(prob.t_key),
        n_measurement_factors=len(prob.meas),
        time_build_s=t_built - t_start,
        time_solve_s=t_solved - t_built,
        time_output_s=time.perf_counter() - t_solved,
    )
    return FusionResult(
        solution=solution_table(state),
        updates=records_table(sorted(records, key=lambda r: r.t)),
        events=events_table([*prep.events, *prob.events]),
        config=config,
        backend="graph",
        info=info,
    )


BAR = "{desc}: {n_fmt}/{total_fmt} {postfix} [{elapsed}]"

__all__ = [
    "ImuSegments",
    "bias_from_polins",
    "causal_gate",
    "fuse_graph",
    "gauss_newton_qr",
    "gyro_noise_density",
    "imu_segments",
    "keyframe_times",
    "levelling_factor",
    "marginal_covariance_qr",
    "marginal_covariances",
    "non_holonomic_factor",
    "pose_cov_body_from_nav",
    "pose_cov_nav_from_body",
    "preintegration_params",
    "sun_factor",
    "yaw_factor",
    "zero_velocity_factor",
]
