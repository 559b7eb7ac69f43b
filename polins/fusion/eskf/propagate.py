"""The fast path of the ESKF: the nominal strapdown vectorised between resets, the covariance per step, rows interpolated.

Between resets the nominal state does not depend on the measurement updates (they act on
the error state), so :func:`advance` propagates it over a whole segment of samples at once
(:func:`polins.ins.strapdown.strapdown`). The segment's covariance steps (at most
``cov_step_s``; a step also ends at every measurement time) are discretised together
(:func:`~polins.fusion.eskf.dynamics.discretize`), then filterpy's ``predict`` and the
filter's own measurement handling (``ESKF.apply``:
gate, update, log, reset) run once per step, in order. A reset ends the segment; the next
starts from the injected state. Measurement times between IMU samples get a virtual sample
with the IMU interpolated linearly, as in the streaming filter.

Output rows between the ends of a step (its *nodes*) interpolate the error state and the
covariance linearly between the posterior at the step start and the prior at the step end:
within the step the error state evolves under ``Phi(tau)``, so the difference is of the
order of the discretisation error (tests/test_eskf.py compares with a reference run at one
covariance step per IMU interval). The nominal part of a row is the strapdown's sample.

Importing this module loads the compiled strapdown (:func:`load_kernels`: numba, its
machine code cached on disk), so that the first run of the filter in a process does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.config import TIME_TOL_S, FuseConfig
from polins.fusion.eskf.blocks import Layout, inject_nav, scale_divisors
from polins.fusion.eskf.dynamics import StepNominal, discretize, step_nominal
from polins.fusion.items import MeasurementItem, UpdateRecord
from polins.fusion.vehicle import VehicleAiding
from polins.ins.state import NavState
from polins.ins.strapdown import Mechanization, rotation_vectors, strapdown
from polins.models import ImuModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int_]

MAX_SEGMENT = 4096  # longest run of samples propagated at once (memory bound)
MIN_SEGMENT = 256  # shortest planned run (after a reset by the attitude-error threshold)
_CHUNK = 64  # covariance steps discretised at once
_NODE_PARTS = ("x_pre", "x_post", "var_pre", "var_post", "att_pre", "att_post", "dx", "linked",
               "P_pre", "P_post", "Phi")  # fmt: skip


class Filter(Protocol):
    """What the fast path uses of the filter (:class:`~polins.fusion.eskf.filter.ESKF`):
    its configuration, error state and nominal state, and its steps."""

    config: FuseConfig
    model: ImuModel
    layout: Layout
    mech: Mechanization
    qc: FloatArray
    n: int
    cov_every: int  # samples per covariance step
    nhc_every: int  # samples per non-holonomic update
    vehicle: VehicleAiding  # the NHC and standstill pseudo-measurements
    count: int  # real samples consumed
    n_resets: int
    t_reset: float
    reset_interval_s: float
    x: FloatArray
    P: FloatArray
    correction: FloatArray  # sum of the update corrections since the last node
    errors: dict[str, FloatArray]
    yaw_aligned: bool
    yaw_epoch: int  # (re-)acquisitions of the yaw
    t: float
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: float
    lon: float
    alt_m: float

    @property
    def started(self) -> bool: ...
    def nominal(self) -> tuple[float, FloatArray, FloatArray, float, float, float]: ...
    def predict(self, Phi: FloatArray, Q: FloatArray) -> None: ...
    def apply(self, item: MeasurementItem) -> UpdateRecord | None: ...
    def reject(self, item: MeasurementItem, reason: str) -> UpdateRecord: ...
    def take_items(self, t_end: float) -> list[MeasurementItem]: ...
    def finish_run(self, t: float, gyro_b: FloatArray, accel_b: FloatArray, count: int) -> None: ...


def checked_run(
    t: ArrayLike, gyro_b: ArrayLike, accel_b: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A run of IMU samples as arrays ``(N,)`` [s], ``(N, 3)`` [rad/s], ``(N, 3)`` [m/s^2];
    ``ValueError`` (one line) for other shapes, non-finite values or times not increasing."""
    t_a = np.asarray(t, dtype=float)
    W = np.asarray(gyro_b, dtype=float)
    A = np.asarray(accel_b, dtype=float)
    N = t_a.shape[0] if t_a.ndim == 1 else -1
    if N < 0 or W.shape != (N, 3) or A.shape != (N, 3):
        raise ValueError(
            f"propagate_many needs t (N,), gyro_b and accel_b (N, 3); got shapes "
            f"{t_a.shape}, {W.shape}, {A.shape}"
        )
    if not (np.isfinite(t_a).all() and np.isfinite(W).all() and np.isfinite(A).all()):
        raise ValueError("gyro_b and accel_b must be finite 3-vectors [rad/s], [m/s^2]")
    if N > 1 and not np.all(np.diff(t_a) > 0):
        k = int(np.flatnonzero(np.diff(t_a) <= 0)[0])
        raise ValueError(f"IMU time {t_a[k + 1]} is not after the previous sample {t_a[k]}")
    return t_a, W, A


