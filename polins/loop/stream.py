"""The navigation loop, streaming: IMU samples and images in, the filter's live estimate out.

The loop of the paper's Eq. 13 (docs/model.md): INS attitude -> image prior -> polarization
heading -> filter. For each image the filter's attitude is the prior handed to
:func:`polins.measure` (its roll/pitch rotate the E-vectors into the level frame, its yaw
only resolves the 180 deg choice near the horizon), and the measurement's inflated sigma
(docs/model.md §10.2) becomes ``R`` of the filter's yaw update (the tilt coupling goes into
``H``: ``FuseConfig.tilt_coupling``), or of a 2-DOF sun-vector update (``update="sun"``).

:class:`NavigationStream` runs the loop incrementally for a vehicle's navigation code
(``add_imu``, ``add_image`` / ``add_measurement``, ``state``); :func:`polins.loop.run_log`
feeds it a recorded log.

The prior, exactly (identical in streaming and batch use)
---------------------------------------------------------
The filter keeps *snapshots* of its estimate at the first IMU sample of every
``snapshot_every_s`` grid cell. The prior of an image at ``t_i`` is the latest snapshot
taken at ``tau < t_i - prior_lag_s`` (or the first one, if none is that old), propagated to
``t_i`` by the strapdown with the snapshot's sensor-error estimates
(:func:`polins.loop.prior.propagate_nominal`). A snapshot at ``tau`` contains the updates of
all images up to ``tau``, so images closer than ``prior_lag_s`` to each other do not depend
on each other and are measured in parallel (a sliding window of up to ``max_in_flight``
images in a process pool, while the filter stays sequential); the prior is propagated where
the image is measured (:class:`polins.loop.prior.PriorJob`). Each measurement updates the
filter at its image time, so the filter holds back the IMU samples after the oldest image
whose measurement is not known yet, and those of the last ``max_image_delay_s`` (an image
may still come). ``add_imu`` collects the samples and, once every ``BLOCK_S`` of IMU time,
screens the block, hands the measured images over (queued in the filter, applied at their
times) and runs the samples the filter can take, in runs of at least ``RUN_S`` unless an
image waits for its prior, through its fast path
(:mod:`polins.fusion.eskf.propagate`), which gives the same estimates as
``polins.fusion.run_fusion`` on the stream's measurement table (to 1e-8 rad). The filter's
covariance steps end where its runs end, so how the samples split into runs (the blocks,
the images measured by then) moves the estimates and the image priors by ~1e-10 rad and
the sigmas by ~1e-5 relative; nothing else depends on timing or on the number of workers.
The cost of the lag: the prior misses the last ``prior_lag_s`` of updates, which typically
moves the tilt far less than its sigma (simulated UGV drives: median 0.001 deg with a MEMS
IMU against a 0.16 deg roll sigma).

Data faults are skipped and reported as events, the run goes on: the fault policy of every
path (:mod:`polins.fusion.faults`, docs/faults.md). An IMU gap longer than ``max_gap_s``
queues its ``"gap"`` item in the filter (the covariance grows as in ``polins.fuse``) and the
images inside it are skipped (``measurement-in-gap``). The units are checked over the
levelling window, and the gyro against the headings once five turning windows of headings
have arrived (docs/streaming.md): a mistake raises ``ImuUnitsError`` from the call that
fed the deciding sample or heading.

Memory and latency are bounded: the IMU buffer spans at most ``prior_lag_s +
max_image_delay_s + RUN_S + BLOCK_S`` and the processing time of the images in flight, at
most ``max_in_flight`` images are in flight (``add_image`` waits for the oldest beyond
that, at most one image's processing), and the measurement, event and solution buffers
hold at most ``max_table_rows`` entries (drain them; the events count what they dropped).
With a thread or process executor ``add_imu`` never waits for an image and ``add_image``
never runs the filter; the inline executor measures in whichever call makes the image's
prior known. ``state()`` costs one filter copy and a fast-path run over the held-back
samples after a measurement update, else a run over the samples since the last call (the
live estimate is the filter replayed over the held-back samples). The filter's compiled
strapdown is loaded when this module is imported
(:func:`polins.fusion.eskf.propagate.load_kernels`).
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import math
from collections import deque
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError
from polins.frames import heading_deg_from_yaw
from polins.fusion.config import (
    TIME_TOL_S,
    FuseConfig,
    config_from_manifest,
    config_with_site,
    site_from_shorthand,
)
from polins.fusion.eskf.filter import ESKF
from polins.fusion.faults import (
    EventKind,
    GyroHeadingCheck,
    ImuScreen,
    ImuUnitsError,
    UnitsWindow,
    default_max_gap_s,
    gap_item,
    gap_reason,
)
from polins.fusion.inputs import PRIOR_COLUMNS, heading_proxy
from polins.fusion.items import UpdateRecord, items_from_table, records_table
from polins.fusion.parts import AUTO, ODOMETER_STD
from polins.fusion.vehicle import odometer_items
from polins.ins.state import NavState
from polins.io.log import model_ref
from polins.io.manifest import MANIFEST_NAME, parse_manifest
from polins.loop.measurer import (
    EXECUTORS,
    ImageMeasurer,
    PendingImage,
    make_executor,
    report_noise_model,
)
from polins.loop.options import LoopOptions
from polins.loop.prior import PriorJob, Sample, SunGrid
from polins.loop.runner import FilterRunner
from polins.loop.state import StreamState
from polins.loop.tables import EventBuffer, measurement_frame
from polins.models import CameraModel, ImuModel, load_camera, load_imu
from polins.site import Site, utc_timestamp

# the further columns of a measured row the filter uses: the sun fit's 2x2 covariance and
# the sigma's parts a heading-bias state carries (docs/filter.md §5.7)
SKY_COLUMNS = ("sun_elevation_b", "sun_elevation_b_std", "yaw_std_model", "yaw_std_noise",
               "yaw_std_correlated")  # fmt: skip

FloatArray = NDArray[np.float64]
# IMU time [s] add_imu collects before it screens the samples and advances the loop: the
# per-call overhead of screening, dispatching and running the filter spread over this block
BLOCK_S = 0.25
# shortest run of samples [s] the filter takes while no image waits for its prior
RUN_S = 1.0


def with_odometer(config: FuseConfig) -> FuseConfig:
    """``config`` for a run with a wheel odometer: an ``"auto"`` ``odometer_std`` becomes
    its value, as :meth:`FuseConfig.resolve` makes it (without resolving the other
    ``"auto"`` choices, which the loop makes itself)."""
    if config.aiding.odometer_std == AUTO:
        return config.replace(odometer_std=ODOMETER_STD)
    return config


def _columns(row: dict[str, Any]) -> tuple[str, ...]:
    """The column names of a measurement row, in order."""
    return tuple(row)


class NavigationStream:
    """Incremental Eq. 13 loop for a vehicle's navigation code (module docstring).

    Parameters
    ----------
    camera : CameraModel
        Camera of the raw images.
    imu_model : ImuModel
        IMU error model of the filter (replaces ``config.imu_model``).
    site : Site, optional
        Start position of the filter and site of the ephemeris (replaces ``config.site``
        when given). None and no ``config.site``: :data:`polins.site.PAPER_SITE` with a
        ``UserWarning``.
    lat_deg, lon_deg, alt_m : float, optional
        Shorthand for ``site=Site(lat_deg, lon_deg, alt_m)`` [deg, deg, m]; not together
        with ``site``.
    epoch_utc : timezone-aware time
        UTC time of ``t = 0`` (for the sun position).
    rot_nb0 : Rotation, optional
        Initial attitude; None: self-alignment (static start for ``align_s``, yaw from
        the first measurement). Images during the levelling window are skipped.
    options : LoopOptions
        Options of the loop (image stage, lags, buffers).
    config : FuseConfig, optional
        The filter's configuration (``vel_n0``, ``gate_prob``, ``nhc_std``, ...); its
        ``use_sun``/``tilt_coupling`` follow ``options.update``
        (:meth:`LoopOptions.filter_config`).
    imu_dt : float, optional
        Nominal IMU interval [s] (default ``1 / imu_model.sample_rate_hz``); sets the
        filter's covariance and non-holonomic cadence as ``polins.fuse`` does.
    executor : {"inline", "thread", "process"}
        Where images are measured: in the calling thread (``add_image`` then takes one
        image's processing time), or in ``workers`` threads / processes.
    workers : int
        Number of image workers.

    Examples
    --------
    >>> nav = NavigationStream(cam, imu_model, site=Site(45.6, 126.7, 150.0),
    ...                        epoch_utc="2023-09-05T07:06:00Z", executor="process")
    >>> nav.add_imu(t, gyro_b, accel_b)       # every IMU sample
    >>> nav.add_image(t_img, raw)             # every camera image (raw mosaic)
    >>> est = nav.state()                     # est.nav: latest NavState with sigmas
    """

    def __init__(
        self,
        camera: CameraModel,
        imu_model: ImuModel,
        *,
        site: Site | None = None,
        lat_deg: float | None = None,
        lon_deg: float | None = None,
        alt_m: float | None = None,
        epoch_utc: Any,
        rot_nb0: Rotation | None = None,
        options: LoopOptions | None = None,
        config: FuseConfig | None = None,
        imu_dt: float | None = None,
        executor: str = "inline",
        workers: int = 1,
    ) -> None:
        site = site_from_shorthand(site, {"lat_deg": lat_deg, "lon_deg": lon_deg, "alt_m": alt_m})
        if executor not in EXECUTORS:
            raise UserInputError(f"executor={executor!r}: expected one of {EXECUTORS}")
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise UserInputError(f"workers={workers!r} must be an integer >= 1")
        if imu_dt is not None and not imu_dt > 0:
            raise UserInputError(f"imu_dt={imu_dt} must be > 0 [s]")
        self.options = options if options is not None else LoopOptions()
        base = config if config is not None else FuseConfig()
        base = dataclasses.replace(base, imu_model=imu_model, site=site or base.site)
        self.config = self.options.filter_config(config_with_site(base, stacklevel=3))
        assert self.config.site is not None
        self.camera = camera
        self.imu_model = imu_model
        self.site = self.config.site
        self.epoch_utc = utc_timestamp(epoch_utc)
        self.rot_nb0 = rot_nb0
        self.imu_dt = float(imu_dt) if imu_dt else 1.0 / imu_model.sample_rate_hz
        self._tol = TIME_TOL_S
        self.workers = workers
        self.max_in_flight = self.options.max_in_flight or (2 * workers + 1)
        measurer = ImageMeasurer(camera, self.options.method, self.options.measure_kwargs())
        self._executor, self._submit_fn = make_executor(executor, workers, measurer)
        self.sun_at = SunGrid(self.config.site, self.epoch_utc)
        self.sun_at(0.0)  # the ephemeris of the first minutes here, not at the first image
        self._runner: FilterRunner | None = None
        self._buf: deque[Sample] = deque()  # accepted samples not yet filtered
        self._hist: deque[Sample] = deque()  # filtered samples a prior may still need
        self._images: deque[PendingImage] = deque()  # added, not yet handed to the filter
        self._by_t: dict[float, dict[str, Any]] = {}  # handed over, awaiting the verdict
        self._rows: deque[dict[str, Any]] = deque(maxlen=self.options.max_table_rows)
        self._updates: deque[UpdateRecord] = deque(maxlen=self.options.max_table_rows)
        self._events = EventBuffer(self.options.max_table_rows)
        # the fault policy of every path (polins.fusion.faults, docs/faults.md)
        full_scale = imu_model.full_scale()
        self._screen = ImuScreen(full_scale, default_max_gap_s(self.config.gap_s, self.imu_dt))
        self._gyro_max_sq, self._accel_max_sq = full_scale[0] ** 2, full_scale[1] ** 2
        self._pending: list[tuple[float, ...]] = []  # added samples not yet screened
        self._t_newest = -math.inf  # time of the newest sample that passed add_imu's screen
        self._t_advanced = -math.inf  # newest sample time when the loop last advanced
        self._units = UnitsWindow(self.config.initial.align_s, full_scale[0])
        self._heading_check = GyroHeadingCheck()
        self._last: Sample | None = None  # the newest accepted sample
        self.n_images = 0  # images added (including skipped ones)
        self._t_last_image = -math.inf
        self._head: ESKF | None = None
        self._head_valid = False
        self._closed = False

    @classmethod
    def from_manifest(
        cls,
        manifest_path: str | Path,
        *,
        rot_nb0: Rotation | None = None,
        options: LoopOptions | None = None,
        executor: str = "inline",
        workers: int = 1,
    ) -> NavigationStream:
        """The stream of the vehicle a log's manifest describes, configured as ``polins
        fuse`` configures that log (docs/streaming.md).

        From the manifest (a folder means its ``manifest.toml``): the camera and IMU model
        files, the site and ``epoch_utc`` of ``[log]``, and the filter configuration of
        ``[vehicle]`` and ``[filter]`` (:meth:`polins.FuseConfig.from_log`'s
        :func:`~polins.fusion.config.config_from_manifest`; a ``[vehicle] odometer`` gives
        the odometer scale-factor state, fed by :meth:`add_odometry`). The log's data
        files are not read; the stream takes SI units whatever ``[units]`` says of them.
        The other parameters are the constructor's.
        """
        path = Path(manifest_path)
        path = path / MANIFEST_NAME if path.is_dir() else path
        tables = parse_manifest(path)
        log, vehicle = tables["log"], tables["vehicle"]
        imu_model = load_imu(model_ref(path.parent, log["imu"]))
        site = Site(log["lat_deg"], log["lon_deg"], log["alt_m"])
        config = config_from_manifest(tables, imu_model, site, path)
        if "odometer" in vehicle:
            config = with_odometer(config)
        return cls(
            load_camera(model_ref(path.parent, log["camera"])),
            imu_model,
            site=site,
            epoch_utc=log["epoch_utc"],
            rot_nb0=rot_nb0,
            options=options,
            config=config,
            executor=executor,
            workers=workers,
        )

    # ------------------------------------------------------------------ reporting
    @property
    def filter(self) -> ESKF | None:
        """The stream's ESKF (None before the first IMU sample)."""
        return None if self._runner is None else self._runner.filter

    @property
    def _snaps(self) -> deque[NavState]:
        """The filter's snapshots (the image priors start from them)."""
        assert self._runner is not None, "no snapshots before the first IMU sample"
        return self._runner.snaps

    @property
    def t_latest(self) -> float:
        """Time of the newest accepted IMU sample [s] (-inf before the first)."""
        return max(self._t_newest, self._screen.t_latest)

    @property
    def counts(self) -> dict[str, int]:
        """Events reported per kind since the start (``polins.fusion.faults.EventKind``)."""
        return dict(self._events.counts)

    @property
    def events_dropped(self) -> int:
        """Events pushed out of the bounded buffer before :meth:`drain_events` took them."""
        return self._events.dropped

    def drain_events(self) -> pd.DataFrame:
        """Reported events (``t, kind, detail``, oldest first) since the last call."""
        return self._events.drain()

    def drain_measurements(self) -> pd.DataFrame:
        """Image rows whose filter verdict is known (``MEASUREMENT_COLUMNS``), and forget them."""
        rows = list(self._rows)
        self._rows.clear()
        return measurement_frame(rows)

    def drain_updates(self) -> pd.DataFrame:
        """The filter's update log since the last call, every measurement kind (images,
        odometer, NHC, ZUPT): ``polins.fusion.items.records_table``, oldest first."""
        records = list(self._updates)
        self._updates.clear()
        return records_table(records)

    def drain_solution(self) -> pd.DataFrame:
        """The filter's estimates since the last call: the solution table of
        ``polins.fuse`` (``polins.ins.state.solution_table``), a row per filtered IMU sample
        or at ``FuseConfig.output_rate_hz``; the filter runs up to ``max_image_delay_s +
        RUN_S + BLOCK_S`` behind the newest sample, and :meth:`flush` / :meth:`close` filter
        the rest. Empty (with the columns once levelled) before the first filtered sample."""
        return pd.DataFrame() if self._runner is None else self._runner.drain_solution()

    # ------------------------------------------------------------------ inputs
    def add_imu(
        self, t: float, gyro_b: Sequence[float] | FloatArray, accel_b: Sequence[float] | FloatArray
    ) -> bool:
        """One IMU sample: instantaneous body rate [rad/s] and specific force [m/s^2] at ``t``.

        Returns False if the sample was dropped (NaN, not after the previous one, beyond the
        full scale; module docstring). Never waits for the image stage. The samples are
        taken in blocks of ``BLOCK_S`` of IMU time: the call that completes a block screens
        it and runs the filter (module docstring).
        """
        t = float(t)
        wx, wy, wz = gyro_b
        fx, fy, fz = accel_b
        row = (t, float(wx), float(wy), float(wz), float(fx), float(fy), float(fz))
        # the screen of polins.fusion.faults on one sample (NaN fails every comparison)
        if not (
            t > self._t_newest
            and row[1] ** 2 + row[2] ** 2 + row[3] ** 2 <= self._gyro_max_sq
            and row[4] ** 2 + row[5] ** 2 + row[6] ** 2 <= self._accel_max_sq
        ):
            self._pending.append(row)  # dropped by the screen, with its event
            self._ingest(run=True)
            return False
        if t > self._t_newest + self._screen.max_gap_s:  # a gap: known to the next call
            self._pending.append(row)
            self._t_newest = t
            self._ingest(run=True)
            return True
        self._pending.append(row)
        self._t_newest = t
        if t >= self._t_advanced + BLOCK_S:
            self._ingest(run=True)
        return True

    def _ingest(self, *, run: bool) -> None:
        """Screen the pending IMU samples into the buffer; with ``run``, advance the loop
        (dispatch images, hand measurements over, run the filter)."""
        if self._pending:
            block = np.array(self._pending, dtype=float)
            self._pending.clear()
            self._accept(block[:, 0], block[:, 1:4], block[:, 4:7])
        if run:
            self._t_advanced = self._t_newest
            self._advance(block=False)

    def add_imu_many(
        self, t: ArrayLike, gyro_b: ArrayLike, accel_b: ArrayLike
    ) -> NDArray[np.bool_]:
        """A block of IMU samples (``(N,)`` times [s], ``(N, 3)`` rates [rad/s] and specific
        forces [m/s^2]): the same as :meth:`add_imu` for each, with the filter run over them
        at once (its fast path; a recorded log). Returns which samples were accepted."""
        t_a = np.asarray(t, dtype=float).reshape(-1)
        w_a = np.asarray(gyro_b, dtype=float).reshape(-1, 3)
        f_a = np.asarray(accel_b, dtype=float).reshape(-1, 3)
        if not len(t_a) == len(w_a) == len(f_a):
            raise UserInputError(
                f"add_imu_many needs t (N,), gyro_b and accel_b (N, 3); got {len(t_a)}, "
                f"{len(w_a)}, {len(f_a)} samples"
            )
        self._ingest(run=False)
        accepted = self._accept(t_a.copy(), w_a.copy(), f_a.copy())
        if accepted.any():
            self._t_newest = self._t_advanced = self._screen.t_latest
            self._advance(block=False)
        return accepted

    def _accept(self, t: FloatArray, w: FloatArray, f: FloatArray) -> NDArray[np.bool_]:
        """The IMU sample policy of :mod:`polins.fusion.faults` over a block (N,) [s],
        (N, 3) [rad/s, m/s^2]: the dropped samples and the gaps reported, the unit checks
        fed; the accepted samples join the buffer. Returns which were accepted."""
        keep, events, gap_ends = self._screen.screen(t, w, f)
        for ev in events:
            self._events.add(ev.t, ev.kind, ev.detail)
        if not keep.any():
            return keep
        if self._runner is None:
            self._runner = FilterRunner(self.config, float(t[keep][0]), self.imu_dt,
                                        self.rot_nb0,
                                        snapshot_every_s=self.options.snapshot_every_s,
                                        max_rows=self.options.max_table_rows)  # fmt: skip
        self._units.add(t[keep], w[keep], f[keep])
        self._heading_check.add_imu(t[keep], w[keep], f[keep])
        kept = np.flatnonzero(keep)
        bounds = [0, *np.searchsorted(kept, gap_ends).tolist(), len(kept)]
        for j, (a, b) in enumerate(itertools.pairwise(bounds)):  # the runs between gaps
            run = kept[a:b]
            samples = list(zip(t[run].tolist(), w[run], f[run], strict=True))
            if j > 0 and self._last is not None:  # the run starts after a gap
                self._bridge(self._last, samples[0])
            self._buf.extend(samples)
            if samples:
                self._last = samples[-1]
        return keep

    def _bridge(self, before: Sample, after: Sample) -> None:
        """An IMU gap between two accepted samples: its event, and its ``"gap"`` item
        queued in the filter at the sample after it (docs/faults.md)."""
        assert self._runner is not None
        item, event = gap_item(before[0], after[0], (before[1], after[1]), (before[2], after[2]))
        self._events.add(event.t, event.kind, event.detail)
        for skipped in self._runner.filter.skip_in_gap(before[0], after[0]):  # odometer speeds
            self._events.add(skipped.t, skipped.kind, skipped.detail)
        self._collect(self._runner.filter.add_items([item]))
        self._head_valid = False

    def add_image(self, t: float, raw: Any, *, sun_n: ArrayLike | None = None) -> bool:
        """One camera image taken at ``t``: a raw mosaic (or a path / bag message).

        ``sun_n`` (ENU sun vector) defaults to the ephemeris at ``t``. Returns False when
        the image was skipped (module docstring). Waits only while ``max_in_flight`` images
        are being measured (at most one image's processing).
        """
        t = float(t)
        index = self.n_images
        self.n_images += 1
        self._ingest(run=False)
        if not self._usable_time(index, t, "image"):
            return False
        s_n = self.sun_at(t) if sun_n is None else np.asarray(sun_n, dtype=float).reshape(3)
        self._images.append(PendingImage(index, t, raw, s_n))
        if self.filter is not None:
            self._dispatch_ready()  # the filter itself runs in add_imu
        while self._busy() > self.max_in_flight:
            self._wait_oldest()
        return True

    def add_measurement(self, t: float, **columns: Any) -> bool:
        """An external measurement row at ``t`` (``polins.fuse`` measurement columns:
        ``yaw, yaw_std`` [rad] and/or ``sun_bx .. sun_bz, sun_std`` with ``sun_n``); it
        takes the place of an image (same ordering policy)."""
        t = float(t)
        index = self.n_images
        self.n_images += 1  # (the samples add_imu holds have no gap: no need to screen them)
        if not self._usable_time(index, t, "measurement"):
            return False
        row: dict[str, Any] = {"ok": True, "reason": "", "event": "", **columns}
        if "yaw" in row and "heading_deg" not in row:
            row["heading_deg"] = float(heading_deg_from_yaw(row["yaw"]))
        s_n = np.array([row.get(f"sun_n{c}", np.nan) for c in "xyz"], dtype=float)
        self._images.append(PendingImage(index, t, None, s_n, row=row))
        return True

    def add_odometry(self, t: ArrayLike, speed: ArrayLike) -> None:
        """Wheel-odometer speeds: times ``t`` [s] and forward speeds ``speed`` [m/s] (vehicle
        frame; one or many), forward-velocity updates with the odometer scale-factor state
        (needs ``odometer_std``: FuseConfig or the manifest's ``[vehicle]``). They are
        applied when the filter reaches their time; an older one is rejected (logged)."""
        std = self.config.odometer_sigma
        if std is None:
            raise UserInputError("add_odometry needs odometer_std [m/s] (FuseConfig, [vehicle])")
        self._ingest(run=False)
        if self._runner is None:
            raise UserInputError("add_odometry: add the first IMU sample first")
        items = odometer_items({"t": np.atleast_1d(t), "speed": np.atleast_1d(speed)}, std)
        self._collect(self._runner.filter.add_items(items))
        self._head_valid = False

    def _usable_time(self, index: int, t: float, what: str) -> bool:
        f = self.filter
        if not math.isfinite(t) or t <= self._t_last_image:
            self._skip(index, t, "image-out-of-order",
                       f"{what} time not after the previous one (t={self._t_last_image!r})")  # fmt: skip
            return False
        gap = self._screen.inside_gap(t)
        if gap is not None:
            self._skip(
                index, t, EventKind.MEASUREMENT_IN_GAP, f"{what} skipped: {gap_reason(*gap)}"
            )
            return False
        if f is None or t < self._units.t_first - self._tol:
            self._skip(index, t, "image-outside-imu", f"{what} before the first IMU sample")
            return False
        align_s = self.config.initial.align_s
        if self.rot_nb0 is None and t <= self._units.t_first + align_s + self._tol:
            self._skip(index, t, "image-during-alignment",
                       f"{what} inside the levelling window ({align_s} s)")  # fmt: skip
            return False
        delay = self.options.max_image_delay_s
        if f.ready and t < max(f.t, self.t_latest - delay) - self._tol:
            self._skip(index, t, "image-late",
                       f"{what} more than max_image_delay_s={delay} s behind the newest IMU "
                       f"sample (t={self.t_latest:.6f})")  # fmt: skip
            return False
        self._t_last_image = t
        return True

    # ------------------------------------------------------------------ outputs
    def state(self) -> StreamState:
        """Latest estimate: all accepted IMU samples, all measurements known so far."""
        levelled = self.filter is not None and self.filter.ready
        self._ingest(run=not levelled)  # the levelling needs no image: done at once
        if self.filter is None or not self.filter.ready:
            return StreamState(nav=None, aligning=True, images_pending=len(self._images))
        self._hand_over_ready(block=False)  # queued in the filter: the head applies them
        pending = len(self._images)
        if self._head is None or not self._head_valid:
            self._head = self.filter.copy()
            self._head_valid = True
        head = self._head
        held = [s for s in self._buf if s[0] > head.t + self._tol] if head.started else self._buf
        if held:  # the held-back samples, through the filter's fast path
            t, gyro, accel = zip(*held, strict=True)
            head.propagate_many(np.array(t), np.array(gyro), np.array(accel))
        head.records.clear()  # bounded memory: the head's log is not used
        return StreamState(nav=head.state(), aligning=False, images_pending=pending)

    def flush(self) -> None:
        """Measure and apply every image added so far; filter every accepted IMU sample."""
        self._ingest(run=False)
        self._advance(block=True, final=True)
        if self._runner is not None:
            self._runner.finish()
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
        else:  # the queued images cancelled, the running ones (one per worker) awaited:
            # a process pool left running prints a traceback at the interpreter's exit
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._closed = True

    # ------------------------------------------------------------------ internals
    def _skip(self, index: int, t: float, kind: str, detail: str) -> None:
        self._events.add(t, kind, detail)
        self._rows.append({"t": t, "image": index, "ok": False, "reason": f"{kind}: {detail}",
                           "accepted": False, "update_reason": "skipped"})  # fmt: skip

    def _skip_in_gaps(self) -> bool:
        """Skip the images (and external measurements) strictly inside an IMU gap, as
        every path does (docs/faults.md); True if one was."""
        if not self._screen.gaps:
            return False
        inside = [(img, self._screen.inside_gap(img.t)) for img in self._images]
        skipped = [(img, gap) for img, gap in inside if gap is not None]
        for img, gap in skipped:
            self._images.remove(img)
            what = "image" if img.row is None else "measurement"
            self._skip(img.index, img.t, EventKind.MEASUREMENT_IN_GAP,
                       f"{what} skipped: {gap_reason(*gap)}")  # fmt: skip
        return bool(skipped)

    def _busy(self) -> int:
        return sum(1 for img in self._images if img.future is not None and not img.resolved)

    def _wait_oldest(self) -> None:
        for img in self._images:
            if img.future is not None and not img.resolved:
                img.future.result()
                return

    def _snapshot_limit(self, img: PendingImage) -> float:
        return img.t - self.options.prior_lag_s - self._tol

    def _prior_ready(self, img: PendingImage) -> bool:
        """The snapshot of ``img`` is final and the IMU reaches the image."""
        f = self.filter
        assert f is not None
        if not f.ready or not self._snaps or self._screen.t_latest < img.t - self._tol:
            return False
        # no later snapshot can be older than the limit once the next sample is past it
        return not self._buf or self._buf[0][0] >= self._snapshot_limit(img)

    def _dispatch(self, img: PendingImage) -> None:
        assert self._runner is not None
        limit = self._snapshot_limit(img)
        snap = self._snaps[0]
        for s in self._snaps:
            if s.t < limit:
                snap = s
            else:
                break
        k = next((i for i, s in enumerate(self._hist) if s[0] >= snap.t - self._tol), 0)
        samples = list(itertools.islice(self._hist, max(k - 1, 0), None))
        for sample in self._buf:  # up to the first sample at or after the image
            samples.append(sample)
            if sample[0] >= img.t:
                break
        # the prior is propagated where the image is measured (off the caller's thread)
        prior = PriorJob.of(snap, samples, img.t, self._runner.filter.mech)
        img.future = self._executor.submit(self._submit_fn, img.item, img.sun_n, prior)
        img.item = None  # the raw image is the worker's now

    def _hand_over(self, images: list[PendingImage]) -> None:
        """Give images' measurements to the filter (before it passes their times), in
        time order: their rows as one measurement table (``items_from_table``, the rules of
        ``polins.fuse``; rows with the same columns at once)."""
        f = self.filter
        assert f is not None
        rows: list[dict[str, Any]] = []
        done = 0
        try:
            for img in images:
                done += 1
                row = self._row_of(img)
                if row is not None:
                    rows.append(row)
        except ImuUnitsError:  # the images after it stay queued
            self._images.extendleft(reversed(images[done:]))
            raise
        finally:  # the rows before it are handed over all the same
            for _, group in itertools.groupby(rows, key=_columns):
                block = list(group)
                items = items_from_table({k: [row[k] for row in block] for k in block[0]},
                                         use_sun=f.config.gating.use_sun,
                                         heading_bias=f.config.heading_bias)  # fmt: skip
                self._collect(f.add_items(items))
            f.records.clear()  # bounded memory: verdicts are kept in the measurement rows

    def _row_of(self, img: PendingImage) -> dict[str, float] | None:
        """The measurement-table row of a measured image for the filter (None when it was
        not measured); its row of the measurement log waits for the filter's verdict."""
        if img.row is None:
            assert img.future is not None
            img.row = dict(img.future.result())
        row = img.row
        row.update(t=img.t, image=img.index)
        for c, v in zip("xyz", img.sun_n, strict=True):
            row[f"sun_n{c}"] = float(v)
        if row.get("event"):
            self._events.add(img.t, row["event"], row["reason"])
        report_noise_model(row, self._events, img.t)
        if not row.get("ok"):
            row.update(accepted=False, update_reason="not measured")
            self._rows.append(row)
            return None
        self._heading_check.add_headings(img.t, heading_proxy(row))  # ImuUnitsError: deg/s
        cols: dict[str, float] = {"t": img.t}
        if "yaw" in row:
            cols.update(yaw=row["yaw"], yaw_std=float(self.config.yaw_sigma(row["yaw_std"])))
        if "sun_bx" in row:
            cols.update({f"sun_b{c}": row[f"sun_b{c}"] for c in "xyz"})
            cols["sun_std"] = float(self.config.sun_sigma(row["sun_std"]))
        else:
            cols.update(sun_bx=math.nan, sun_by=math.nan, sun_bz=math.nan)
        cols.update({f"sun_n{c}": row[f"sun_n{c}"] for c in "xyz"})
        if all(np.isfinite(row.get(c, np.nan)) for c in PRIOR_COLUMNS):
            cols.update({c: row[c] for c in PRIOR_COLUMNS})
        cols.update({c: float(row[c]) for c in SKY_COLUMNS if c in row})
        self._by_t[img.t] = row
        self._head_valid = False  # the head may have passed the measurement's time
        return cols

    def _collect(self, records: Iterable[UpdateRecord]) -> None:
        for rec in records:
            self._head_valid = False
            self._updates.append(rec)
            row = self._by_t.pop(rec.t, None) if rec.name in ("yaw", "sun") else None
            if row is None:
                continue
            row.update(accepted=bool(rec.accepted), update_reason=rec.reason,
                       nis=rec.nis, nis_dof=rec.dim)  # fmt: skip
            if rec.name == "yaw" and rec.innovation:  # measured minus predicted yaw [rad]
                row["innovation"] = float(rec.innovation[0])
            self._rows.append(row)

    def _filter_run(self, n: int) -> None:
        """Filter the first ``n`` buffered IMU samples (module docstring)."""
        assert self._runner is not None
        samples = [self._buf.popleft() for _ in range(n)]
        self._hist.extend(samples)
        records, changed = self._runner.run(samples)
        if changed:
            self._head_valid = False
            self._collect(records)
        self._trim()

    def _runnable(self, final: bool) -> int:
        """Buffered samples the filter can take now: before the next image to hand over,
        and not inside the window where a late image may still come (at least one)."""
        tol = self._tol
        t_image = self._images[0].t - tol if self._images else math.inf
        if final:
            t_wait = math.inf
        elif self.filter is not None and not self.filter.ready:  # up to the levelling's end
            t_wait = self._units.t_first + self.config.initial.align_s + tol
        else:
            t_wait = max(self._screen.t_latest - self.options.max_image_delay_s,
                         self._t_last_image)  # fmt: skip
        times = [sample[0] for sample in self._buf]  # increasing
        return max(1, min(bisect.bisect_left(times, t_image), bisect.bisect_right(times, t_wait)))

    def _trim(self) -> None:
        """Forget snapshots and IMU history that no future prior can need."""
        f = self.filter
        assert f is not None
        waiting = [img.t for img in self._images if not img.dispatched]
        t_ref = min(waiting) if waiting else max(self._t_last_image, f.t)
        limit = t_ref - self.options.prior_lag_s - self._tol
        while len(self._snaps) > 1 and self._snaps[1].t < limit:
            self._snaps.popleft()
        oldest = min((img.t for img in self._images), default=self._t_last_image)
        self._screen.gaps = [g for g in self._screen.gaps if g[1] > oldest]
        keep_from = min(self._snaps[0].t if self._snaps else math.inf, f.t)
        while len(self._hist) > 1 and self._hist[1][0] <= keep_from:
            self._hist.popleft()

    def _advance(self, *, block: bool, final: bool = False) -> None:
        """Dispatch images whose prior is known, hand results over, filter IMU samples."""
        if self.filter is None:
            return
        while True:
            progressed = self._skip_in_gaps()
            progressed = self._dispatch_ready() or progressed
            progressed = self._drain(block=block, final=final) or progressed
            if not progressed:
                if block and any(img.future is not None and not img.resolved
                                 for img in self._images):  # fmt: skip
                    self._wait_oldest()
                    continue
                return

    def _hand_over_ready(self, block: bool) -> bool:
        """Hand the measured images over in time order (the filter applies each at its
        time; ``block``: wait for the measurements); True if any was."""
        ready = []
        while self._images and self._images[0].dispatched and (self._images[0].resolved or block):
            ready.append(self._images.popleft())
        if ready:
            self._hand_over(ready)
        return bool(ready)

    def _dispatch_ready(self) -> bool:
        """Dispatch the waiting images whose prior is known; True if any was."""
        progressed = False
        for img in self._images:  # in time order: priors become known in order
            if img.dispatched:
                continue
            if not self._prior_ready(img):
                break
            self._dispatch(img)
            progressed = True
        return progressed

    def _drain(self, *, block: bool, final: bool) -> bool:
        """Hand the images due before the next buffered IMU sample over and filter the
        samples no image can still precede; True if anything was done."""
        f = self.filter
        assert f is not None
        tol = self._tol
        delay = self.options.max_image_delay_s
        progressed = False
        while True:
            progressed = self._hand_over_ready(block) or progressed
            if not self._buf:
                return progressed
            t_next = self._buf[0][0]
            if self._images and self._images[0].t <= t_next + tol:
                img = self._images[0]
                if img.dispatched or f.ready:
                    return progressed  # its prior or its measurement is not known yet
                self._images.popleft()  # no prior can ever come
                self._skip(img.index, img.t, "image-during-alignment",
                           "no attitude yet (self-alignment still levelling)")  # fmt: skip
                progressed = True
                continue
            late = t_next > self._screen.t_latest - delay and t_next > self._t_last_image
            if not final and f.ready and late:
                return progressed  # an image up to max_image_delay_s late may still come
            n = self._runnable(final)
            if not (final or not f.ready or self._prior_wanted()) and (
                self._buf[n - 1][0] - t_next < RUN_S
            ):
                return progressed  # a longer run later: the run's overhead spread wider
            self._filter_run(n)
            progressed = True

    def _prior_wanted(self) -> bool:
        """An image waits for the filter to pass its prior's snapshot time."""
        return any(not img.dispatched for img in self._images)


__all__ = ["NavigationStream", "StreamState", "with_odometer"]
