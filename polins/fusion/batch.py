"""Batch path of the ESKF: runs of IMU samples vectorised between resets, RTS smoother.

Between resets the nominal state does not depend on the measurement updates (they act on
the error state, :mod:`polins.fusion.eskf`), so :func:`advance` propagates it for a whole
segment of samples at once (:func:`polins.ins.strapdown`). The covariance steps of the
segment (``cov_every`` IMU intervals, ending early at measurement epochs; a step in
progress in the filter carries over) are discretised together from cumulative sums of the
per-interval terms (:func:`~polins.fusion.eskf.step_exponent`,
:func:`~polins.fusion.eskf.van_loan`) and multiplied into block transitions between the
epochs (:func:`block_transitions`). filterpy's ``predict`` and ``update`` then run once per
epoch, in order, with the filter's own measurement handling (``ESKF._apply``: gating,
records, resets). The result equals one ``ESKF.propagate`` call per sample to rounding
error (tests/test_eskf.py: 1e-9 rad, 1e-9 relative in the sigmas).

Output rows inside a covariance step report what ``ESKF.state()`` gives there: the state
at the start of their step propagated over the step so far, with the error dynamics frozen
at their mean over the step's first IMU interval. Without smoothing only what the solution
table needs is computed, as polynomials in the partial-step length per step
(:func:`~polins.fusion.eskf.partial_step_polynomials`: the error state, the covariance
diagonal and its attitude block), evaluated per row; with full covariances (``full_cov``,
smoothing) the partial transition of every row is computed.

:func:`run_batch` runs a fresh filter over a whole log (``polins.fuse``),
``ESKF.propagate_many`` runs :func:`advance` on a filter in any state (streaming use).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from filterpy.kalman import predict as kf_predict
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.eskf import (
    ESKF,
    N_DYNAMIC,
    SA,
    SG,
    _StepSums,
    nav_error_dynamics,
    partial_step_polynomials,
    solution_columns,
    step_exponent,
    van_loan,
)
from polins.fusion.items import MeasurementItem
from polins.fusion.measurement import ATT, BA, BG, N_ERROR, POS, VEL
from polins.ins.earth import radii_of_curvature
from polins.ins.strapdown import NavTrack, rotation_vectors, strapdown

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int_]


# ============================================================================ output
@dataclass(frozen=True, eq=False)
class BatchOutput:
    """Estimates at the output IMU samples of :func:`run_batch` (arrays over rows).

    ``sigma`` holds the square roots of the covariance diagonals, ``P_att`` the attitude
    blocks; ``P`` the full error covariances, only when asked for (``full_cov``) or when
    smoothing. ``smoothed`` (if requested) is another :class:`BatchOutput` with the
    Rauch-Tung-Striebel estimates.
    """

    t: FloatArray
    rot_nb: Rotation
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    height: FloatArray
    bg: FloatArray
    ba: FloatArray
    sg: FloatArray | None
    sa: FloatArray | None
    sigma: FloatArray
    P_att: FloatArray
    yaw_aligned: FloatArray
    P: FloatArray | None = None
    smoothed: BatchOutput | None = None

    def columns(self) -> dict[str, FloatArray]:
        """Solution-table columns (:func:`~polins.fusion.eskf.solution_columns`)."""
        return solution_columns(
            t=self.t,
            rot_nb=self.rot_nb,
            vel_n=self.vel_n,
            lat=self.lat,
            lon=self.lon,
            height=self.height,
            bg=self.bg,
            ba=self.ba,
            sg=self.sg,
            sa=self.sa,
            P_diag_att=self.P_att,
            sigma=self.sigma,
            yaw_aligned=self.yaw_aligned,
        )


def _inject_many(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    lat: FloatArray,
    lon: FloatArray,
    height: FloatArray,
    dx: FloatArray,
) -> tuple[Rotation, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Vectorised ``nominal (+) dx`` for the navigation part (``eskf.inject``)."""
    r_m, r_n = radii_of_curvature(lat)
    mat = Rotation.from_rotvec(dx[:, ATT]).as_matrix() @ mat_nb
    return (
        Rotation.from_matrix(mat, assume_valid=True),
        vel_n + dx[:, VEL],
        lat + dx[:, POS.start + 1] / (r_m + height),
        lon + dx[:, POS.start] / ((r_n + height) * np.cos(lat)),
        height + dx[:, POS.start + 2],
    )


@dataclass
class _Chain:
    """Smoother storage: epochs (where the covariance was propagated to) and output rows."""

    P_prior: list[FloatArray] = field(default_factory=list)
    P_post: list[FloatArray] = field(default_factory=list)
    Phi: list[FloatArray | None] = field(default_factory=list)  # from the previous epoch
    dx: list[FloatArray] = field(default_factory=list)
    out_next: list[IntArray] = field(default_factory=list)  # next epoch or -1
    out_gain: list[FloatArray] = field(default_factory=list)  # per output row: C_o


@dataclass
class _Rows:
    """Output rows collected segment by segment (arrays concatenated at the end)."""

    full: bool
    cols: dict[str, list[Any]] = field(default_factory=dict)
    chain: _Chain | None = None

    def add(self, **values: Any) -> None:
        for key, val in values.items():
            self.cols.setdefault(key, []).append(val)