def load_kernels() -> None:
    """Load the compiled strapdown the fast path runs (once per process: numba, the machine
    code cached on disk next to :mod:`polins.ins.strapdown`)."""
    nav0 = NavState(0.0, Rotation.identity(), np.zeros(3), 0.0, 0.0, 0.0)
    gravity = np.tile([0.0, 0.0, 9.8], (2, 1))
    strapdown(nav0, np.array([0.0, 0.01]), np.zeros((2, 3)), gravity, Mechanization())


@dataclass(frozen=True, eq=False)
class Nodes:
    """The filter at the ends of its covariance steps (G nodes; node 0 is the start).

    ``x_pre``/``x_post`` (G, n): error state before the updates at the node and after
    them (and after a reset); ``var_pre``/``var_post`` (G, n) and ``att_pre``/``att_post``
    (G, 3, 3): covariance diagonals and attitude blocks. ``dx`` (G, n): the update
    corrections at the node (before any reset); ``linked`` (G,): False where a new chain
    starts (node 0, a yaw (re-)acquisition). With ``full``: ``P_pre``, ``P_post`` and the step
    transitions ``Phi`` (into the node) (G, n, n), for the smoother.
    """

    x_pre: FloatArray
    x_post: FloatArray
    var_pre: FloatArray
    var_post: FloatArray
    att_pre: FloatArray
    att_post: FloatArray
    dx: FloatArray
    linked: NDArray[np.bool_]
    P_pre: FloatArray | None = None
    P_post: FloatArray | None = None
    Phi: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class Rows:
    """Output rows (R): nominal state, the sensor-error estimates of their segment, and
    where they sit between nodes: the row lies in the step from node ``node`` to
    ``node + 1`` at the fraction ``w`` of it."""

    t: FloatArray
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt_m: FloatArray
    errors: dict[str, FloatArray]
    node: IntArray
    w: FloatArray
    yaw_aligned: NDArray[np.bool_]


