"""The loop of the paper's Eq. 13: INS attitude -> image prior -> polarization heading -> filter.

For each image the filter's attitude is the prior handed to :func:`polins.measure` (its
roll/pitch rotate the E-vectors into the level frame, its yaw only resolves the 180 deg choice
near the horizon), and the measurement's inflated sigma (SPEC 10.2) becomes ``R`` of the
filter's yaw update (the tilt coupling goes into ``H``: ``EskfOptions.tilt_coupling``), or of
a 2-DOF sun-vector update (``update="sun"``, which measures the sun zenith from the image too).

One class, :class:`NavigationStream`, runs the loop incrementally for a vehicle's navigation
code (``add_imu``, ``add_image`` / ``add_measurement``, ``state``); :func:`run_log` feeds it a
recorded log in time order with a process pool for the images and then computes the final
solution with ``polins.fuse`` (ESKF, RTS smoother or GTSAM graph).

The prior, exactly (identical in streaming and batch use)
---------------------------------------------------------
The filter (``polins.fusion.eskf.ESKF``) keeps *snapshots* of its estimate at the first IMU
sample of every ``snapshot_every_s`` grid cell. The prior of an image at ``t_i`` is the latest
snapshot taken at ``tau < t_i - prior_lag_s`` (or the first one, if none is that old),
propagated to ``t_i`` by the strapdown (:func:`polins.ins.strapdown`) with the snapshot's
bias estimates. A snapshot at ``tau`` contains the updates of all images up to ``tau``, so
images closer than ``prior_lag_s`` to each other do not depend on each other and are measured
in parallel (a sliding window of up to ``max_in_flight`` images in a process pool, while the
filter stays sequential). Each measurement updates the filter at its image time (the ESKF
interpolates the IMU to it), so the filter holds back the IMU samples after the oldest image
whose measurement is not known yet. The result depends only on the data and the options,
never on the number of workers or on timing. The cost of the lag: the prior misses the last
``prior_lag_s`` of updates, which typically moves the tilt far less than its sigma (simulated
UGV drives: median 0.001 deg with a MEMS IMU against a 0.16 deg roll sigma); the yaw of the
prior is only used near the horizon.

Policies for bad data (reported as events, never fatal)
-------------------------------------------------------
* IMU sample with NaN/inf: dropped (``imu-nonfinite``).
* IMU sample not after the previous accepted one (duplicate or out of order): dropped
  (``imu-out-of-order``).
* IMU gap longer than ``max_imu_gap_s``: reported (``imu-gap``) and propagated across with
  the rates interpolated linearly (the covariance grows with the gap).
* Image not after the previous image: skipped (``image-out-of-order``).
* Image older than the filter can still take (more than ``max_image_delay_s`` behind the IMU,
  after the filter has moved past it): skipped (``image-late``).
* Image before the first IMU sample or after the last one: skipped (``image-outside-imu``).
* Image inside the levelling window of a self-alignment: skipped (``image-during-alignment``).
* Image that cannot be read or decoded (corrupt, truncated, wrong size), or for which the
  measurement raised: skipped (``image-unreadable`` / ``image-error``), the run goes on.
* Image refused by the measurement (too few pixels, sun near the zenith, ...): kept in the
  measurement table with ``ok=False`` and its reason; no update.
* Update refused by the filter's chi-square gate: kept with ``accepted=False`` and the reason.

Memory and latency of the streaming object are bounded: the IMU buffer spans at most
``prior_lag_s + max_image_delay_s`` plus the processing time of the images in flight, at
most ``max_in_flight`` images are in flight (``add_image`` waits for the oldest beyond that,
at most one image's processing), and the tables are bounded ring buffers (drain them with
:meth:`NavigationStream.drain_measurements`). With a thread or process executor ``add_imu``
never waits for an image; the inline executor measures in whichever call makes the image's
prior known. ``state()`` costs one filter step per IMU sample since the last measurement
update (the live estimate is the filter replayed over the held-back samples).
"""

from __future__ import annotations

import copy
import math
import multiprocessing as mp
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.frames import euler_from_rot_nb, heading_deg_from_yaw, rot_nb_from_euler, wrap_angle
from polins.fusion import check_filter_options, eskf_options
from polins.fusion.eskf import ESKF, FilterState
from polins.fusion.inputs import PRIOR_COLUMNS
from polins.fusion.items import UpdateRecord
from polins.ins.strapdown import Mechanization, NavState, strapdown
from polins.io.images import ImageReadError, load_raw
from polins.io.log import Log
from polins.models.loader import CameraModel, ImuModel
from polins.site import utc_timestamp

FloatArray = NDArray[np.float64]

EVENT_KINDS = (
    "imu-nonfinite",
    "imu-out-of-order",
    "imu-gap",
    "image-out-of-order",
    "image-late",
    "image-outside-imu",
    "image-during-alignment",
    "image-unreadable",
    "image-error",
)
MEASUREMENT_COLUMNS = (
    "t", "ok", "reason", "yaw", "yaw_std", "heading_deg", "heading_std_deg", "epsilon",
    "epsilon_std", "n_pixels", "yaw_std_meas", "sun_bx", "sun_by", "sun_bz", "sun_nx",
    "sun_ny", "sun_nz", "sun_std", "eigen_gap", "residual_rms", "prior_t", "prior_roll",
    "prior_pitch", "prior_yaw", "accepted", "update_reason", "innovation", "nis", "nis_dof",
    "measure_s", "image",
)  # fmt: skip