# ============================================================================ helpers
def _assign_samples(
    t: FloatArray, items: Sequence[MeasurementItem], tol: float
) -> tuple[
    list[tuple[int, float]],
    list[int | tuple[int, int]],
    list[MeasurementItem],
    list[MeasurementItem],
]:
    """Map measurement items (sorted) to real samples or to virtual (interpolated) samples.

    Mirrors the streaming rule: an item within ``tol`` of a real sample uses it; otherwise a
    virtual sample at the item time between the two real samples, shared by later items
    within ``tol`` of it.

    Returns
    -------
    virtual : list of (interval k, time)
        Virtual samples between real samples ``k - 1`` and ``k``.
    where : list
        Per used item: real index (int) or ``(k, j)`` = j-th virtual sample of the list.
    used, early : lists of MeasurementItem
        Items inside the samples; items before the first sample (rejected). Items after
        the last sample are in neither (they stay pending).
    """
    virtual: list[tuple[int, float]] = []
    where: list[int | tuple[int, int]] = []
    used: list[MeasurementItem] = []
    early: list[MeasurementItem] = []
    n = len(t)
    t_items = np.array([item.t for item in items], dtype=float)
    ks = np.searchsorted(t, t_items - tol, side="left").tolist()
    for item, k in zip(items, ks, strict=True):
        if k >= n:
            continue
        if t[k] <= item.t + tol:
            where.append(k)
        elif k == 0:
            early.append(item)
            continue
        elif virtual and virtual[-1][0] == k and item.t <= virtual[-1][1] + tol:
            where.append((k, len(virtual) - 1))
        else:
            virtual.append((k, item.t))
            where.append((k, len(virtual) - 1))
        used.append(item)
    return virtual, where, used, early


