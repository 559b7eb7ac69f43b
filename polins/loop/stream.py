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

Each image is measured with a prior from a filter snapshot (:mod:`polins.loop.prior`:
which snapshot, why images closer than ``prior_lag_s`` are measured in parallel, what the
lag costs). Each measurement updates the filter at its image time, so the filter holds back
the IMU samples after the oldest image whose measurement is not known yet, and those of the
last ``max_image_delay_s`` (an image may still come). ``add_imu`` collects the samples
(:mod:`polins.loop.intake`) and, once every ``BLOCK_S`` of IMU time, screens the block,
hands the measured images over (:mod:`polins.loop.images`; queued in the filter, applied at
their times) and runs the samples the filter can take, in runs of at least ``RUN_S``
unless an image waits for its prior, through its fast path
(:mod:`polins.fusion.eskf.propagate`, :mod:`polins.loop.runner`), which gives the same
estimates as ``polins.fusion.run_fusion`` on the stream's measurement table (to 1e-8 rad).
The filter's covariance steps end where its runs end, so how the samples split into runs
(the blocks, the images measured by then) moves the estimates and the image priors by
~1e-10 rad and the sigmas by ~1e-5 relative; nothing else depends on timing or on the
number of workers.

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

import dataclasses
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
    config_with_site,
    site_from_shorthand,
)
from polins.fusion.eskf.filter import ESKF
from polins.fusion.faults import (
    ImuUnitsError,
    default_max_gap_s,
    gap_item,
)
from polins.fusion.items import UpdateRecord, records_table
from polins.fusion.vehicle import odometer_items
from polins.loop.images import ImageQueue, row_items
from polins.loop.intake import ImuIntake
from polins.loop.measurer import (
    EXECUTORS,
    ImageMeasurer,
    PendingImage,
    make_executor,
)
from polins.loop.options import LoopOptions
from polins.loop.prior import SunGrid
from polins.loop.runner import FilterRunner, Snapshot
from polins.loop.samples import Sample
from polins.loop.setup import manifest_setup
from polins.loop.state import StreamState
from polins.loop.tables import EventBuffer
from polins.models import CameraModel, ImuModel
from polins.site import Site, utc_timestamp

