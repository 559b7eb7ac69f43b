"""The navigation loop over a recorded log: :func:`run_log` measures every image and fuses it once.

The filter runs once. :func:`run_log` feeds the log to a
:class:`~polins.loop.stream.NavigationStream` in time order (images measured by a pool of
processes); the stream's filter is the one the Eq. 13 loop needs for the image priors, and
it also keeps its estimate at every accepted IMU sample (or at ``output_rate_hz``), which
*is* the final ESKF solution (a second pass through ``polins.fuse`` would only repeat it). The
other backends are other estimators, run once on the stream's measurement table
(:func:`fuse_measurements`): the RTS smoother (a forward pass that stores what the backward
pass needs) and the GTSAM graph.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError
from polins.fusion.api import run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.result import FusionResult
from polins.io.images import ImageIndex
from polins.io.log import Log
from polins.loop.options import LoopOptions
from polins.loop.setup import with_odometer
from polins.loop.stream import NavigationStream
from polins.loop.tables import EVENT_COLUMNS

MEASUREMENT_INPUTS = ("t", "yaw", "yaw_std", "sun_bx", "sun_by", "sun_bz", "sun_nx", "sun_ny",
                      "sun_nz", "sun_std", "prior_roll", "prior_pitch", "prior_yaw")  # fmt: skip


def fuse_measurements(
    imu: pd.DataFrame,
    measurements: pd.DataFrame,
    config: FuseConfig,
    *,
    rot_nb0: Rotation | None = None,
    backend: str = "eskf",
    odometry: pd.DataFrame | None = None,
    progress: bool = False,
) -> FusionResult:
    """A solution from the loop's measurement table (its rows with ``ok``): ``run_fusion``
    (``progress``: a tqdm line while the graph solves).

    ``config`` is the stream's filter configuration (:attr:`NavigationStream.config`): the
    IMU samples the stream accepted meet the same fault policy (docs/faults.md) here, its
    gaps bridged alike (the images inside them were skipped by the stream).
    """
    ok = measurements["ok"].to_numpy(dtype=bool)
    table = measurements.loc[ok, list(MEASUREMENT_INPUTS)].reset_index(drop=True).astype(float)
    return run_fusion(imu, table, backend, rot_nb0, config, odometry, progress)


def check_images_exist(log: Log) -> None:
    """Refuse a log none of whose image files exists, before any work (``UserInputError``,
    one line naming the missing folder and the count); some missing files are data faults
    (``image-unreadable`` events, docs/faults.md)."""
    images = log.images
    if not isinstance(images, ImageIndex) or not len(images):
        return
    exists = np.array([f.exists() for f in images.files])
    if exists.any():
        return
    folders = sorted({f.parent for f in images.files})
    gone = [d for d in folders if not d.is_dir()]
    where = f"the image folder {gone[0]} does not exist" if gone else f"none is in {folders[0]}"
    raise UserInputError(
        f"{log.manifest_path}: {where}: all {len(images)} images of the index are missing"
    )


def log_config(log: Log, config: FuseConfig | None) -> FuseConfig:
    """The filter configuration of a log's run: ``config``, or the log's own
    (``FuseConfig.from_log``), with the odometer's sigma when the log has odometry."""
    base = config if config is not None else FuseConfig.from_log(log)
    return base if log.odometry is None else with_odometer(base)


def run_log(
    log: Log,
    *,
    options: LoopOptions | None = None,
    config: FuseConfig | None = None,
    backend: str = "eskf",
    workers: int | None = None,
    rot_nb0: Rotation | None = None,
    progress: bool = True,
) -> FusionResult:
    """Measurement and fusion of a recorded log: the Eq. 13 loop, its filter run once.

    Parameters
    ----------
    log : Log
        From ``polins.io.read_log``; its site and IMU model replace those of ``config``.
    options : LoopOptions
    config : FuseConfig, optional
        The filter's configuration (default: the log's ``[filter]`` table, else defaults).
        ``smooth=True`` gives the Rauch-Tung-Striebel smoothed solution.
    backend : {"eskf", "graph"}
        Backend of the final solution (the loop itself always runs the ESKF).
    workers : int, optional
        Image processes; default all cores; 1 measures in this process.
    rot_nb0 : Rotation, optional
        Initial attitude; default self-alignment.
    progress : bool
        tqdm progress bar over the images.

    Returns
    -------
    FusionResult
        With ``measurements`` (one row per image), ``updates`` (every measurement kind:
        images, odometer, NHC, ZUPT) and in ``info``: ``timing``, ``settings`` and
        ``imu_used`` (``FusionResult`` lists them).
    """
    from tqdm import tqdm

    check_images_exist(log)
    opts = options if options is not None else LoopOptions()
    base = log_config(log, config)
    base.check_backend(backend)
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise UserInputError(f"workers={workers!r} must be an integer >= 1")
    n_workers = int(workers) if workers else (os.cpu_count() or 1)
    own_solution = backend == "eskf" and not base.output.smooth
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
        site=log.site,
        epoch_utc=log.epoch_utc,
        rot_nb0=rot_nb0,
        options=opts,
        config=base.replace(smooth=False),
        imu_dt=dt_med,
        executor="process" if n_workers > 1 else "inline",
        workers=n_workers,
    )
    k = 0

    def feed(stop: int) -> None:
        nonlocal k
        if stop > k:
            used[k:stop] = stream.add_imu_many(t_imu[k:stop], gyro[k:stop], accel[k:stop])
        k = max(k, stop)

    odometry = log.odometry
    with stream:
        if odometry is not None and len(t_imu):  # queued in the filter, applied in time
            feed(1)
            stream.add_odometry(odometry["t"].to_numpy(float), odometry["speed"].to_numpy(float))
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
    events = stream.drain_events()
    if log.events:  # faults found while loading the log (paths outside its folder)
        loaded = pd.DataFrame(list(log.events), columns=pd.Index(EVENT_COLUMNS))
        events = pd.concat([loaded, events], ignore_index=True)
    imu_used = imu.loc[used].reset_index(drop=True)
    t_fuse = time.perf_counter()
    config = stream.config.replace(smooth=base.output.smooth)
    if own_solution:
        fused = FusionResult(stream.drain_solution(), stream.drain_updates(), events, config)
    else:
        fused = fuse_measurements(
            imu_used,
            measurements,
            config,
            rot_nb0=rot_nb0,
            backend=backend,
            odometry=odometry,
            progress=progress,
        )
    end = time.perf_counter()
    measure_s = measurements["measure_s"].to_numpy(dtype=float)
    settings = {
        "manifest": str(log.manifest_path),
        "backend": backend,
        "solver": base.graph.solver if backend == "graph" else None,
        "smooth": base.output.smooth,
        "workers": n_workers,
        "method": opts.method,
        "update": opts.update,
        "prior_lag_s": opts.prior_lag_s,
        "measure_options": opts.measure_kwargs(),
        "fuse_options": {k: v for k, v in base.changes().items() if k not in ("imu_model", "site")},
        "camera": log.camera.name,
        "camera_shape": list(log.camera.shape),
        "imu_model": log.imu_model.name,
        "rot_nb0_given": rot_nb0 is not None,
        "events_dropped": stream.events_dropped,  # beyond the bounded event buffer
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
    info = {**fused.info, "timing": timing, "settings": settings, "imu_used": imu_used}
    return dataclasses.replace(fused, events=events, backend=backend, info=info,
                               measurements=measurements)  # fmt: skip


__all__ = ["MEASUREMENT_INPUTS", "fuse_measurements", "log_config", "run_log"]