class _Log:
    """Collects nodes and rows during :func:`advance`.

    A node keeps references to the filter's arrays (each step's prediction makes new
    ones); at the end of each segment (:meth:`close_segment`) the segment's covariances
    are reduced at once to their diagonals and attitude blocks, unless ``full``: a node
    then holds ~1 KB instead of ~8 KB (22 states), an hour's 36 000 nodes 31 MB.
    """

    def __init__(self, filt: Filter, full: bool) -> None:
        self.full = full
        self.n = filt.n
        self.open: list[tuple[Any, ...]] = []  # the segment's nodes, not yet reduced
        self.count = 0  # nodes so far
        self.parts: dict[str, list[NDArray[Any]]] = {k: [] for k in _NODE_PARTS}
        self.rows: dict[str, list[NDArray[Any]]] = {k: [] for k in Rows.__dataclass_fields__}
        self.row_errors: dict[str, list[FloatArray]] = {k: [] for k in filt.errors}
        self.node(filt, filt.x, filt.P, None, False)

    def node(self, filt: Filter, x_pre: FloatArray, P_pre: FloatArray,
             Phi: FloatArray | None, linked: bool) -> None:  # fmt: skip
        """The node at the filter's time (after its updates): the prior ``x_pre, P_pre``."""
        self.open.append((x_pre, filt.x, P_pre, filt.P, filt.correction, linked, Phi))
        self.count += 1
        filt.correction = np.zeros(self.n)

    def close_segment(self) -> None:
        """Reduce the open nodes (class docstring)."""
        if not self.open:
            return
        x_pre, x_post, P_pre, P_post, dx, linked, Phi = zip(*self.open, strict=True)
        self.open = []
        Pa, Pb = np.stack(P_pre), np.stack(P_post)
        parts = {"x_pre": np.stack(x_pre), "x_post": np.stack(x_post), "dx": np.stack(dx),
                 "linked": np.array(linked, dtype=bool),
                 "var_pre": np.diagonal(Pa, axis1=1, axis2=2).copy(),
                 "var_post": np.diagonal(Pb, axis1=1, axis2=2).copy(),
                 "att_pre": Pa[:, 0:3, 0:3].copy(), "att_post": Pb[:, 0:3, 0:3].copy()}  # fmt: skip
        if self.full:
            eye = np.eye(self.n)
            parts.update(P_pre=Pa, P_post=Pb,
                         Phi=np.stack([eye if p is None else p for p in Phi]))  # fmt: skip
        for key, value in parts.items():
            self.parts[key].append(value)

    def add_rows(self, t: FloatArray, nominal: tuple[FloatArray, ...], errors: dict[str, FloatArray],
                 node: IntArray, w: FloatArray, aligned: NDArray[np.bool_]) -> None:  # fmt: skip
        r = self.rows
        for key, value in zip(("mat_nb", "vel_n", "lat", "lon", "alt_m"), nominal, strict=True):
            r[key].append(value)
        r["t"].append(t)
        r["node"].append(node)
        r["w"].append(w)
        r["yaw_aligned"].append(aligned)
        for k, v in errors.items():
            self.row_errors[k].append(np.broadcast_to(v, (t.shape[0], v.shape[0])))

    def result(self) -> tuple[Nodes, Rows]:
        self.close_segment()
        nodes = Nodes(**{k: np.concatenate(v) for k, v in self.parts.items() if v})
        rows = {k: np.concatenate(v) for k, v in self.rows.items() if k != "errors"}
        errors = {k: np.concatenate(v) for k, v in self.row_errors.items()}
        return nodes, Rows(errors=errors, **rows)


def _schedule(
    filt: Filter, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray, base: int
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, dict[int, list[MeasurementItem]]]:
    """The merged sample grid (real samples and the virtual samples of measurement times
    between them), the merged index of each real sample, and the items per merged index."""
    W, A = gyro_b, accel_b
    tol = TIME_TOL_S
    N = t.shape[0]
    items = filt.take_items(float(t[-1]) + tol)
    early = [it for it in items if it.t < t[0] - tol]
    for it in early:
        filt.reject(it, f"out of sequence: t={it.t} is before the filter time {t[0]}")
    items = items[len(early) :] if early else items
    t_items = np.array([it.t for it in items], dtype=float)
    ks = np.searchsorted(t, t_items - tol, side="left").tolist()
    virtual: list[tuple[int, float]] = []
    where: list[tuple[bool, int]] = []  # (real, index among real / virtual samples)
    for it, k in zip(items, ks, strict=True):
        if t[k] <= it.t + tol:
            where.append((True, k))
        elif virtual and virtual[-1][0] == k and it.t <= virtual[-1][1] + tol:
            where.append((False, len(virtual) - 1))
        else:
            virtual.append((k, it.t))
            where.append((False, len(virtual) - 1))
    if virtual:
        kv = np.array([v[0] for v in virtual])
        tv = np.array([v[1] for v in virtual])
        frac = ((tv - t[kv - 1]) / (t[kv] - t[kv - 1]))[:, None]
        T = np.concatenate([t, tv])
        order = np.argsort(T, kind="stable")
        T = T[order]
        W = np.concatenate([W, W[kv - 1] + (W[kv] - W[kv - 1]) * frac])[order]
        A = np.concatenate([A, A[kv - 1] + (A[kv] - A[kv - 1]) * frac])[order]
        merged = np.empty(order.size, dtype=int)
        merged[order] = np.arange(order.size)
    else:
        T, merged = t, np.arange(N)
    epochs: dict[int, list[MeasurementItem]] = {}
    for it, (real, i) in zip(items, where, strict=True):
        m = int(merged[i if real else N + i])
        epochs.setdefault(m, []).append(filt.vehicle.attach(it, W[m]) if it.kind == "odo" else it)
    # the vehicle's pseudo-measurements (NHC, standstill) along the new samples
    first = 0 if not filt.started else 1
    new = slice(first, N)
    for kk, it in filt.vehicle.items(t[new], gyro_b[new], accel_b[new], base + first - 1):
        epochs.setdefault(int(merged[kk + first]), []).append(it)
    return T, W, A, merged[:N], epochs