@dataclass(frozen=True)
class LoopOptions:
    """Options of the Eq. 13 loop (SI units, radians).

    Attributes
    ----------
    method : str
        ``polins.measure`` method ("compensated", "traditional", "paper").
    measure_options : mapping
        Keyword options of ``polins.measure`` (``polins.compass.MeasureOptions`` fields).
    update : {"yaw", "sun"}
        Filter update per image: the yaw with the tilt coupling in ``H`` (default), or the
        2-DOF sun vector. Either way the sun zenith is measured from the image
        (``fixed_zenith=False`` unless ``measure_options`` says otherwise): the filter's
        yaw model is then exact in the prior's tilt (docs/measurement.md, "The yaw in a
        filter"), and the free zenith costs no precision.
    prior_lag_s : float
        Age of the filter snapshot the image priors are propagated from [s] (module doc).
    snapshot_every_s : float
        Grid of the filter snapshots [s].
    max_image_delay_s : float
        How long the filter waits for an image that is older than the newest IMU sample [s]
        (streaming: the camera's delivery latency).
    max_imu_gap_s : float
        IMU intervals longer than this are reported as gaps [s].
    max_in_flight : int or None
        Images being measured at once; default ``2 * workers + 1``.
    record_solution : bool
        Keep the filter's state at every IMU sample (drain with ``drain_solution``).
    max_table_rows : int
        Bound of the in-memory measurement, event and solution tables.
    """

    method: str = "compensated"
    measure_options: Mapping[str, Any] = field(default_factory=dict)
    update: str = "yaw"
    prior_lag_s: float = 1.0
    snapshot_every_s: float = 0.1
    max_image_delay_s: float = 0.5
    max_imu_gap_s: float = 0.1
    max_in_flight: int | None = None
    record_solution: bool = False
    max_table_rows: int = 1_000_000

    def __post_init__(self) -> None:
        if self.update not in ("yaw", "sun"):
            raise ValueError(f"update={self.update!r}: expected 'yaw' or 'sun'")
        for name in ("prior_lag_s", "max_image_delay_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}={getattr(self, name)} must be >= 0 [s]")
        for name in ("snapshot_every_s", "max_imu_gap_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}={getattr(self, name)} must be > 0 [s]")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise ValueError(f"max_in_flight={self.max_in_flight} must be >= 1")
        if self.update == "sun" and self.measure_options.get("fixed_zenith", False):
            raise ValueError(
                "update='sun' needs the sun zenith measured from the image: "
                "measure_options fixed_zenith=False"
            )

    def measure_kwargs(self) -> dict[str, Any]:
        """The ``polins.measure`` options actually used."""
        opts = dict(self.measure_options)
        opts.setdefault("fixed_zenith", False)
        return opts

    def fuse_options(self, overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """``polins.fuse`` options of the filter matching this loop (plus ``overrides``)."""
        opts: dict[str, Any] = {
            "use_sun": self.update == "sun",
            "tilt_coupling": self.update == "yaw",
        }
        opts.update(overrides or {})
        check_filter_options(opts)
        return opts


# ----------------------------------------------------------------------------- image stage
class ImageMeasurer:
    """``polins.measure`` on one image item, never raising (picklable; one per worker).

    Parameters
    ----------
    camera : CameraModel
    method : str
    options : mapping
        ``polins.measure`` keyword options.
    """

    def __init__(self, camera: CameraModel, method: str, options: Mapping[str, Any]) -> None:
        from polins.compass.measure import _options

        _options(dict(options))  # unknown options fail here, not in every image
        self.camera = camera
        self.method = method
        self.options = dict(options)

    def __call__(self, item: Any, sun_n: FloatArray, quat_prior: FloatArray) -> dict[str, Any]:
        """Measure one image; returns a measurement row (``ok=False`` with a reason on failure)."""
        from polins.compass.measure import measure

        start = time.perf_counter()
        row: dict[str, Any] = {"ok": False, "reason": "", "event": ""}
        try:
            raw = load_raw(item, shape=self.camera.shape)
        except ImageReadError as exc:
            row.update(reason=f"unreadable image: {exc}", event="image-unreadable")
        except Exception as exc:
            row.update(reason=f"unreadable image: {type(exc).__name__}: {exc}",
                       event="image-unreadable")  # fmt: skip
        else:
            try:
                m = measure(
                    raw,
                    self.camera,
                    sun_n=sun_n,
                    rot_nb_prior=Rotation.from_quat(quat_prior),
                    method=self.method,
                    **self.options,
                )
            except Exception as exc:
                row.update(reason=f"measurement failed: {type(exc).__name__}: {exc}",
                           event="image-error")  # fmt: skip
            else:
                row.update(
                    ok=bool(m.ok),
                    reason=m.reason,
                    yaw=m.yaw,
                    yaw_std=m.yaw_std,
                    yaw_std_meas=m.yaw_std_meas,
                    heading_deg=m.heading_deg,
                    heading_std_deg=math.degrees(m.yaw_std),
                    epsilon=m.epsilon,
                    epsilon_std=m.epsilon_std,
                    n_pixels=int(m.n_pixels),
                    sun_bx=m.sun_b[0],
                    sun_by=m.sun_b[1],
                    sun_bz=m.sun_b[2],
                    sun_std=m.sun_std,
                    eigen_gap=m.eigen_gap,
                    residual_rms=m.residual_rms,
                )
        row["measure_s"] = time.perf_counter() - start
        return row


_WORKER: ImageMeasurer | None = None


def _worker_init(measurer: ImageMeasurer) -> None:
    global _WORKER
    _WORKER = measurer


def _worker_call(item: Any, sun_n: FloatArray, quat_prior: FloatArray) -> dict[str, Any]:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER(item, sun_n, quat_prior)


class _InlineExecutor(Executor):
    """Runs each job at submission (no parallelism; deterministic reference)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        fut: Future[Any] = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # pragma: no cover - the measurer does not raise
            fut.set_exception(exc)
        return fut


def make_executor(
    kind: str, workers: int, measurer: ImageMeasurer
) -> tuple[Executor, Callable[..., dict[str, Any]]]:
    """An executor for the image stage and the function to submit to it.

    ``kind``: "inline" (in the caller), "thread" or "process" (``workers`` processes, each
    initialised once with the camera so its per-camera caches are built once).
    """
    if kind == "inline":
        return _InlineExecutor(), measurer
    if kind == "thread":
        return ThreadPoolExecutor(max_workers=workers), measurer
    if kind == "process":
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context(method),
            initializer=_worker_init,
            initargs=(measurer,),
        )
        return pool, _worker_call
    raise ValueError(f"executor {kind!r}: expected 'inline', 'thread' or 'process'")


# ----------------------------------------------------------------------------- helpers
SUN_GRID_S = 10.0  # [s] grid of the ephemeris inside the stream
_SUN_BLOCK = 32  # grid points computed per ephemeris call
Sample = tuple[float, FloatArray, FloatArray]  # (t [s], gyro_b [rad/s], accel_b [m/s^2])


def _clone_filter(eskf: ESKF) -> ESKF:
    """An independent copy of a filter (without its record history)."""
    records = eskf.records
    eskf.records = []
    try:
        clone = copy.deepcopy(eskf)
    finally:
        eskf.records = records
    return clone


def _sample_at(t: float, samples: list[Sample]) -> tuple[FloatArray, FloatArray]:
    """IMU sample at ``t`` inside ``samples`` (linear between the bracketing samples)."""
    ts = [s[0] for s in samples]
    k = int(np.searchsorted(ts, t, side="left"))
    for j in (k - 1, k):  # at a sample (to the filter's time tolerance)
        if 0 <= j < len(samples) and abs(samples[j][0] - t) <= 1e-6:
            return samples[j][1], samples[j][2]
    if k == 0 or k >= len(samples):
        raise ValueError(f"no IMU samples around t={t}")
    a, b = samples[k - 1], samples[k]
    frac = (t - a[0]) / (b[0] - a[0])
    return a[1] + (b[1] - a[1]) * frac, a[2] + (b[2] - a[2]) * frac


def propagate_nominal(
    state: FilterState, samples: list[Sample], t_end: float, mech: Mechanization
) -> Rotation:
    """Attitude at ``t_end`` from a filter estimate and raw IMU samples around it.

    The strapdown (:func:`polins.ins.strapdown`) runs from ``state.t`` to ``t_end`` through
    the samples in between, with linearly interpolated samples at both ends if they fall
    between samples (the IMU convention), corrected by the estimate's biases and scale
    factors as the filter does. ``samples`` must cover ``[state.t, t_end]``.
    """
    if t_end <= state.t + 1e-9:
        return state.rot_nb
    w0, f0 = _sample_at(state.t, samples)
    w1, f1 = _sample_at(t_end, samples)
    inner = [s for s in samples if state.t + 1e-9 < s[0] < t_end - 1e-9]
    t = np.array([state.t, *[s[0] for s in inner], t_end])
    w = np.array([w0, *[s[1] for s in inner], w1])
    f = np.array([f0, *[s[2] for s in inner], f1])
    w = (w - state.bg) / (1.0 + state.sg)
    f = (f - state.ba) / (1.0 + state.sa)
    nav0 = NavState(state.t, state.rot_nb, state.vel_n, state.lat, state.lon, state.height)
    track = strapdown(nav0, t, w, f, mech)
    return Rotation.from_matrix(track.mat_nb[-1])


@dataclass
class _Image:
    index: int
    t: float
    item: Any  # raw mosaic, path or bag message; None once dispatched
    sun_n: FloatArray
    future: Future[dict[str, Any]] | None = None
    prior: dict[str, float] = field(default_factory=dict)
    row: dict[str, Any] | None = None  # the measurement, once known

    @property
    def dispatched(self) -> bool:
        return self.future is not None or self.row is not None

    @property
    def resolved(self) -> bool:
        return self.row is not None or (self.future is not None and self.future.done())


@dataclass(frozen=True)
class NavigationEstimate:
    """Latest estimate of :meth:`NavigationStream.state` (radians, SI).

    ``yaw``, ``heading_deg`` and ``yaw_std`` are NaN before the yaw is aligned
    (self-alignment waits for the first measurement).
    """

    t: float
    rot_nb: Rotation
    roll: float
    pitch: float
    yaw: float
    heading_deg: float
    roll_std: float
    pitch_std: float
    yaw_std: float
    vel_n: FloatArray
    lat: float
    lon: float
    height: float
    bg: FloatArray
    ba: FloatArray
    yaw_aligned: bool
    images_pending: int


# ----------------------------------------------------------------------------- the stream
class NavigationStream:
    """Incremental Eq. 13 loop for a vehicle's navigation code (module docstring).

    Parameters
    ----------
    camera : CameraModel
        Camera of the raw images.
    imu_model : ImuModel
        IMU error model of the filter.
    lat_deg, lon_deg, alt_m : float
        Start position (geodetic) [deg, deg, m]; also the site of the ephemeris.
    epoch_utc : timezone-aware time
        UTC time of ``t = 0`` (for the sun position).
    rot_nb0 : Rotation, optional
        Initial attitude; None: self-alignment (static start for ``align_s``, yaw from the
        first measurement). Images during the levelling window are skipped.
    vel_n0 : (3,) array_like
        Initial ENU velocity [m/s].
    options : LoopOptions
    fuse_options : mapping, optional
        Filter options by their ``polins.fuse`` names (``gate_prob``, ``nhc_std``, ...).
    imu_dt : float, optional
        Nominal IMU interval [s] (default ``1 / imu_model.sample_rate_hz``); sets the
        stride of the non-holonomic constraint as ``polins.fuse`` does.
    executor : {"inline", "thread", "process"}
        Where images are measured: in the calling thread (``add_image`` then takes one
        image's processing time), or in ``workers`` threads / processes.
    workers : int
        Number of image workers.

    Examples
    --------
    >>> nav = NavigationStream(cam, imu_model, lat_deg=45.6, lon_deg=126.7, alt_m=150.0,
    ...                        epoch_utc="2023-09-05T07:06:00Z", executor="process")
    >>> nav.add_imu(t, gyro_b, accel_b)       # every IMU sample
    >>> nav.add_image(t_img, raw)             # every camera image (raw mosaic)
    >>> est = nav.state()                     # latest attitude/heading with sigmas
    """

    def __init__(
        self,
        camera: CameraModel,
        imu_model: ImuModel,
        *,
        lat_deg: float,
        lon_deg: float,
        alt_m: float = 0.0,
        epoch_utc: Any,
        rot_nb0: Rotation | None = None,
        vel_n0: ArrayLike = (0.0, 0.0, 0.0),
        options: LoopOptions | None = None,
        fuse_options: Mapping[str, Any] | None = None,
        imu_dt: float | None = None,
        executor: str = "inline",
        workers: int = 1,
    ) -> None:
        self.camera = camera
        self.imu_model = imu_model
        self.lat_deg, self.lon_deg, self.alt_m = float(lat_deg), float(lon_deg), float(alt_m)
        self.epoch_utc = utc_timestamp(epoch_utc)
        self.rot_nb0 = rot_nb0
        self.vel_n0 = np.array(vel_n0, dtype=float)
        self.options = options if options is not None else LoopOptions()
        dt = float(imu_dt) if imu_dt else 1.0 / imu_model.sample_rate_hz
        self.eskf_opts = eskf_options(imu_model, dt, **self.options.fuse_options(fuse_options))
        if workers < 1:
            raise ValueError(f"workers={workers} must be >= 1")
        self.workers = int(workers)
        self.max_in_flight = self.options.max_in_flight or (2 * self.workers + 1)
        measurer = ImageMeasurer(camera, self.options.method, self.options.measure_kwargs())
        self._executor, self._submit_fn = make_executor(executor, self.workers, measurer)
        self.filter: ESKF | None = None
        rows = self.options.max_table_rows
        self._buf: deque[Sample] = deque()  # accepted samples not yet filtered
        self._hist: deque[Sample] = deque()  # filtered samples a prior may still need
        self._snaps: deque[FilterState] = deque()
        self._images: deque[_Image] = deque()  # added, not yet handed to the filter
        self._by_t: dict[float, dict[str, Any]] = {}  # handed over, awaiting the verdict
        self._rows: deque[dict[str, Any]] = deque(maxlen=rows)
        self._events: deque[dict[str, Any]] = deque(maxlen=rows)
        self._solution: deque[dict[str, float]] = deque(maxlen=rows)
        self.counts: dict[str, int] = dict.fromkeys(EVENT_KINDS, 0)
        self.n_imu = 0  # accepted IMU samples
        self.n_images = 0  # images added (including skipped ones)
        self._t_latest = -math.inf  # newest accepted IMU time
        self._t_first = math.nan  # first accepted IMU time (the filter's start)
        self._t_last_image = -math.inf
        self._head: ESKF | None = None
        self._head_valid = False
        self._sun_blocks: dict[int, FloatArray] = {}
        self._closed = False

    # ------------------------------------------------------------------ reporting
    def _event(self, t: float, kind: str, detail: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        self._events.append({"t": float(t), "kind": kind, "detail": detail})

    def events(self) -> pd.DataFrame:
        """Reported events (``t, kind, detail``), oldest first."""
        return pd.DataFrame(list(self._events), columns=pd.Index(["t", "kind", "detail"]))

    def drain_measurements(self) -> pd.DataFrame:
        """Image rows whose filter verdict is known (``MEASUREMENT_COLUMNS``), and forget them."""
        rows = list(self._rows)
        self._rows.clear()
        return measurement_frame(rows)

    def drain_solution(self) -> pd.DataFrame:
        """Filter estimates at every filtered IMU sample since the last call
        (``record_solution=True``; ``polins.fuse`` solution columns)."""
        rows = list(self._solution)
        self._solution.clear()
        return pd.DataFrame(rows)

    # ------------------------------------------------------------------ inputs
    def add_imu(self, t: float, gyro_b: ArrayLike, accel_b: ArrayLike) -> bool:
        """One IMU sample: instantaneous body rate [rad/s] and specific force [m/s^2] at ``t``.

        Returns False if the sample was dropped (NaN, not after the previous one; module
        docstring). Never waits for the image stage.
        """
        t = float(t)
        w = np.array(gyro_b, dtype=float).reshape(3)
        f = np.array(accel_b, dtype=float).reshape(3)
        if not (math.isfinite(t) and np.all(np.isfinite(w)) and np.all(np.isfinite(f))):
            self._event(t, "imu-nonfinite", "IMU sample with NaN/inf dropped")
            return False
        if t <= self._t_latest:
            what = "duplicated" if t == self._t_latest else "out-of-order"
            self._event(t, "imu-out-of-order",
                        f"{what} IMU sample dropped (previous t={self._t_latest!r})")  # fmt: skip
            return False
        if self.n_imu and t - self._t_latest > self.options.max_imu_gap_s:
            self._event(t, "imu-gap",
                        f"{t - self._t_latest:.4g} s without IMU data after "
                        f"t={self._t_latest:.6f}; propagated across")  # fmt: skip
        if self.filter is None:
            self._t_first = t
            self.filter = ESKF(
                self.imu_model,
                t,
                math.radians(self.lat_deg),
                math.radians(self.lon_deg),
                self.alt_m,
                rot_nb0=self.rot_nb0,
                vel_n0=self.vel_n0,
                options=self.eskf_opts,
            )
            if self.filter.ready:  # attitude given: the initial state is the first snapshot
                self._snaps.append(self.filter.state())
        self._t_latest = t
        self.n_imu += 1
        sample = (t, w, f)
        self._buf.append(sample)
        if self._head is not None and self._head_valid:
            self._head.propagate(*sample)
            self._head.records.clear()  # bounded memory: the head's log is not used
        self._advance(block=False)
        return True

    def add_image(self, t: float, raw: Any, *, sun_n: ArrayLike | None = None) -> bool:
        """One camera image taken at ``t``: a raw mosaic (or a path / bag message).

        ``sun_n`` (ENU sun vector) defaults to the ephemeris at ``t``. Returns False when
        the image was skipped (module docstring). Waits only while ``max_in_flight`` images
        are being measured (at most one image's processing).
        """
        t = float(t)
        index = self.n_images
        self.n_images += 1
        if not self._usable_time(index, t, "image"):
            return False
        s_n = self.sun_at(t) if sun_n is None else np.asarray(sun_n, dtype=float).reshape(3)
        self._images.append(_Image(index, t, raw, s_n))
        self._advance(block=False)
        while self._busy() > self.max_in_flight:
            self._wait_oldest()
            self._advance(block=False)
        return True

    def add_measurement(self, t: float, **columns: Any) -> bool:
        """An external measurement row at ``t`` (``polins.fuse`` measurement columns:
        ``yaw, yaw_std`` [rad] and/or ``sun_bx .. sun_bz, sun_std`` with ``sun_n``); it
        takes the place of an image (same ordering policy)."""
        t = float(t)
        index = self.n_images
        self.n_images += 1
        if not self._usable_time(index, t, "measurement"):
            return False
        row: dict[str, Any] = {"ok": True, "reason": "", "event": "", **columns}
        if "yaw" in row and "heading_deg" not in row:
            row["heading_deg"] = float(heading_deg_from_yaw(row["yaw"]))
        s_n = np.array([row.get(f"sun_n{c}", np.nan) for c in "xyz"], dtype=float)
        self._images.append(_Image(index, t, None, s_n, row=row))
        self._advance(block=False)
        return True

    def _usable_time(self, index: int, t: float, what: str) -> bool:
        f = self.filter
        if not math.isfinite(t) or t <= self._t_last_image:
            self._skip(index, t, "image-out-of-order",
                       f"{what} time not after the previous one (t={self._t_last_image!r})")  # fmt: skip
            return False
        if f is None or t < self._t_first - self.eskf_opts.time_tol:
            self._skip(index, t, "image-outside-imu", f"{what} before the first IMU sample")
            return False
        if (
            self.rot_nb0 is None
            and t <= self._t_first + self.eskf_opts.align_s + self.eskf_opts.time_tol
        ):
            self._skip(index, t, "image-during-alignment",
                       f"{what} inside the levelling window ({self.eskf_opts.align_s} s)")  # fmt: skip
            return False
        if f.ready and t < f.t - self.eskf_opts.time_tol:
            self._skip(index, t, "image-late",
                       f"{what} arrived after the filter passed t={f.t:.6f} "
                       f"(max_image_delay_s={self.options.max_image_delay_s})")  # fmt: skip
            return False
        self._t_last_image = t
        return True

    def sun_at(self, t: float) -> FloatArray:
        """ENU sun vector at log time ``t`` [s]: the NREL SPA (``polins.sun_position``) on a
        grid of ``SUN_GRID_S`` seconds, interpolated linearly and normalised.

        The interpolation error is below 1e-6 deg (the sun moves < 0.005 deg/s along a
        smooth path); the grid is computed in fixed blocks, so the value depends on ``t``
        only, never on the order of the calls.
        """
        x = float(t) / SUN_GRID_S
        k = math.floor(x)
        a, b = self._sun_grid(k), self._sun_grid(k + 1)
        v = a + (b - a) * (x - k)
        return np.asarray(v / np.linalg.norm(v), dtype=float)

    def _sun_grid(self, k: int) -> FloatArray:
        from polins.sky.ephemeris import sun_position, sun_vector_n

        block, i = divmod(k, _SUN_BLOCK)
        if block not in self._sun_blocks:
            times = pd.DatetimeIndex(
                self.epoch_utc
                + pd.to_timedelta(SUN_GRID_S * (block * _SUN_BLOCK + np.arange(_SUN_BLOCK)), "s")
            )
            sun = sun_position(times, self.lat_deg, self.lon_deg, self.alt_m)
            self._sun_blocks[block] = sun_vector_n(sun.azimuth, sun.zenith)
            for old in [b for b in self._sun_blocks if abs(b - block) > 2]:
                del self._sun_blocks[old]
        return np.asarray(self._sun_blocks[block][i])

    # ------------------------------------------------------------------ outputs
    def state(self) -> NavigationEstimate:
        """Latest estimate: all accepted IMU samples, all measurements known so far."""
        if self.filter is None:
            raise RuntimeError("no estimate yet: feed IMU samples first")
        if self._head is None or not self._head_valid:
            self._head = _clone_filter(self.filter)
            for s in self._buf:
                self._head.propagate(*s)
            self._head.records.clear()
            self._head_valid = True
        if not self._head.ready:
            raise RuntimeError(
                f"no estimate yet: self-alignment levels for {self.eskf_opts.align_s} s"
            )
        st = self._head.state()
        yaw, pitch, roll = euler_from_rot_nb(st.rot_nb)
        ypr_std = st.euler_std()
        aligned = bool(st.yaw_aligned)
        return NavigationEstimate(
            t=st.t,
            rot_nb=st.rot_nb,
            roll=float(roll),
            pitch=float(pitch),
            yaw=float(yaw) if aligned else math.nan,
            heading_deg=float(heading_deg_from_yaw(yaw)) if aligned else math.nan,
            roll_std=float(ypr_std[2]),
            pitch_std=float(ypr_std[1]),
            yaw_std=float(ypr_std[0]) if aligned else math.nan,
            vel_n=st.vel_n,
            lat=st.lat,
            lon=st.lon,
            height=st.height,
            bg=st.bg,
            ba=st.ba,
            yaw_aligned=aligned,
            images_pending=len(self._images),
        )

    def flush(self) -> None:
        """Measure and apply every image added so far; filter every accepted IMU sample."""
        self._advance(block=True, final=True)
        for img in list(self._images):  # after the last IMU sample
            self._skip(img.index, img.t, "image-outside-imu", "image after the last IMU sample")
        self._images.clear()
        for row in self._by_t.values():  # handed over, never applied
            row.update(accepted=False, update_reason="after the last IMU sample")
            self._rows.append(row)
        self._by_t.clear()

    def close(self) -> None:
        """Flush, then stop the workers."""
        if not self._closed:
            try:
                self.flush()
            finally:
                self._executor.shutdown(wait=True, cancel_futures=True)
                self._closed = True

    def __enter__(self) -> NavigationStream:
        return self

    def __exit__(self, *exc: object) -> None:
        if exc[0] is None:
            self.close()
        else:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._closed = True

    # ------------------------------------------------------------------ internals
    def _skip(self, index: int, t: float, kind: str, detail: str) -> None:
        self._event(t, kind, detail)
        self._rows.append({"t": t, "image": index, "ok": False, "reason": f"{kind}: {detail}",
                           "accepted": False, "update_reason": "skipped"})  # fmt: skip

    def _busy(self) -> int:
        return sum(1 for img in self._images if img.future is not None and not img.resolved)

    def _wait_oldest(self) -> None:
        for img in self._images:
            if img.future is not None and not img.resolved:
                img.future.result()
                return

    def _snapshot_limit(self, img: _Image) -> float:
        return img.t - self.options.prior_lag_s - self.eskf_opts.time_tol

    def _prior_ready(self, img: _Image) -> bool:
        """The snapshot of ``img`` is final and the IMU reaches the image."""
        f = self.filter
        assert f is not None
        if not f.ready or not self._snaps or self._t_latest < img.t - self.eskf_opts.time_tol:
            return False
        # no later snapshot can be older than the limit once the next sample is past it
        return not self._buf or self._buf[0][0] >= self._snapshot_limit(img)

    def _dispatch(self, img: _Image) -> None:
        limit = self._snapshot_limit(img)
        snap = self._snaps[0]
        for s in self._snaps:
            if s.t < limit:
                snap = s
            else:
                break
        samples = [s for s in self._hist] + [s for s in self._buf if s[0] <= img.t + 1.0]
        rot_prior = propagate_nominal(snap, samples, img.t, self.eskf_opts.mech)
        yaw, pitch, roll = euler_from_rot_nb(rot_prior)
        img.prior = {"prior_t": snap.t, "prior_roll": float(roll),
                     "prior_pitch": float(pitch), "prior_yaw": float(yaw)}  # fmt: skip
        img.future = self._executor.submit(self._submit_fn, img.item, img.sun_n,
                                           rot_prior.as_quat())  # fmt: skip
        img.item = None  # the raw image is the worker's now

    def _hand_over(self, img: _Image) -> None:
        """Give an image's measurement to the filter (before it passes the image time)."""
        f = self.filter
        assert f is not None
        if img.row is None:
            assert img.future is not None
            img.row = dict(img.future.result())
        row = img.row
        row.update(img.prior)
        row.update(t=img.t, image=img.index)
        for c, v in zip("xyz", img.sun_n, strict=True):
            row[f"sun_n{c}"] = float(v)
        if row.get("event"):
            self._event(img.t, row["event"], row["reason"])
        if not row.get("ok"):
            row.update(accepted=False, update_reason="not measured")
            self._rows.append(row)
            return
        cols: dict[str, Any] = {}
        if "yaw" in row:
            cols.update(yaw=row["yaw"], yaw_std=row["yaw_std"])
            if f.ready and f.yaw_aligned:
                row["innovation"] = float(wrap_angle(row["yaw"] - self._predicted_yaw(img.t)))
        if "sun_bx" in row:
            cols.update(sun_b=[row["sun_bx"], row["sun_by"], row["sun_bz"]],
                        sun_std=row["sun_std"])  # fmt: skip
        if all(np.isfinite(row.get(c, np.nan)) for c in PRIOR_COLUMNS):
            cols["rot_nb_prior"] = rot_nb_from_euler(
                row["prior_yaw"], row["prior_pitch"], row["prior_roll"]
            )
        self._by_t[img.t] = row
        self._collect(f.add_measurement(img.t, sun_n=img.sun_n, **cols))
        f.records.clear()  # bounded memory: verdicts are kept in the measurement rows

    def _predicted_yaw(self, t: float) -> float:
        f = self.filter
        assert f is not None
        st = f.state()
        samples = [s for s in self._hist if s[0] >= st.t - 1e-9] + list(self._buf)
        if not samples or samples[-1][0] < t:
            return float(euler_from_rot_nb(st.rot_nb)[0])
        return float(euler_from_rot_nb(propagate_nominal(st, samples, t, self.eskf_opts.mech))[0])

    def _collect(self, records: Iterable[UpdateRecord]) -> None:
        for rec in records:
            self._head_valid = False
            row = self._by_t.pop(rec.t, None) if rec.name in ("yaw", "sun") else None
            if row is None:
                continue
            row.update(accepted=bool(rec.accepted), update_reason=rec.reason,
                       nis=rec.nis, nis_dof=rec.dim)  # fmt: skip
            self._rows.append(row)

    def _filter_next(self) -> None:
        f = self.filter
        assert f is not None
        s = self._buf.popleft()
        n_resets = f.n_resets
        recs = f.propagate(*s)
        f.records.clear()  # bounded memory: verdicts are kept in the measurement rows
        self._hist.append(s)
        if recs or f.n_resets != n_resets:
            self._head_valid = False
            self._collect(recs)
        if f.ready:
            step = self.options.snapshot_every_s
            if not self._snaps or math.floor(f.t / step) > math.floor(self._snaps[-1].t / step):
                self._snaps.append(f.state())
            if self.options.record_solution:
                self._solution.append(f.state().row())
        self._trim()

    def _trim(self) -> None:
        """Forget snapshots and IMU history that no future prior can need."""
        f = self.filter
        assert f is not None
        waiting = [img.t for img in self._images if not img.dispatched]
        t_ref = min(waiting) if waiting else max(self._t_last_image, f.t)
        limit = t_ref - self.options.prior_lag_s - self.eskf_opts.time_tol
        while len(self._snaps) > 1 and self._snaps[1].t < limit:
            self._snaps.popleft()
        keep_from = min(self._snaps[0].t if self._snaps else math.inf, f.t)
        while len(self._hist) > 1 and self._hist[1][0] <= keep_from:
            self._hist.popleft()

    def _advance(self, *, block: bool, final: bool = False) -> None:
        """Dispatch images whose prior is known, hand results over, filter IMU samples."""
        f = self.filter
        if f is None:
            return
        tol = self.eskf_opts.time_tol
        delay = self.options.max_image_delay_s
        while True:
            progressed = False
            for img in self._images:  # in time order: priors become known in order
                if img.dispatched:
                    continue
                if not self._prior_ready(img):
                    break
                self._dispatch(img)
                progressed = True
            while self._buf:
                t_next = self._buf[0][0]
                if self._images and self._images[0].t <= t_next + tol:
                    img = self._images[0]
                    if not img.dispatched and not f.ready:  # no prior can ever come
                        self._images.popleft()
                        self._skip(img.index, img.t, "image-during-alignment",
                                   "no attitude yet (self-alignment still levelling)")  # fmt: skip
                        progressed = True
                        continue
                    if not img.dispatched or not (img.resolved or block):
                        break
                    self._images.popleft()
                    self._hand_over(img)
                    progressed = True
                    continue
                if not final and t_next > self._t_latest - delay and t_next > self._t_last_image:
                    break  # an image up to max_image_delay_s late may still come
                self._filter_next()
                progressed = True
            if not progressed:
                if block and any(img.future is not None and not img.resolved
                                 for img in self._images):  # fmt: skip
                    self._wait_oldest()
                    continue
                return


def measurement_frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """Image rows as a table with ``MEASUREMENT_COLUMNS`` (sorted by time)."""
    df = pd.DataFrame(rows)
    for col in MEASUREMENT_COLUMNS:
        if col not in df.columns:
            df[col] = np.nan
    df = df.loc[:, list(MEASUREMENT_COLUMNS)]
    if len(df):
        df = df.sort_values("t", kind="stable").reset_index(drop=True)
    df["ok"] = df["ok"].fillna(False).astype(bool)
    df["accepted"] = df["accepted"].fillna(False).astype(bool)
    df["reason"] = df["reason"].fillna("").astype(str)
    df["update_reason"] = df["update_reason"].fillna("").astype(str)
    return df


# ----------------------------------------------------------------------------- batch
@dataclass(frozen=True, eq=False)
class RunResult:
    """What :func:`run_log` produced.

    Attributes
    ----------
    solution : DataFrame
        ``polins.fuse`` solution at every accepted IMU sample.
    measurements : DataFrame
        One row per image (``MEASUREMENT_COLUMNS``).
    events : DataFrame
        ``t, kind, detail`` of skipped data and gaps.
    imu : DataFrame
        The IMU samples used (after the sample policy).
    timing : dict
        ``run_s, loop_s, fuse_s, images, imu_samples, workers, measure_s_mean`` [s, counts].
    settings : dict
        Options of the run (for the summary).
    """

    solution: pd.DataFrame
    measurements: pd.DataFrame
    events: pd.DataFrame
    imu: pd.DataFrame
    timing: dict[str, float]
    settings: dict[str, Any]


def fuse_measurements(
    imu: pd.DataFrame,
    measurements: pd.DataFrame,
    *,
    imu_model: ImuModel,
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    options: LoopOptions,
    rot_nb0: Rotation | None = None,
    backend: str = "eskf",
    smooth: bool = False,
    fuse_options: Mapping[str, Any] | None = None,
) -> pd.DataFrame:
    """Final solution from the loop's measurement table with ``polins.fuse``.

    Uses the rows with ``ok`` and the loop's filter options; IMU gaps were reported by
    the loop and are bridged here (``max_gap_s`` above the longest one).
    """
    from polins.fusion import fuse

    ok = measurements["ok"].to_numpy(dtype=bool)
    cols = ["t", "yaw", "yaw_std", "sun_bx", "sun_by", "sun_bz", "sun_nx", "sun_ny", "sun_nz",
            "sun_std", "prior_roll", "prior_pitch", "prior_yaw"]  # fmt: skip
    table = measurements.loc[ok, cols].reset_index(drop=True).astype(float)
    t = imu["t"].to_numpy(dtype=float)
    longest = float(np.max(np.diff(t))) if len(t) > 1 else 0.0
    opts = options.fuse_options(fuse_options)
    if backend == "graph":  # the graph takes its own options
        shared = ("earth_rate", "att_std0", "vel_std0", "nhc_std", "align_s", "use_sun",
                  "tilt_coupling")  # fmt: skip
        opts = {k: v for k, v in opts.items() if k in shared}
    else:
        opts.update(smooth=smooth, max_gap_s=max(longest * 1.001, 1e-3))
    return fuse(
        imu,
        table,
        backend=backend,
        rot_nb0=rot_nb0,
        imu_model=imu_model,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=alt_m,
        **opts,
    )


def run_log(
    log: Log,
    *,
    options: LoopOptions | None = None,
    backend: str = "eskf",
    smooth: bool = False,
    workers: int | None = None,
    rot_nb0: Rotation | None = None,
    fuse_options: Mapping[str, Any] | None = None,
    progress: bool = True,
) -> RunResult:
    """Measurement and fusion of a recorded log: the Eq. 13 loop, then ``polins.fuse``.

    The samples and images are fed to a :class:`NavigationStream` in time order (images
    measured by a pool of ``workers`` processes), which produces the measurement table
    with the filter's verdicts; the final solution is ``polins.fuse`` on the accepted IMU
    samples and the measured images (the same filter: for ``backend="eskf"`` without
    smoothing it equals the stream's estimates to rounding).

    Parameters
    ----------
    log : Log
        From ``polins.io.read_log``.
    options : LoopOptions
    backend : {"eskf", "graph"}
        Backend of the final solution (the loop itself runs the ESKF).
    smooth : bool
        Rauch-Tung-Striebel smoother for the final ESKF solution.
    workers : int, optional
        Image processes; default all cores; 1 measures in this process.
    rot_nb0 : Rotation, optional
        Initial attitude; default self-alignment.
    fuse_options : mapping, optional
        Filter options by their ``polins.fuse`` names.
    progress : bool
        tqdm progress bar over the images.
    """
    from tqdm import tqdm

    opts = options if options is not None else LoopOptions()
    n_workers = int(workers) if workers else (os.cpu_count() or 1)
    start = time.perf_counter()
    imu = log.imu
    t_imu = imu["t"].to_numpy(dtype=float)
    gyro = imu[["gx", "gy", "gz"]].to_numpy(dtype=float)
    accel = imu[["ax", "ay", "az"]].to_numpy(dtype=float)
    t_img = np.asarray(log.images.t, dtype=float)
    dt_imu = np.diff(t_imu[np.isfinite(t_imu)])
    dt_med = float(np.median(dt_imu[dt_imu > 0])) if np.any(dt_imu > 0) else None
    used = np.zeros(len(t_imu), dtype=bool)
    stream = NavigationStream(
        log.camera,
        log.imu_model,
        lat_deg=log.lat_deg,
        lon_deg=log.lon_deg,
        alt_m=log.alt_m,
        epoch_utc=log.epoch_utc,
        rot_nb0=rot_nb0,
        options=opts,
        fuse_options=fuse_options,
        imu_dt=dt_med,
        executor="process" if n_workers > 1 else "inline",
        workers=n_workers,
    )
    k = 0

    def feed(stop: int) -> None:
        nonlocal k
        for j in range(k, stop):
            used[j] = stream.add_imu(t_imu[j], gyro[j], accel[j])
        k = max(k, stop)

    with stream:
        bar = tqdm(total=len(t_img), desc="images", unit="img", disable=not progress)
        for t, item in log.images:
            stop = k
            while stop < len(t_imu) and not t_imu[stop] > t:  # samples up to the image
                stop += 1  # (a NaN time is fed and reported by the stream)
            feed(min(stop + 1, len(t_imu)))  # ... and the one after it
            stream.add_image(t, item)
            bar.update(1)
        feed(len(t_imu))
        stream.flush()
        bar.close()
    loop_s = time.perf_counter() - start
    measurements = stream.drain_measurements()
    events = stream.events()
    imu_used = imu.loc[used].reset_index(drop=True)
    t_fuse = time.perf_counter()
    solution = fuse_measurements(
        imu_used,
        measurements,
        imu_model=log.imu_model,
        lat_deg=log.lat_deg,
        lon_deg=log.lon_deg,
        alt_m=log.alt_m,
        options=opts,
        rot_nb0=rot_nb0,
        backend=backend,
        smooth=smooth,
        fuse_options=fuse_options,
    )
    end = time.perf_counter()
    measure_s = measurements["measure_s"].to_numpy(dtype=float)
    settings = {
        "manifest": str(log.manifest_path),
        "backend": backend,
        "smooth": smooth,
        "workers": n_workers,
        "method": opts.method,
        "update": opts.update,
        "prior_lag_s": opts.prior_lag_s,
        "measure_options": opts.measure_kwargs(),
        "fuse_options": dict(fuse_options or {}),
        "camera": log.camera.name,
        "camera_shape": list(log.camera.shape),
        "imu_model": log.imu_model.name,
        "rot_nb0_given": rot_nb0 is not None,
    }
    timing = {
        "run_s": end - start,
        "loop_s": loop_s,
        "fuse_s": end - t_fuse,
        "images": float(len(t_img)),
        "imu_samples": float(len(t_imu)),
        "workers": float(n_workers),
        "measure_s_mean": float(np.nanmean(measure_s))
        if np.isfinite(measure_s).any()
        else math.nan,
    }
    return RunResult(solution, measurements, events, imu_used, timing, settings)


__all__ = [
    "EVENT_KINDS",
    "MEASUREMENT_COLUMNS",
    "ImageMeasurer",
    "LoopOptions",
    "NavigationEstimate",
    "NavigationStream",
    "RunResult",
    "fuse_measurements",
    "make_executor",
    "measurement_frame",
    "propagate_nominal",
    "run_log",
]
