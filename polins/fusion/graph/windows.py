"""The batch solver's graph over a window of keyframes, its initial values, and the prior a window passes to the next.

A log longer than :data:`WINDOW_S` is solved in windows (docs/filter.md §9): window ``i``
spans ``WINDOW_S`` of keyframes, the next starts :data:`OVERLAP_S` before its end (at the
join) with the information of everything before the join as its prior
(:func:`past_prior`: the linearized factors before the join eliminated down to the join's
keyframe and the run's constants, GTSAM's ``LinearContainerFactor``), and each window
reports its keyframes before the next window's join. The cost and memory of a solve then
grow linearly with the log; a window's estimates use the whole past and ``OVERLAP_S`` of
the future.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import NDArray

from polins.fusion.graph.batched import FactorBatch, ScaleImuBatch
from polins.fusion.graph.batched import linearize as batched_linearize
from polins.fusion.graph.problem import Problem

FloatArray = NDArray[np.float64]

# [s] A batch window's span and the overlap of consecutive windows: a 10-minute window
# holds about 350 MB (the 300 s README log's graph peaks at 0.6 GB with the inputs); the
# future beyond a minute changes the attitude of a MEMS drive by far less than its sigma.
WINDOW_S = 600.0
OVERLAP_S = 60.0


def windows(t_key: FloatArray, window_s: float, overlap_s: float) -> list[tuple[range, int]]:
    """The windows of keyframes at times ``t_key`` [s]: ``(frames, join)`` with ``frames``
    the window's keyframes and ``join`` the first keyframe the next window reports (the
    last window's: ``len(t_key)``). One window when the log is no longer than
    ``window_s``."""
    n = len(t_key)
    out: list[tuple[range, int]] = []
    start = 0
    while True:
        if t_key[-1] - t_key[start] <= window_s:
            out.append((range(start, n), n))
            return out
        join = int(np.searchsorted(t_key, t_key[start] + window_s - overlap_s))
        end = int(np.searchsorted(t_key, t_key[join] + overlap_s, side="right"))
        out.append((range(start, max(end, join + 1)), join))
        start = join


@dataclass(eq=False)
class BatchGraph:
    """The graph of a window (:func:`batch_graph`): the graph, its initial values, the
    batches of its Python factors (:mod:`polins.fusion.graph.batched`), the index in the
    graph of each measurement factor (index into ``Problem.meas``) and of each keyframe's
    own factors (those after the IMU factor and links that lead to it)."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    batches: list[FactorBatch]
    where: dict[int, int]
    own: dict[int, int]

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The graph linearized at ``values``, its Python factors evaluated by type."""
        return batched_linearize(self.graph, values, self.batches)

    def remove(self, gated: Iterable[int]) -> None:
        """Take the measurement factors ``gated`` (indices into ``Problem.meas``) out."""
        for i in gated:
            self.graph.remove(self.where.pop(i))


def window_values(
    prob: Problem, values: gtsam.Values, frames: range, newer: gtsam.Values | None = None
) -> gtsam.Values:
    """The values of the keys of keyframes ``frames`` (and the constants) in ``newer``
    where it has them, else in ``values``."""
    out = gtsam.Values()
    for k in frames:
        for key in prob.keys_at(k, k == frames[0]):
            src = newer if newer is not None and newer.exists(key) else values
            letter = chr(gtsam.Symbol(key).chr())
            if letter == "x":
                out.insert(key, src.atPose3(key))
            elif letter == "b":
                out.insert(key, src.atConstantBias(key))
            else:
                out.insert(key, src.atVector(key))
    return out


def batch_graph(
    prob: Problem,
    rejected: set[int],
    linearization: gtsam.Values | None,
    frames: range | None = None,
    priors: Sequence[gtsam.NonlinearFactor] | None = None,
) -> BatchGraph:
    """The graph of keyframes ``frames`` (default: all) without the ``rejected``
    measurement factors, with the first keyframe's ``priors`` (default: the problem's),
    and initial values (dead reckoning from the first keyframe, or ``linearization``,
    whose velocity, position and bias also set the transport rate and the bias of the
    preintegration)."""
    frames = range(len(prob.t_key)) if frames is None else frames
    first = frames[0]
    imu_batch = ScaleImuBatch()
    graph = gtsam.NonlinearFactorGraph()
    for f in prob.priors if priors is None else priors:
        graph.add(f)
    values = gtsam.Values()
    state, bias = prob.state0, prob.bias0
    if linearization is None:
        values.insert(X(0), state.pose())
        values.insert(V(0), state.velocity())
        values.insert(B(0), bias)
        values.insert(prob.scale_values(0))
        values.insert(prob.states.initial(0, prob.states.guess))
    where: dict[int, int] = {}
    own: dict[int, int] = {}
    for k in frames:
        if k > first:
            for f in prob.links[k] + prob.scale_factors_at(k):
                graph.add(f)
            if linearization is not None:
                state = gtsam.NavState(linearization.atPose3(X(k - 1)),
                                       linearization.atVector(V(k - 1)))  # fmt: skip
                bias = linearization.atConstantBias(B(k - 1))
            pim = prob.preintegrate(k - 1, bias, prob.imu_correction(state))
            graph.add(prob.imu_factor(k - 1, pim, batch=imu_batch))
            if linearization is None:
                state = pim.predict(state, bias)
                values.insert(X(k), state.pose())
                values.insert(V(k), state.velocity())
                values.insert(B(k), bias)
                values.insert(prob.states.initial(k, prob.states.guess))
                values.insert(prob.scale_values(k))
        elif k == 0:
            for f in prob.scale_factors_at(0):  # the scale factors' priors
                graph.add(f)
        own[k] = graph.size()
        add_own(graph, prob, k, rejected, where)
    if linearization is not None:
        values = window_values(prob, linearization, frames)
    return BatchGraph(graph, values, [*prob.batches(), imu_batch], where, own)


def add_own(
    graph: gtsam.NonlinearFactorGraph,
    prob: Problem,
    k: int,
    rejected: set[int],
    where: dict[int, int],
) -> None:
    """Keyframe ``k``'s constraints and measurement factors (not the ``rejected``), their
    indices into ``where``."""
    for f in prob.aux[k]:
        graph.add(f)
    for i in prob.meas_at[k]:
        if i not in rejected:
            where[i] = graph.size()
            graph.add(prob.meas[i].factor)


def past_prior(
    prob: Problem, built: BatchGraph, result: gtsam.Values, join: int
) -> list[gtsam.NonlinearFactor]:
    """The information of a window's factors before keyframe ``join`` (its prior, the IMU
    factors and links up to ``join``; not ``join``'s own measurements) on ``join``'s keys
    and the run's constants: those factors linearized at ``result`` and the other keys
    eliminated (QR), as ``LinearContainerFactor``s at ``result``."""
    linear = built.linearize(result)
    past = gtsam.GaussianFactorGraph()
    for i in range(built.own[join]):
        factor = linear.at(i)
        if factor is not None:
            past.push_back(factor)
    keep = set(prob.keys_at(join, True))
    gone = [key for key in past.keyVector() if key not in keep]
    _tree, remaining = past.eliminatePartialMultifrontal(gone, gtsam.EliminateQR)
    point = window_values(prob, result, range(join, join + 1))
    container = gtsam.LinearContainerFactor.ConvertLinearGraph(remaining, point)
    return [container.at(i) for i in range(container.size())]


__all__ = ["OVERLAP_S", "WINDOW_S", "BatchGraph", "batch_graph", "past_prior", "windows"]