def advance(
    filt: Filter,
    t: FloatArray,
    gyro_b: FloatArray,
    accel_b: FloatArray,
    output_mask: NDArray[np.bool_] | None = None,
    *,
    full: bool = False,
) -> tuple[Nodes, Rows] | None:
    """Run the filter over IMU samples with the fast path (module docstring).

    ``t[0]`` is the filter's current sample: the first sample of a levelled filter that has
    consumed none (``t[0] = t0``), or its last consumed sample (no step in progress:
    ``ESKF.flush``). The pending items up to ``t[-1]`` are applied on the way.

    Parameters
    ----------
    filt : ESKF
        The filter; left at ``t[-1]``, as the streaming filter would be.
    t : (N,) ndarray
        Sample times [s], strictly increasing.
    gyro_b, accel_b : (N, 3) ndarray
        Raw IMU samples [rad/s], [m/s^2].
    output_mask : (N,) bool ndarray, optional
        Samples to report (None: no rows).
    full : bool
        Keep the full node covariances and transitions (for the smoother).

    Returns
    -------
    (Nodes, Rows) or None
        None without ``output_mask``.
    """
    fresh = not filt.started
    base = 1 if fresh else filt.count
    T, W, A, real_at, epochs = _schedule(filt, t, gyro_b, accel_b, base)
    M = T.shape[0]
    for it in epochs.pop(0, []):  # items at the first sample (a fresh filter)
        filt.apply(it)
    rec = None if output_mask is None else _Log(filt, full)  # node 0: the start
    out = np.zeros(M, dtype=bool)
    if output_mask is not None:
        out[real_at[np.asarray(output_mask, dtype=bool)]] = True
    ep = np.array(sorted(epochs), dtype=int)
    s = 0
    reset_s = filt.reset_interval_s
    horizon = MIN_SEGMENT  # planned samples: doubled after a segment without an early reset
    while s < M - 1:
        due = int(np.searchsorted(T, float(filt.t_reset + reset_s - TIME_TOL_S)))
        i_due = int(np.searchsorted(ep, max(due, s + 1)))
        e = min(M - 1, s + horizon, int(ep[i_due]) if i_due < ep.size else M - 1)
        ends = _step_ends(s, e, ep, filt.cov_every)
        s = _segment(filt, T, W, A, s, ends, epochs, rec, out)
        early = s < e and filt.t - filt.t_reset < reset_s  # a reset by the angle threshold
        horizon = MIN_SEGMENT if early else min(2 * horizon, MAX_SEGMENT)
    last = len(t) - 1
    filt.finish_run(float(t[last]), gyro_b[last], accel_b[last], base + last)
    if rec is None:
        return None
    if out[M - 1]:
        nominal = filt.nominal()
        rec.add_rows(
            np.array([nominal[0]]), tuple(np.asarray(v)[None] for v in nominal[1:]),
            filt.errors, np.array([rec.count - 1]), np.zeros(1),
            np.array([filt.yaw_aligned]),
        )  # fmt: skip
    return rec.result()


def _step_ends(s: int, e: int, epochs: IntArray, every: int) -> IntArray:
    """Ends of the covariance steps in ``(s, e]``: after ``every`` intervals, at each epoch
    (a sample with measurements) and at ``e``."""
    marks = [*epochs[(epochs > s) & (epochs < e)].tolist(), e]
    ends: list[int] = []
    prev = s
    for m in marks:
        ends.extend(range(prev + every, m, every))
        ends.append(m)
        prev = m
    return np.array(ends, dtype=int)