def block_transitions(
    Phi: FloatArray,
    Q: FloatArray,
    starts: IntArray,
    ends: IntArray,
    at_block: IntArray,
    at_pos: IntArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Products of per-step transitions over consecutive blocks of steps.

    Block ``s`` covers steps ``starts[s] .. ends[s] - 1``. Returns the block transition
    ``Pi[s] = Phi[e-1] ... Phi[b]`` and noise ``Qa[s]`` (the recursion
    ``Qa <- Phi Qa Phi^T + Q``, i.e. what filterpy's ``predict`` does step by step), and
    the partial products after ``at_pos[i]`` steps of block ``at_block[i]`` (position 0 is
    the identity / zero). The loop runs over the positions inside the blocks and is
    vectorised across the blocks.
    """
    n = Phi.shape[-1]
    lengths = ends - starts
    L = int(lengths.max())
    Pi_at = np.empty((at_block.size, n, n))
    Qa_at = np.empty((at_block.size, n, n))
    first = at_pos == 0
    Pi_at[first] = np.eye(n)
    Qa_at[first] = 0.0
    Pi = Phi[starts].copy()  # after the first step of every block
    Qa = Q[starts].copy()
    order = np.argsort(at_pos, kind="stable")
    bounds = np.searchsorted(at_pos[order], np.arange(L + 1))
    short = int(lengths.min())
    for j in range(1, L):
        want = order[bounds[j] : bounds[j + 1]]
        if want.size:
            Pi_at[want] = Pi[at_block[want]]
            Qa_at[want] = Qa[at_block[want]]
        if j < short:
            Pj = Phi[starts + j]
            Pi = Pj @ Pi
            Qa = Pj @ Qa @ np.swapaxes(Pj, -1, -2) + Q[starts + j]
        else:
            act = np.flatnonzero(lengths > j)
            Pj = Phi[starts[act] + j]
            Pi[act] = Pj @ Pi[act]
            Qa[act] = Pj @ Qa[act] @ np.swapaxes(Pj, -1, -2) + Q[starts[act] + j]
    want = order[bounds[L] :]
    if want.size:  # positions at the block ends
        Pi_at[want] = Pi[at_block[want]]
        Qa_at[want] = Qa[at_block[want]]
    return Pi, Qa, Pi_at, Qa_at


def _split_gaps(marks: IntArray, every: int, first: int | None = None) -> IntArray:
    """Split ``0 < marks[0] < marks[1] < ...`` into pieces of at most ``every``.

    Returns the piece ends: for each gap ``(previous mark, mark]`` the points
    ``previous + every, previous + 2 every, ...`` before the mark, then the mark. With
    ``first`` the first piece of the first gap is at most ``first`` long.
    """
    if first is not None and first < every and marks.size and first < marks[0]:
        marks = np.concatenate([[first], marks])  # the first piece ends there
    if marks.size == 0:
        return marks.astype(int)
    prev = np.concatenate([[0], marks[:-1]])
    count = (marks - prev + every - 1) // every  # pieces per gap
    start = np.repeat(prev, count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + 1
    return np.minimum(start + k * every, np.repeat(marks, count)).astype(int)


def _step_boundaries(n: int, epochs: IntArray, every: int, first: int | None = None) -> IntArray:
    """Ends of the covariance steps over intervals ``0 .. n - 1`` (relative sample indices).

    A step ends after ``every`` intervals (``first`` for the first step, when a step is in
    progress) or at an epoch (a sample with measurements), whichever comes first (the
    streaming rule), and at ``n``.
    """
    marks = np.append(epochs[(epochs > 0) & (epochs < n)], n)  # epochs: sorted, unique
    return _split_gaps(marks.astype(int), every, first)


@dataclass(frozen=True, eq=False)
class _Segment:
    """Per-interval terms of a segment as cumulative sums, and the step in progress.

    ``cs`` ``(n + 1, m)`` holds the cumulative sums (leading zero row) of the columns
    ``dt``, ``mat_nb_mid dt`` (9), ``dv_force_n`` (3) and, with scale factors,
    ``mat_nb_mid diag(phi)`` (9) and ``mat_nb_mid diag(f_mid) dt`` (9). ``carry`` ``(m,)``
    are the sums of the step in progress at the segment start (the first step includes
    them), ``carry_first`` those of its first interval; ``divisors`` the scale-factor terms
    of the segment (fixed until the next reset).
    """

    track: NavTrack
    divisors: tuple[FloatArray | float, FloatArray | float]
    cs: FloatArray
    carry: FloatArray | None
    carry_first: FloatArray | None
    carry_start: tuple[FloatArray, float, float] | None

    def sums(self, a: IntArray, b: IntArray, q0: NDArray[np.bool_]) -> list[FloatArray]:
        """Sums over the intervals ``a .. b - 1`` (plus the carry where ``q0``):
        ``[dt, mat dt, dv_force(, mat phi, mat f dt)]``."""
        s = self.cs[b] - self.cs[a]
        if self.carry is not None and q0.any():
            s[q0] += self.carry
        return _split_sums(s)

    def duration(self, a: IntArray, b: IntArray, q0: NDArray[np.bool_]) -> FloatArray:
        """The ``dt`` of :meth:`sums`."""
        T = self.cs[b, 0] - self.cs[a, 0]
        if self.carry is not None and q0.any():
            T[q0] += self.carry[0]
        return T

    def first_sums(self, a: IntArray, q0: NDArray[np.bool_]) -> list[FloatArray]:
        """:meth:`sums` over the first interval of the steps starting at ``a`` (the carry's
        first interval where ``q0``)."""
        s = self.cs[a + 1] - self.cs[a]
        if self.carry_first is not None and q0.any():
            s[q0] = self.carry_first
        return _split_sums(s)

    def step_nav(
        self, a: IntArray, q0: NDArray[np.bool_]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Velocity, latitude and height at step starts ``a`` (the carry's where ``q0``)."""
        tr = self.track
        vel, lat, h = tr.vel_n[a], tr.lat[a], tr.height[a]
        if self.carry_start is not None and q0.any():
            vel[q0], lat[q0], h[q0] = self.carry_start
        return vel, lat, h


def _split_sums(s: FloatArray) -> list[FloatArray]:
    """Columns of :class:`_Segment` sums ``(k, m)`` as ``[dt, mat, dv(, mat_omega,
    mat_force)]``."""
    k = s.shape[0]
    out = [s[:, 0], s[:, 1:10].reshape(k, 3, 3), s[:, 10:13]]
    if s.shape[1] > 13:
        out += [s[:, 13:22].reshape(k, 3, 3), s[:, 22:31].reshape(k, 3, 3)]
    return out


def _flat_sums(
    sf: bool, dt: float, mat: FloatArray, dv: FloatArray, *scale: FloatArray
) -> FloatArray:
    """The inverse of :func:`_split_sums` for one step (the scale-factor terms if ``sf``)."""
    parts: list[FloatArray] = [np.array([dt]), mat.ravel(), dv]
    if sf:
        parts += [scale[0].ravel(), scale[1].ravel()]
    return np.concatenate(parts)


def _segment(eskf: ESKF, track: NavTrack, Wc: FloatArray, Ac: FloatArray) -> _Segment:
    """Cumulative per-interval sums of a segment and the filter's step in progress."""
    dt = np.diff(track.t)
    n = dt.shape[0]
    sf = eskf.n > N_ERROR
    terms = np.empty((n, 31 if sf else 13))
    terms[:, 0] = dt
    np.multiply(track.mat_nb_mid.reshape(n, 9), dt[:, None], out=terms[:, 1:10])
    terms[:, 10:13] = track.dv_force_n
    if sf:
        phi, _ = rotation_vectors(Wc[:-1], Wc[1:], dt)
        f_dt = 0.5 * (Ac[:-1] + Ac[1:]) * dt[:, None]
        mid = track.mat_nb_mid
        terms[:, 13:22] = (mid * phi[:, None, :]).reshape(n, 9)
        terms[:, 22:31] = (mid * f_dt[:, None, :]).reshape(n, 9)
    cs = np.empty((n + 1, terms.shape[1]))
    cs[0] = 0.0
    np.cumsum(terms, axis=0, out=cs[1:])
    sums = eskf._sums
    div = eskf._divisors()
    if sums.n == 0:
        return _Segment(track, div, cs, None, None, None)
    assert sums.first is not None
    carry = _flat_sums(sf, sums.dt, sums.mat, sums.dv, sums.mat_omega, sums.mat_force)
    first = _flat_sums(sf, *sums.first)
    return _Segment(track, div, cs, carry, first, (sums.vel_n, sums.lat, sums.height))


def _transition_exponent(
    eskf: ESKF, seg: _Segment, a: IntArray, b: IntArray | None, q0: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray]:
    """``A = F T`` (top rows) and ``T`` over the intervals ``a .. b - 1`` of steps starting
    at ``a`` (``q0``: the step that includes the carry); ``b`` None: over the first interval
    of the steps."""
    s = seg.first_sums(a, q0) if b is None else seg.sums(a, b, q0)
    vel, lat, h = seg.step_nav(a, q0)
    F_nav = nav_error_dynamics(vel, lat, h, eskf.options.mech)
    sf = eskf.n > N_ERROR
    A = step_exponent(
        F_nav, s[0], s[1], s[2], eskf.n, seg.divisors, s[3] if sf else None,
        s[4] if sf else None,
    )  # fmt: skip
    return A, s[0]


# ============================================================================ the core
_ROW_CHUNK = 4096  # rows with full covariances per chunk (bounds the row matrices' memory)


def advance(
    eskf: ESKF,
    t: ArrayLike,
    gyro_b: ArrayLike,
    accel_b: ArrayLike,
    *,
    output_mask: ArrayLike | None = None,
    smooth: bool = False,
    full_cov: bool = False,
    max_segment: int = 4096,
) -> _Rows | None:
    """Consume a run of IMU samples with the batch machinery (module docstring).

    The filter may be fresh (levelled or with ``rot_nb0``; the first sample must be at
    its ``t0``) or in any state after consumed samples; the pending measurement items
    (``eskf._pending``) are applied on the way. The filter is left exactly as one
    ``propagate`` call per sample would leave it (to rounding error).

    Parameters
    ----------
    eskf : ESKF
        The filter (ready: levelling done).
    t : (N,) array_like
        Sample times [s], strictly increasing, after the last consumed sample.
    gyro_b, accel_b : (N, 3) array_like
        Raw IMU samples [rad/s], [m/s^2].
    output_mask : (N,) bool array_like, optional
        Samples to report (None: no rows are computed).
    smooth : bool
        Collect what the Rauch-Tung-Striebel smoother needs (fresh filter only).
    full_cov : bool
        Full covariances in the rows (otherwise only diagonals and attitude blocks).
    max_segment : int
        Longest run of samples propagated at once (memory bound).

    Returns
    -------
    _Rows or None
        The rows (None without ``output_mask``).
    """
    o = eskf.options
    tol = o.time_tol
    t = np.asarray(t, dtype=float)
    W = np.asarray(gyro_b, dtype=float)
    A = np.asarray(accel_b, dtype=float)
    if not eskf.ready:
        raise ValueError("advance needs a levelled filter (feed the alignment window first)")
    fresh = eskf._cur is None
    if fresh:
        if abs(t[0] - eskf._t0) > tol:
            raise ValueError(f"the first IMU sample must be at t0={eskf._t0}, got {t[0]}")
        base = 1
        T_real, W_real, A_real = t, W, A
    else:
        if smooth:
            raise ValueError("smoothing needs a fresh filter (run_batch)")
        t_c, w_c, f_c = eskf._real  # type: ignore[misc]
        if t[0] <= t_c:
            raise ValueError(f"IMU time {t[0]} is not after the previous sample {t_c}")
        base = eskf._count
        T_real = np.concatenate([[t_c], t])
        W_real = np.concatenate([w_c[None], W])
        A_real = np.concatenate([f_c[None], A])
    N = T_real.shape[0]
    rows = None
    out = np.zeros(N, dtype=bool)
    if output_mask is not None:
        rows = _Rows(full=smooth or full_cov)
        out[N - t.shape[0] :] = np.asarray(output_mask, dtype=bool)
    max_segment = max(int(max_segment), 2 * o.cov_every)

    # ---- measurement items -> (virtual) samples
    # only the items up to the last sample can be used now (the queue is sorted)
    pending = eskf._pending
    limit = float(T_real[-1]) + tol
    n_now = 0
    while n_now < len(pending) and pending[n_now].t <= limit:
        n_now += 1
    user, later_items = pending[:n_now], pending[n_now:]
    virtual, where, used, early = _assign_samples(T_real, user, tol)
    for item in early:
        if fresh:
            reason = f"out of sequence: t={item.t} is before the first IMU sample"
        else:
            reason = f"out of sequence: t={item.t} is before the filter time {eskf.t}"
        eskf._record(item, 0, math.nan, False, reason)
    used_ids = {id(it) for it in used} | {id(it) for it in early}
    eskf._pending = [it for it in user if id(it) not in used_ids] + later_items
    n_virt = len(virtual)
    v_k = np.array([v[0] for v in virtual], dtype=int)
    v_t = np.array([v[1] for v in virtual], dtype=float)
    aug_real = np.arange(N) + np.searchsorted(v_k, np.arange(N), side="right")
    aug_virt = v_k + np.arange(n_virt)  # virtual j sits just before real sample v_k[j]
    M = N + n_virt
    if n_virt:
        T = np.empty(M)
        Wa = np.empty((M, 3))
        Aa = np.empty((M, 3))
        T[aug_real], Wa[aug_real], Aa[aug_real] = T_real, W_real, A_real
        frac = (v_t - T_real[v_k - 1]) / (T_real[v_k] - T_real[v_k - 1])
        T[aug_virt] = v_t
        Wa[aug_virt] = W_real[v_k - 1] + (W_real[v_k] - W_real[v_k - 1]) * frac[:, None]
        Aa[aug_virt] = A_real[v_k - 1] + (A_real[v_k] - A_real[v_k - 1]) * frac[:, None]
    else:
        T, Wa, Aa = T_real, W_real, A_real
    out_aug = np.zeros(M, dtype=bool)
    out_aug[aug_real] = out
    items_at: dict[int, list[MeasurementItem]] = {}
    for item, w_ in zip(used, where, strict=True):
        idx = int(aug_real[w_]) if isinstance(w_, int) else int(aug_virt[w_[1]])
        items_at.setdefault(idx, []).append(item)
    if o.nhc_std is not None:
        ks = np.arange(1, N)
        for k in aug_real[ks[(base + ks - 1) % o.nhc_every == 0]].tolist():
            items_at.setdefault(k, []).append(MeasurementItem(float(T[k]), "nhc", o.nhc_std))
    item_idx = np.array(sorted(items_at), dtype=int)
    valid_idx = np.array(
        sorted(i for i, its in items_at.items() if any(x.valid for x in its)), dtype=int
    )
    align_idx = np.array(
        sorted(
            i
            for i, its in items_at.items()
            if any(x.valid and x.kind in ("yaw", "sun") for x in its)
        ),
        dtype=int,
    )

    chain = _Chain() if smooth else None
    if rows is not None:
        rows.chain = chain

    # ---- the first sample
    eskf._track_dx = smooth
    if fresh:
        eskf._cur = eskf._real = (float(T[0]), Wa[0].copy(), Aa[0].copy())
        eskf._count = 1
    eskf._dx_epoch = np.zeros(eskf.n)
    P_prior0 = eskf.P
    for item in items_at.get(0, ()):
        eskf._apply(item)
    if chain is not None:
        chain.P_prior.append(P_prior0)
        chain.P_post.append(eskf.P)
        chain.Phi.append(None)
        chain.dx.append(eskf._dx_epoch)

    every = o.cov_every
    cur = 0
    n_ep = 1  # chain epochs so far
    last_done = M == 1  # the row of the last sample is written
    while cur < M - 1:
        # ---- plan the segment: up to the next reset (time rule) or yaw alignment
        stop = min(M - 1, cur + max_segment)
        capped = stop < M - 1
        later = valid_idx[np.searchsorted(valid_idx, cur, side="right") :]
        if later.size:
            due = T[later] - eskf.t_reset >= o.reset_interval_s
            k = int(due.argmax())
            if due[k] and later[k] <= stop:
                stop, capped = int(later[k]), False
        if not eskf.yaw_aligned:
            j = int(np.searchsorted(align_idx, cur, side="right"))
            if j < align_idx.size and align_idx[j] <= stop:
                stop, capped = int(align_idx[j]), False
        e0, e1 = np.searchsorted(item_idx, [cur, stop], side="right")
        epochs = item_idx[e0:e1] - cur  # samples with measurements, (0, n_seg]
        n_seg = stop - cur
        carry_n = eskf._sums.n
        ends = _step_boundaries(n_seg, epochs, every, every - carry_n if carry_n else None)
        starts = np.empty_like(ends)
        starts[0] = 0
        starts[1:] = ends[:-1]
        is_ep = np.zeros(n_seg + 1, dtype=bool)
        is_ep[epochs] = True
        lengths = ends - starts
        lengths[0] += carry_n
        complete = (lengths == every) | is_ep[ends]
        if capped and not complete[-1]:
            # a capped segment must end where the streaming filter ends a step too
            last = int(np.flatnonzero(complete)[-1]) + 1
            ends, starts, complete = ends[:last], starts[:last], complete[:last]
            n_seg = int(ends[-1])
            stop = cur + n_seg
        final = stop == M - 1
        n_steps = ends.size if complete[-1] else ends.size - 1
        # ---- nominal track
        sl = slice(cur, stop + 1)
        Wc, Ac = eskf._corrected(Wa[sl], Aa[sl])
        track = strapdown(eskf.nav, T[sl], Wc, Ac, o.mech)
        seg = _segment(eskf, track, Wc, Ac)
        eskf._sums = _StepSums()  # the first step (with the carry) is predicted below
        q0_steps = np.zeros(n_steps, dtype=bool)
        q0_steps[:1] = carry_n > 0
        consts = (eskf.bg, eskf.ba, eskf.sg, eskf.sa, eskf.yaw_aligned)
        # ---- candidate output rows: their steps (in the last segment of a run also a
        # last pseudo-step after its last complete step) and the partial steps
        sel = q = mid_i = np.zeros(0, dtype=int)
        a_rows = starts[:n_steps]
        if rows is not None:
            sel = np.flatnonzero(out_aug[cur : stop + 1 if final else stop])
            if final:
                a_rows = np.append(a_rows, ends[n_steps - 1] if n_steps else 0)
            q = np.searchsorted(a_rows, sel, side="right") - 1
            mid_i = np.flatnonzero((sel > a_rows[q]) | ((q == 0) & (carry_n > 0)))
        # ---- transition matrices of the complete steps
        if n_steps:
            A_s, T_s = _transition_exponent(eskf, seg, starts[:n_steps], ends[:n_steps], q0_steps)
            Phi, Q = van_loan(A_s, T_s, eskf.qc)
        broke = False
        x_post, P_post = [eskf.x], [eskf.P]
        P_prior: list[FloatArray] = []
        n_done = done = rel_end = 0
        Pi = Pi_at = Qa_at = None
        step_block = step_pos = np.zeros(0, dtype=int)
        if n_steps:
            # ---- blocks of steps between epochs (at most `chunk` steps each)
            is_end = is_ep[ends[:n_steps]]
            is_end[-1] = True
            b_end = _split_gaps(np.flatnonzero(is_end) + 1, o.chunk)
            if b_end.size == n_steps and not smooth:  # one step per block
                Pi, Qa = Phi, Q
                step_block = np.arange(n_steps)
                step_pos = np.zeros(n_steps, dtype=int)
            else:
                b_start = np.concatenate([[0], b_end[:-1]])
                step_block = np.repeat(np.arange(b_end.size), b_end - b_start)
                step_pos = np.arange(n_steps) - b_start[step_block]
                Pi, Qa, Pi_at, Qa_at = block_transitions(
                    Phi, Q, b_start, b_end, step_block, step_pos
                )
            # ---- sequential pass over the block ends: filterpy predict, updates, resets
            n_done = b_end.size
            for s, e_rel in enumerate(ends[b_end - 1].tolist()):
                eskf.x, eskf.P = kf_predict(eskf.x, eskf.P, Pi[s], Qa[s])
                eskf._set_track(track, e_rel)
                its = items_at.get(cur + e_rel)
                if chain is None:
                    if its:
                        resets = eskf.n_resets
                        for item in its:
                            eskf._apply(item)
                        broke = eskf.n_resets != resets
                else:
                    P_prior.append(eskf.P)
                    eskf._dx_epoch = np.zeros(eskf.n)
                    aligned_before, resets = eskf.yaw_aligned, eskf.n_resets
                    for item in its or ():
                        eskf._apply(item)
                    broke = eskf.n_resets != resets
                    chain.P_prior.append(P_prior[-1])
                    chain.P_post.append(eskf.P)
                    chain.Phi.append(Pi[s] if aligned_before == eskf.yaw_aligned else None)
                    chain.dx.append(eskf._dx_epoch)
                x_post.append(eskf.x)
                P_post.append(eskf.P)
                if broke:
                    n_done = s + 1
                    break
            done = int(b_end[n_done - 1])
            rel_end = int(ends[done - 1])
        tail = final and not broke
        if tail:
            eskf._set_track(track, n_seg)
            if done < ends.size:  # the step in progress at the end: carry it over
                a_t = np.array([rel_end])
                q0_t = np.array([done == 0 and carry_n > 0])
                s_t = seg.sums(a_t, np.array([n_seg]), q0_t)
                vel, lat, h = seg.step_nav(a_t, q0_t)
                f_t = seg.first_sums(a_t, q0_t)
                sums = _StepSums(
                    n=n_seg - rel_end + (carry_n if done == 0 else 0),
                    dt=float(s_t[0][0]),
                    mat=s_t[1][0].copy(),
                    dv=s_t[2][0].copy(),
                    vel_n=vel[0],
                    lat=float(lat[0]),
                    height=float(h[0]),
                )
                scale_first = (np.zeros((3, 3)), np.zeros((3, 3)))
                if eskf.n > N_ERROR:
                    sums.mat_omega, sums.mat_force = s_t[3][0].copy(), s_t[4][0].copy()
                    scale_first = (f_t[3][0], f_t[4][0])
                sums.first = (float(f_t[0][0]), f_t[1][0], f_t[2][0], *scale_first)
                eskf._sums = sums
        # ---- output rows of this segment
        if rows is not None and sel.size:
            keep = np.ones(sel.size, dtype=bool) if tail else sel < rel_end
            if keep.any():
                # state at the start of every step of the rows (the block start propagated
                # through the steps before it; the pseudo-step: the state at the end)
                n_q = done + int(tail)
                blk = np.full(n_q, n_done)
                pos = np.zeros(n_q, dtype=int)
                blk[:done], pos[:done] = step_block[:done], step_pos[:done]
                x_step = np.array(x_post)[blk]
                P_step = np.array(P_post)[blk]
                inner = np.flatnonzero(pos > 0)
                if inner.size:
                    assert Pi_at is not None and Qa_at is not None
                    Pa = Pi_at[inner]
                    x_step[inner] = (Pa @ x_step[inner][..., None])[..., 0]
                    P_step[inner] = Pa @ P_step[inner] @ np.swapaxes(Pa, -1, -2) + Qa_at[inner]
                # rows inside a step: the step so far with the error dynamics frozen at
                # their mean over the step's first interval (ESKF.state)
                mid_k = mid_i[keep[mid_i]]
                kept = np.flatnonzero(keep)
                mid_pos = np.searchsorted(kept, mid_k)  # mid rows among the kept rows
                q_mid = q[mid_k]
                q0_mid = (q_mid == 0) & (carry_n > 0)
                tau = seg.duration(a_rows[q_mid], sel[mid_k], q0_mid)
                steps, step_of = np.unique(q_mid, return_inverse=True)
                F0 = np.zeros((0, N_DYNAMIC, eskf.n))
                if steps.size:
                    A1, T1 = _transition_exponent(
                        eskf, seg, a_rows[steps], None, (steps == 0) & (carry_n > 0)
                    )
                    F0 = A1 / T1[:, None, None]
                # polynomials per step pay off from about two rows per step
                per_row = rows.full or mid_k.size < 2 * steps.size
                if not per_row:
                    poly = partial_step_polynomials(F0, P_step[steps], x_step[steps], eskf.qc)
                    _segment_rows(
                        rows, seg, T[cur + sel[kept]], sel[kept], q[kept], mid_pos,
                        (*poly, step_of, tau), x_step, P_step, consts,
                    )  # fmt: skip
                for c0 in range(0, kept.size if per_row else 0, _ROW_CHUNK):
                    ks = kept[c0 : c0 + _ROW_CHUNK]
                    m0, m1 = np.searchsorted(mid_pos, [c0, c0 + ks.size])
                    mp = mid_pos[m0:m1] - c0  # mid rows of this chunk
                    tau_c = tau[m0:m1]
                    mats = van_loan(F0[step_of[m0:m1]] * tau_c[:, None, None], tau_c, eskf.qc)
                    _segment_rows(
                        rows, seg, T[cur + sel[ks]], sel[ks], q[ks], mp, mats, x_step, P_step,
                        consts,
                    )  # fmt: skip
                    if chain is not None:
                        _chain_rows(
                            chain, rows, q[ks], mp, done, step_block, Pi_at, Pi, mats[0],
                            P_prior, n_ep, eskf.n,
                        )  # fmt: skip
            if tail:
                last_done = True
        n_ep += n_done
        cur = M - 1 if tail else cur + rel_end
    eskf._real = (float(T_real[-1]), W_real[-1].copy(), A_real[-1].copy())
    eskf._cur = eskf._real
    eskf._count = base + N - 1
    eskf._track_dx = False
    if rows is not None and out[-1] and not last_done:
        _state_row(eskf, rows, chain)
    return rows


def _state_row(eskf: ESKF, rows: _Rows, chain: _Chain | None) -> None:
    """A row with the filter's current state (no step in progress)."""
    nom = eskf._nom
    P = eskf.P
    rows.add(
        t=np.array([float(nom.t)]),
        mat=nom.mat_nb[None],
        vel=nom.vel_n[None],
        lat=np.array([float(nom.lat)]),
        lon=np.array([float(nom.lon)]),
        h=np.array([float(nom.height)]),
        x=eskf.x[None],
        var=np.diagonal(P)[None].copy(),
        P_att=P[None, ATT, ATT],
        bg=eskf.bg[None],
        ba=eskf.ba[None],
        sg=eskf.sg[None],
        sa=eskf.sa[None],
        al=np.array([eskf.yaw_aligned]),
    )
    if rows.full:
        rows.add(P=P[None])
    if chain is not None:
        chain.out_next.append(np.array([-1]))
        chain.out_gain.append(np.zeros((1, eskf.n, eskf.n)))


def _segment_rows(
    rows: _Rows,
    seg: _Segment,
    t_rows: FloatArray,
    sel: IntArray,
    q: IntArray,
    mid: IntArray,
    mats: tuple[NDArray[Any], ...],
    x_step: FloatArray,
    P_step: FloatArray,
    consts: tuple[FloatArray, FloatArray, FloatArray, FloatArray, bool],
) -> None:
    """Rows at the relative samples ``sel`` of a segment (what ``ESKF.state()`` gives).

    ``q`` are the rows' steps with the states ``x_step``, ``P_step`` at their starts;
    the rows ``mid`` (inside a step) propagate the partial step with ``mats``: ``(Phi, Q)``
    per mid row (always with full covariances), or ``(cx, cv, ca, i, tau)``: the polynomials of
    :func:`~polins.fusion.eskf.partial_step_polynomials` of the steps, each mid row's index
    ``i`` into them and its partial-step length ``tau`` [s].
    """
    R = sel.size
    x = x_step[q]
    if len(mats) == 2:
        P = P_step[q]
        if mid.size:
            Phi_p, Q_p = mats
            x[mid] = (Phi_p @ x[mid][..., None])[..., 0]
            P[mid] = Phi_p @ P[mid] @ np.swapaxes(Phi_p, -1, -2) + Q_p
        var = np.diagonal(P, axis1=-2, axis2=-1).copy()
        P_att = P[:, ATT, ATT]
        if rows.full:
            rows.add(P=P)
    else:
        var = np.diagonal(P_step, axis1=-2, axis2=-1)[q]
        P_att = P_step[q, ATT, ATT]
        if mid.size:
            cx, cv, ca, i, tau = mats
            n = x.shape[1]
            coef = np.concatenate([cv, ca.reshape(*ca.shape[:2], 9), np.zeros_like(cv)], axis=2)
            coef[:, :4, n + 9 :] = cx
            val = _polynomials_at(coef, i, tau)
            var[mid], P_att[mid], x[mid] = (
                val[:, :n],
                val[:, n : n + 9].reshape(-1, 3, 3),
                val[:, n + 9 :],
            )
    bg, ba, sg, sa, aligned = consts
    tr = seg.track
    rows.add(
        t=t_rows,
        mat=tr.mat_nb[sel],
        vel=tr.vel_n[sel],
        lat=tr.lat[sel],
        lon=tr.lon[sel],
        h=tr.height[sel],
        x=x,
        var=var,
        P_att=P_att,
        bg=np.broadcast_to(bg, (R, 3)),
        ba=np.broadcast_to(ba, (R, 3)),
        sg=np.broadcast_to(sg, (R, 3)),
        sa=np.broadcast_to(sa, (R, 3)),
        al=np.full(R, aligned),
    )


def _polynomials_at(coef: FloatArray, i: NDArray[Any], tau: NDArray[Any]) -> FloatArray:
    """``sum_p tau^p coef[i, p]`` per row ``(R, m)``: coefficients ``coef`` ``(steps, degree
    + 1, m)``, the rows' steps ``i`` (non-decreasing) and arguments ``tau`` ``(R,)``.

    One batched product per step (the rows of a step padded to the longest run of rows).
    """
    steps, deg = coef.shape[:2]
    counts = np.bincount(i, minlength=steps)
    pos = np.arange(i.size) - (np.cumsum(counts) - counts)[i]  # row within its step
    powers = np.zeros((steps, int(counts.max(initial=0)), deg))
    powers[i, pos] = tau[:, None] ** np.arange(deg)
    return (powers @ coef)[i, pos]


def _chain_rows(
    chain: _Chain,
    rows: _Rows,
    q: IntArray,
    mid_pos: IntArray,
    done: int,
    step_block: IntArray,
    Pi_at: FloatArray | None,
    Pi: FloatArray | None,
    Phi_p: FloatArray | None,
    P_prior: list[FloatArray],
    n_ep: int,
    n: int,
) -> None:
    """Smoother gains of the rows just added: ``C_o = P_o Pi(end <- o)^T P_prior(end)^-1``
    with ``Pi(end <- o)`` from the block transition and the partial products (mid-step: the
    inverse of the partial step)."""
    R = q.size
    nxt = np.full(R, -1)
    gain = np.zeros((R, n, n))
    mid = np.zeros(R, dtype=bool)
    mid[mid_pos] = True
    inside = q < done  # rows after the last epoch have no later epoch
    if np.any(inside):
        assert Pi is not None and Pi_at is not None
        qi = q[inside]
        b = step_block[qi]
        trans = np.swapaxes(
            np.linalg.solve(np.swapaxes(Pi_at[qi], -1, -2), np.swapaxes(Pi[b], -1, -2)), -1, -2
        )
        mid_i = mid[inside]
        if np.any(mid_i) and Phi_p is not None:
            take = inside[mid]  # Phi_p rows are the mid rows
            trans[mid_i] = np.swapaxes(
                np.linalg.solve(
                    np.swapaxes(Phi_p[take], -1, -2), np.swapaxes(trans[mid_i], -1, -2)
                ),
                -1,
                -2,
            )
        Pp = np.array(P_prior)[b]
        P_o = rows.cols["P"][-1][inside]
        gain[inside] = np.swapaxes(np.linalg.solve(Pp, trans @ P_o), -1, -2)
        nxt[inside] = n_ep + b
    chain.out_next.append(nxt)
    chain.out_gain.append(gain)


# ============================================================================ whole logs
def run_batch(
    eskf: ESKF,
    t: ArrayLike,
    gyro_b: ArrayLike,
    accel_b: ArrayLike,
    items: Sequence[MeasurementItem],
    *,
    output_mask: ArrayLike | None = None,
    smooth: bool = False,
    full_cov: bool = False,
    max_segment: int = 4096,
) -> BatchOutput:
    """Run a fresh :class:`~polins.fusion.eskf.ESKF` over a whole IMU log.

    Gives the same estimates as feeding the samples one by one to ``ESKF.propagate``
    (with the items queued by ``ESKF.add_items``), to rounding error (module docstring).

    Parameters
    ----------
    eskf : ESKF
        A filter that has not consumed any sample yet; it is left at the end of the log.
    t : (N,) array_like
        IMU sample times [s], strictly increasing, ``t[0] = eskf.t``.
    gyro_b, accel_b : (N, 3) array_like
        Raw IMU samples [rad/s], [m/s^2].
    items : sequence of MeasurementItem
        Measurements (any order), added to the filter's queue.
    output_mask : (N,) bool array_like, optional
        IMU samples to report (default all).
    smooth : bool
        Also run the Rauch-Tung-Striebel smoother.
    full_cov : bool
        Keep the full covariance of every row (``BatchOutput.P``).
    max_segment : int
        Longest run of samples propagated at once (memory bound).

    Returns
    -------
    BatchOutput
    """
    o = eskf.options
    tol = o.time_tol
    t = np.asarray(t, dtype=float)
    W = np.asarray(gyro_b, dtype=float)
    A = np.asarray(accel_b, dtype=float)
    N = t.shape[0]
    if eskf._cur is not None or (eskf._align_buffer is not None and eskf._align_buffer):
        raise ValueError("run_batch needs a filter that has not consumed any IMU sample")
    if N < 2 or W.shape != (N, 3) or A.shape != (N, 3):
        raise ValueError("run_batch needs at least 2 samples: t (N,), gyro_b and accel_b (N, 3)")
    if abs(t[0] - eskf._t0) > tol:
        raise ValueError(f"the first IMU sample must be at t0={eskf._t0}, got {t[0]}")
    out = np.ones(N, dtype=bool) if output_mask is None else np.asarray(output_mask, dtype=bool)
    if out.shape != (N,):
        raise ValueError(f"output_mask must have shape ({N},), got {out.shape}")
    if smooth or full_cov:
        row_bytes = eskf.n * eskf.n * 8 * (3 if smooth else 1)
        if out.sum() * row_bytes > 4e9:
            raise ValueError(
                f"{int(out.sum())} output rows with full covariances need "
                f"{out.sum() * row_bytes / 1e9:.1f} GB; report fewer rows (output_rate_hz)"
            )
    # ---- self-alignment (levelling), as the streaming path does it
    if not eskf.ready:
        k_end = int(np.searchsorted(t - eskf._t0, o.align_s - tol, side="left"))
        if k_end >= N:
            raise ValueError(
                f"the IMU log ({t[-1] - t[0]:.3f} s) is shorter than the alignment window "
                f"align_s={o.align_s} s; give rot_nb0 or a longer log"
            )
        window = [
            (float(t[k]), W[k].copy(), A[k].copy())
            for k in range(k_end + 1)
            if t[k] - eskf._t0 <= o.align_s + tol
        ]
        eskf._align_buffer = None
        eskf._level(window)
    eskf._pending = sorted([*eskf._pending, *items], key=lambda it: it.order)
    rows = advance(
        eskf, t, W, A, output_mask=out, smooth=smooth, full_cov=full_cov, max_segment=max_segment
    )
    assert rows is not None
    return _assemble(eskf, rows, smooth)


def _assemble(eskf: ESKF, rows: _Rows, smooth: bool) -> BatchOutput:
    """Stack the output rows, apply the error state, and run the smoother if asked."""
    if not rows.cols:
        raise ValueError("output_mask selects no IMU sample")
    cat = {k: np.concatenate(v) for k, v in rows.cols.items()}
    x = cat["x"]
    sf = eskf.n > N_ERROR

    def build(
        dx: FloatArray, var: FloatArray, P_att: FloatArray, P: FloatArray | None
    ) -> BatchOutput:
        rot, vel, lat, lon, h = _inject_many(
            cat["mat"], cat["vel"], cat["lat"], cat["lon"], cat["h"], dx
        )
        return BatchOutput(
            t=cat["t"],
            rot_nb=rot,
            vel_n=vel,
            lat=lat,
            lon=lon,
            height=h,
            bg=cat["bg"] + dx[:, BG],
            ba=cat["ba"] + dx[:, BA],
            sg=cat["sg"] + dx[:, SG] if sf else None,
            sa=cat["sa"] + dx[:, SA] if sf else None,
            sigma=np.sqrt(np.clip(var, 0.0, None)),
            P_att=P_att,
            yaw_aligned=cat["al"].astype(bool),
            P=P,
        )

    P_rows = cat.get("P")
    result = build(x, cat["var"], cat["P_att"], P_rows)
    chain = rows.chain
    if not smooth or chain is None:
        return result
    assert P_rows is not None
    nxt = np.concatenate(chain.out_next)
    gain = np.concatenate(chain.out_gain)
    delta, P_s = rts_smooth(chain.P_prior, chain.P_post, chain.Phi, chain.dx)
    d_out = np.zeros_like(x)
    P_out = P_rows.copy()
    idx = np.flatnonzero(nxt >= 0)
    if idx.size:
        i = nxt[idx]
        linked = np.array([chain.Phi[k] is not None for k in i])
        idx, i = idx[linked], i[linked]
        innov = np.array(chain.dx)[i] + delta[i]
        d_out[idx] = (gain[idx] @ innov[..., None])[..., 0]
        dP = P_s[i] - np.array(chain.P_prior)[i]
        P_out[idx] = P_rows[idx] + gain[idx] @ dP @ np.swapaxes(gain[idx], -1, -2)
    var = np.diagonal(P_out, axis1=-2, axis2=-1).copy()
    smoothed = build(x + d_out, var, P_out[:, ATT, ATT], P_out)
    return replace(result, smoothed=smoothed)


def rts_smooth(
    P_prior: Sequence[FloatArray],
    P_post: Sequence[FloatArray],
    Phi: Sequence[FloatArray | None],
    dx: Sequence[FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """Rauch-Tung-Striebel smoother in error-state (correction) form.

    With the filtered estimates ``x_i`` at epochs ``i``, the transitions ``Phi_i`` from
    epoch ``i - 1`` to ``i`` (None starts a new chain, e.g. at the yaw alignment), the
    prior and posterior covariances and the filter's update corrections ``dx_i`` at each
    epoch, the smoothed estimate is ``x_i (+) delta_i`` with::

        C_i     = P_i^+ Phi_{i+1}^T (P_{i+1}^-)^-1
        delta_i = C_i (dx_{i+1} + delta_{i+1}),            delta_last = 0
        P_i^s   = P_i^+ + C_i (P_{i+1}^s - P_{i+1}^-) C_i^T

    Returns
    -------
    delta : (E, n) ndarray
        Smoothed corrections at the epochs.
    P_s : (E, n, n) ndarray
        Smoothed covariances.
    """
    E = len(P_post)
    n = P_post[0].shape[0]
    delta = np.zeros((E, n))
    P_s = np.array(P_post, dtype=float)
    for i in range(E - 2, -1, -1):
        phi = Phi[i + 1]
        if phi is None:
            continue
        C = np.linalg.solve(P_prior[i + 1], phi @ P_post[i]).T
        delta[i] = C @ (dx[i + 1] + delta[i + 1])
        P_s[i] = P_post[i] + C @ (P_s[i + 1] - P_prior[i + 1]) @ C.T
    return delta, P_s