FloatArray = NDArray[np.float64]
# IMU time [s] add_imu collects before it screens the samples and advances the loop: the
# per-call overhead of screening, dispatching and running the filter spread over this block
BLOCK_S = 0.25
# shortest run of samples [s] the filter takes while no image waits for its prior
RUN_S = 1.0


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
        self._updates: deque[UpdateRecord] = deque(maxlen=self.options.max_table_rows)
        self._events = EventBuffer(self.options.max_table_rows)
        self._queue = ImageQueue(self._executor, self._submit_fn, self._events,
                                 self.options.max_table_rows)  # fmt: skip
        self._images = self._queue.pending  # added, not yet handed to the filter
        # the fault policy of every path (polins.fusion.faults, docs/faults.md)
        self._intake = ImuIntake(imu_model.full_scale(),
                                 default_max_gap_s(self.config.gap_s, self.imu_dt),
                                 self.config.initial.align_s, BLOCK_S, self._events)  # fmt: skip
        self._screen, self._units = self._intake.screen, self._intake.units
        self._buf = self._intake.queue  # accepted samples not yet filtered
        self.n_images = 0  # images added (including skipped ones)
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

        From the manifest (a folder means its ``manifest.toml``,
        :func:`polins.loop.setup.manifest_setup`): the camera and IMU model files, the site
        and ``epoch_utc`` of ``[log]``, and the filter configuration of ``[vehicle]`` and
        ``[filter]`` (a ``[vehicle] odometer`` gives the odometer scale-factor state, fed by
        :meth:`add_odometry`). The log's data files are not read; the stream takes SI units
        whatever ``[units]`` says of them. The other parameters are the constructor's.
        """
        setup = manifest_setup(manifest_path)
        camera, imu_model = setup.pop("camera"), setup.pop("imu_model")
        return cls(camera, imu_model, rot_nb0=rot_nb0, options=options, executor=executor,
                   workers=workers, **setup)  # fmt: skip

    # ------------------------------------------------------------------ reporting
    @property
    def filter(self) -> ESKF | None:
        """The stream's ESKF (None before the first IMU sample)."""
        return None if self._runner is None else self._runner.filter

    @property
    def _snaps(self) -> deque[Snapshot]:
        """The filter's snapshots (the image priors start from them)."""
        assert self._runner is not None, "no snapshots before the first IMU sample"
        return self._runner.snaps

    @property
    def t_latest(self) -> float:
        """Time of the newest accepted IMU sample [s] (-inf before the first)."""
        return max(self._intake.t_newest, self._screen.t_latest)

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
        return self._queue.drain()

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
        accepted, due = self._intake.add(t, gyro_b, accel_b)
        if due:
            self._ingest(run=True)
        return accepted

    def _ingest(self, *, run: bool) -> None:
        """Screen the pending IMU samples into the buffer; with ``run``, advance the loop
        (dispatch images, hand measurements over, run the filter)."""
        block = self._intake.pending_block()
        if block is not None:
            self._accept(block[:, 0], block[:, 1:4], block[:, 4:7])
        if run:
            self._intake.t_advanced = self._intake.t_newest
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
            self._intake.t_newest = self._intake.t_advanced = self._screen.t_latest
            self._advance(block=False)
        return accepted

    def _accept(self, t: FloatArray, w: FloatArray, f: FloatArray) -> NDArray[np.bool_]:
        """The IMU sample policy of :mod:`polins.fusion.faults` over a block (N,) [s],
        (N, 3) [rad/s, m/s^2]: the dropped samples and the gaps reported, the unit checks
        fed; the accepted samples join the buffer. Returns which were accepted."""
        keep, gap_ends = self._intake.screen_block(t, w, f)
        if not keep.any():
            return keep
        if self._runner is None:
            self._runner = FilterRunner(self.config, float(t[keep][0]), self.imu_dt,
                                        self.rot_nb0,
                                        snapshot_every_s=self.options.snapshot_every_s,
                                        max_rows=self.options.max_table_rows)  # fmt: skip
        for before, after in self._intake.queue_block(t, w, f, keep, gap_ends):
            self._bridge(before, after)
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
        while self._queue.busy() > self.max_in_flight:
            self._queue.wait_oldest()
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
        """Whether an image (or measurement) at ``t`` can be used
        (:meth:`ImageQueue.admit`); else it is skipped with its reason."""
        f = self.filter
        levelling = self.rot_nb0 is None
        return self._queue.admit(
            index, t, what, gap=self._screen.inside_gap(t),
            t_first=None if f is None else self._units.t_first - self._tol,
            t_level_end=self._units.t_first + self.config.initial.align_s + self._tol
            if levelling else -math.inf,
            align_s=self.config.initial.align_s,
            t_late=max(f.t, self.t_latest - self.options.max_image_delay_s) - self._tol
            if f is not None and f.ready else -math.inf,
            delay=self.options.max_image_delay_s, t_latest=self.t_latest,
        )  # fmt: skip

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
        buf = self._buf
        k = int(np.searchsorted(buf.t, head.t + self._tol, side="right")) if head.started else 0
        if k < len(buf):  # the held-back samples, through the filter's fast path
            head.propagate_many(buf.t[k:], buf.gyro_b[k:], buf.accel_b[k:])
        head.records.clear()  # bounded memory: the head's log is not used
        return StreamState(nav=head.state(), aligning=False, images_pending=pending)

    def flush(self) -> None:
        """Measure and apply every image added so far; filter every accepted IMU sample."""
        self._ingest(run=False)
        self._advance(block=True, final=True)
        if self._runner is not None:
            self._runner.finish()
        self._queue.close()

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
    def _snapshot_limit(self, img: PendingImage) -> float:
        return img.t - self.options.prior_lag_s - self._tol

    def _prior_ready(self, img: PendingImage) -> bool:
        """The snapshot of ``img`` is final and the IMU reaches the image."""
        f = self.filter
        assert f is not None
        if not f.ready or not self._snaps or self._screen.t_latest < img.t - self._tol:
            return False
        # no later snapshot can be older than the limit once the next sample is past it
        return not self._buf or self._buf.t[0] >= self._snapshot_limit(img)

    def _dispatch(self, img: PendingImage) -> None:
        assert self._runner is not None
        prior = self._runner.prior_job(img.t, self._snapshot_limit(img), self._buf)
        self._queue.submit(img, prior)

    def _hand_over(self, images: list[PendingImage]) -> None:
        """Give images' measurements to the filter (before it passes their times), in
        time order (:func:`~polins.loop.images.row_items`)."""
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
            for items in row_items(rows, f.config):
                self._collect(f.add_items(items))
            f.records.clear()  # bounded memory: verdicts are kept in the measurement rows

    def _row_of(self, img: PendingImage) -> dict[str, float] | None:
        """The measurement-table row of a measured image for the filter (None when it was
        not measured): :meth:`ImageQueue.filter_row`."""
        cols = self._queue.filter_row(img, self.config, self._intake.heading_check)
        if cols is not None:
            self._head_valid = False  # the head may have passed the measurement's time
        return cols

    def _collect(self, records: Iterable[UpdateRecord]) -> None:
        for rec in records:
            self._head_valid = False
            self._updates.append(rec)
            self._queue.verdict(rec)

    def _filter_run(self, n: int) -> None:
        """Filter the first ``n`` buffered IMU samples (module docstring)."""
        assert self._runner is not None
        t, gyro, accel = self._buf.take(n)
        records, changed = self._runner.run(t, gyro, accel)
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
                         self._queue.t_last)  # fmt: skip
        times = self._buf.t  # increasing
        n_ready = min(np.searchsorted(times, t_image, side="left"),
                      np.searchsorted(times, t_wait, side="right"))  # fmt: skip
        return max(1, int(n_ready))

    def _trim(self) -> None:
        """Forget snapshots and IMU history that no future prior can need."""
        f = self.filter
        assert f is not None
        waiting = [img.t for img in self._images if not img.dispatched]
        t_ref = min(waiting) if waiting else max(self._queue.t_last, f.t)
        assert self._runner is not None
        self._runner.trim(t_ref - self.options.prior_lag_s - self._tol)
        oldest = min((img.t for img in self._images), default=self._queue.t_last)
        self._screen.gaps = [g for g in self._screen.gaps if g[1] > oldest]

    def _advance(self, *, block: bool, final: bool = False) -> None:
        """Dispatch images whose prior is known, hand results over, filter IMU samples."""
        if self.filter is None:
            return
        while True:
            progressed = self._queue.skip_in_gaps(self._screen)
            progressed = self._dispatch_ready() or progressed
            progressed = self._drain(block=block, final=final) or progressed
            if not progressed:
                if block and any(img.future is not None and not img.resolved
                                 for img in self._images):  # fmt: skip
                    self._queue.wait_oldest()
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
            t_next = float(self._buf.t[0])
            if self._images and self._images[0].t <= t_next + tol:
                img = self._images[0]
                if img.dispatched or f.ready:
                    return progressed  # its prior or its measurement is not known yet
                self._images.popleft()  # no prior can ever come
                self._queue.skip(img.index, img.t, "image-during-alignment",
                           "no attitude yet (self-alignment still levelling)")  # fmt: skip
                progressed = True
                continue
            late = t_next > self._screen.t_latest - delay and t_next > self._queue.t_last
            if not final and f.ready and late:
                return progressed  # an image up to max_image_delay_s late may still come
            n = self._runnable(final)
            if not (final or not f.ready or self._prior_wanted()) and (
                self._buf.t[n - 1] - t_next < RUN_S
            ):
                return progressed  # a longer run later: the run's overhead spread wider
            self._filter_run(n)
            progressed = True

    def _prior_wanted(self) -> bool:
        """An image waits for the filter to pass its prior's snapshot time."""
        return any(not img.dispatched for img in self._images)


__all__ = ["NavigationStream", "StreamState"]