def _segment(
    filt: Filter,
    T: FloatArray,
    W: FloatArray,
    A: FloatArray,
    s: int,
    ends: IntArray,
    epochs: dict[int, list[MeasurementItem]],
    rec: _Log | None,
    out: NDArray[np.bool_],
) -> int:
    """Steps of one segment from merged sample ``s``; returns where the next one starts."""
    e = int(ends[-1])
    wc, fc = filt.layout.correct(W[s : e + 1], A[s : e + 1], filt.errors)
    t0, mat0, vel0, lat0, lon0, alt0 = filt.nominal()
    start = NavState(t0, Rotation.from_matrix(mat0, assume_valid=True), vel0, lat0, lon0, alt0)
    track = strapdown(start, T[s : e + 1], wc, fc, filt.mech)
    dt = np.diff(T[s : e + 1])
    sf = "sg" in filt.errors
    rate_sq_dt = np.sum((0.5 * (wc[:-1] + wc[1:])) ** 2, axis=1) * dt
    parts = [dt[:, None], (track.mat_nb_mid * dt[:, None, None]).reshape(-1, 9), track.dv_force_n,
             rate_sq_dt[:, None]]  # fmt: skip
    if sf:
        phi, _ = rotation_vectors(wc[:-1], wc[1:], dt)
        f_dt = 0.5 * (fc[:-1] + fc[1:]) * dt[:, None]
        parts += [(track.mat_nb_mid * phi[:, None, :]).reshape(-1, 9),
                  (track.mat_nb_mid * f_dt[:, None, :]).reshape(-1, 9)]  # fmt: skip
    cs = np.zeros((dt.shape[0] + 1, sum(p.shape[1] for p in parts)))
    np.cumsum(np.hstack(parts), axis=0, out=cs[1:])
    a = np.concatenate([[0], ends[:-1] - s])
    b = ends - s
    sums = cs[b] - cs[a]
    S = b.size
    step = step_nominal(
        sums[:, 0], sums[:, 1:10].reshape(S, 3, 3), sums[:, 10:13], track.vel_n[a],
        track.lat[a], track.alt_m[a],
        filt.mech, scale_divisors(filt.errors),
        sums[:, 14:23].reshape(S, 3, 3) if sf else None,
        sums[:, 23:32].reshape(S, 3, 3) if sf else None,
        sums[:, 13],
    )  # fmt: skip
    errors = {k: v.copy() for k, v in filt.errors.items()}
    n_nodes = rec.count if rec is not None else 0
    resets, done = filt.n_resets, S
    step_aligned = []
    t_l, lat_l, lon_l, alt_l = (v.tolist() for v in (T[s : e + 1], track.lat, track.lon,
                                                        track.alt_m))  # fmt: skip
    mat, vel = track.mat_nb, track.vel_n
    for j, i in enumerate(b.tolist()):
        if j % _CHUNK == 0:  # discretise the next steps (a reset ends the segment early)
            Phi, Q = discretize(*_chunk(filt, step, j))
        step_aligned.append(filt.yaw_aligned)
        filt.predict(Phi[j % _CHUNK], Q[j % _CHUNK])
        x_pre, P_pre = filt.x, filt.P
        filt.t, filt.mat_nb, filt.vel_n = t_l[i], mat[i], vel[i]
        filt.lat, filt.lon, filt.alt_m = lat_l[i], lon_l[i], alt_l[i]
        epoch = filt.yaw_epoch
        for it in epochs.get(s + i, ()):
            filt.apply(it)
        if rec is not None:
            rec.node(
                filt, x_pre, P_pre, Phi[j % _CHUNK] if rec.full else None, epoch == filt.yaw_epoch
            )
        if filt.n_resets != resets:
            done = j + 1
            break
    if rec is not None:
        rec.close_segment()
        stop = s + int(b[done - 1])
        p = np.flatnonzero(out[s:stop]) + s
        if p.size:
            jr = np.searchsorted(b[:done], p - s, side="right")
            ta, tb = T[s + a[jr]], T[s + b[jr]]
            rows = p - s
            rec.add_rows(
                T[p],
                (track.mat_nb[rows], track.vel_n[rows], track.lat[rows], track.lon[rows],
                 track.alt_m[rows]),
                errors, n_nodes - 1 + jr, (T[p] - ta) / (tb - ta),
                np.array(step_aligned)[jr],
            )  # fmt: skip
    if filt.n_resets == resets:
        filt.mat_nb = Rotation.from_matrix(filt.mat_nb).as_matrix()  # orthonormal at segment ends
    return s + int(b[done - 1])


def _chunk(filt: Filter, step: StepNominal, j: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(F, dt, qc)`` of the steps ``j .. j + _CHUNK - 1`` of a segment."""
    part = slice(j, j + _CHUNK)
    sub = StepNominal(
        dt=step.dt[part], mat_nb=step.mat_nb[part], force_n=step.force_n[part],
        vel_n=step.vel_n[part], lat=step.lat[part], alt_m=step.alt_m[part], mech=step.mech,
        gyro_divisor=step.gyro_divisor, accel_divisor=step.accel_divisor,
        mat_omega=None if step.mat_omega is None else step.mat_omega[part],
        mat_force=None if step.mat_force is None else step.mat_force[part],
        rate_sq=None if step.rate_sq is None else step.rate_sq[part],
    )  # fmt: skip
    return filt.layout.dynamics(sub), sub.dt, filt.layout.step_noise(filt.qc, filt.model, sub)


def interpolate(
    nodes: Nodes,
    rows: Rows,
    slices: dict[str, slice],
    delta: FloatArray | None = None,
    P_smooth: FloatArray | None = None,
) -> NavState:
    """The rows' estimates: ``nominal (+) x`` with ``x`` and the covariance interpolated
    between the nodes (module docstring), the blocks' sigmas by ``slices``; with the
    smoother's corrections ``delta`` and covariances ``P_smooth`` at the nodes
    (:func:`~polins.fusion.eskf.smoother.rts_smooth`), the smoothed estimates."""
    G, n = nodes.x_pre.shape
    # per node: [x, var, attitude block] after the node (start of a step) and before it
    post = np.hstack([nodes.x_post, nodes.var_post, nodes.att_post.reshape(G, 9)])
    pre = np.hstack([nodes.x_pre, nodes.var_pre, nodes.att_pre.reshape(G, 9)])
    if delta is not None and P_smooth is not None:
        smooth = np.hstack([delta, np.diagonal(P_smooth, axis1=1, axis2=2),
                            P_smooth[:, 0:3, 0:3].reshape(G, 9)])  # fmt: skip
        post[:, :n] += delta
        post[:, n:] = smooth[:, n:]
        link = nodes.linked[:, None]
        pre[:, :n] += np.where(link, nodes.dx + delta, 0.0)
        pre[:, n:] = np.where(link, smooth[:, n:], pre[:, n:])
    change = np.zeros_like(post)  # over the step that starts at the node
    change[:-1] = pre[1:] - post[:-1]
    val = np.take(change, rows.node, axis=0)
    val *= rows.w[:, None]
    val += np.take(post, rows.node, axis=0)
    x, sig = val[:, :n], np.sqrt(np.clip(val[:, n : 2 * n], 0.0, None))
    mat, vel, lat, lon, alt = inject_nav(rows.mat_nb, rows.vel_n, rows.lat, rows.lon, rows.alt_m, x)
    return NavState(
        t=rows.t,
        rot_nb=Rotation.from_matrix(mat, assume_valid=True),
        vel_n=vel,
        lat=lat,
        lon=lon,
        alt_m=alt,
        errors={k: v + x[:, slices[k]] for k, v in rows.errors.items()},
        sigma={k: sig[:, sl] for k, sl in slices.items()},
        att_cov=val[:, 2 * n :].reshape(-1, 3, 3),
        yaw_aligned=rows.yaw_aligned,
    )


load_kernels()  # at import, not in the first run of the filter (module docstring)
