"""The image stage of the loop: ``polins.measure`` on one image, in this process, threads or processes.

:class:`ImageMeasurer` turns one image item (a raw mosaic, a path or a bag message) and its
prior into a measurement row. A data fault of the image (it cannot be read or decoded:
:class:`polins.io.ImageReadError`; OpenCV failing on its pixels: ``cv2.error``) gives a row
with ``ok=False`` and the event to report (docs/faults.md); any other exception is a bug and
propagates to the caller (through the executor's future).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import signal
import time
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from polins.compass.measure import NoiseModelWarning, check_measure_options, measure
from polins.compass.measurement import NOISE_RATIO_BAND
from polins.fusion.inputs import measurement_row
from polins.io.images import ImageReadError, load_raw
from polins.loop.prior import PriorJob
from polins.loop.tables import EventBuffer
from polins.models import CameraModel

FloatArray = NDArray[np.float64]
EXECUTORS = ("inline", "thread", "process")


class ImageMeasurer:
    """``polins.measure`` on one image item (picklable; one per worker).

    Parameters
    ----------
    camera : CameraModel
    method : str
        ``polins.measure`` method.
    options : mapping
        ``polins.measure`` keyword options (checked here, not in every image).
    """

    def __init__(self, camera: CameraModel, method: str, options: Mapping[str, Any]) -> None:
        check_measure_options(method, dict(options))  # a bad method or option fails here, once
        self.camera = camera
        self.method = method
        self.options = dict(options)

    def __call__(self, item: Any, sun_n: FloatArray, prior: PriorJob) -> dict[str, Any]:
        """Measure one image; a measurement row (``ok=False``, reason and event on a data
        fault) with the prior's columns.

        Parameters
        ----------
        item : array, path or bag message
            What :func:`polins.io.load_raw` loads.
        sun_n : (3,) ndarray
            ENU sun vector at the image time.
        prior : PriorJob
            What the prior attitude (body -> ENU) at the image time is computed from.
        """
        start = time.perf_counter()
        rot_prior = prior.rotation()
        row: dict[str, Any] = {"ok": False, "reason": "", "event": "", **prior.columns(rot_prior)}
        try:
            raw = load_raw(item, shape=self.camera.shape)
        except ImageReadError as exc:
            row.update(reason=f"unreadable image: {exc}", event="image-unreadable")
        else:
            try:
                with warnings.catch_warnings():  # the loop reports it once per run
                    warnings.simplefilter("ignore", NoiseModelWarning)
                    m = measure(raw, self.camera, sun_n=sun_n,
                                rot_nb_prior=rot_prior,
                                method=self.method, **self.options)  # fmt: skip
            except cv2.error as exc:
                row.update(reason=f"measurement failed: OpenCV: {exc}", event="image-error")
            else:  # the row polins.fuse takes, and the sigma in degrees for the table
                row.update(measurement_row(m), heading_std_deg=math.degrees(m.yaw_std))
        row["measure_s"] = time.perf_counter() - start
        return row


def report_noise_model(row: Mapping[str, Any], events: EventBuffer, t: float) -> None:
    """Report the first image of a run whose measured noise is outside ``NOISE_RATIO_BAND``
    times the camera file's noise model: one ``noise-model`` event and one
    ``NoiseModelWarning`` (``polins.measure`` warns per image; the loop once, and every
    image's ``noise_ratio`` is in its row)."""
    ratio = float(row.get("noise_ratio", math.nan))
    low, high = NOISE_RATIO_BAND
    if not row.get("ok") or not ratio > 1e-3 or low <= ratio <= high:
        return
    if events.counts["noise-model"]:
        return
    detail = (
        f"measured noise is {ratio:.2f} x the camera file's noise model (outside [{low:g}, "
        f"{high:g}]): check read_noise_dn, the channel gains and dark offsets (reported once; "
        "every image's noise_ratio is in measurements.csv)"
    )
    events.add(t, "noise-model", detail)
    warnings.warn(detail, NoiseModelWarning, stacklevel=4)


# The measurer of a worker process, set once by the pool's initializer (so the camera and
# its per-camera caches are built once per process, not sent with every image).
_WORKER: ImageMeasurer | None = None


def _worker_init(measurer: ImageMeasurer) -> None:
    global _WORKER
    _WORKER = measurer
    # Ctrl-C is the parent's to handle (one line, outputs unchanged): a worker of any start
    # method must not print a traceback of its own
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _worker_call(item: Any, sun_n: FloatArray, prior: PriorJob) -> dict[str, Any]:
    if _WORKER is None:
        raise RuntimeError("image worker used before its initializer ran")
    return _WORKER(item, sun_n, prior)


def _worker_ready() -> bool:
    return _WORKER is not None


class InlineExecutor(Executor):
    """Runs each job at submission, in the caller (no parallelism; the deterministic reference)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        """Run ``fn(*args, **kwargs)`` now; its result or exception is in the returned future."""
        fut: Future[Any] = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # the future carries it to the caller's result()
            fut.set_exception(exc)
        return fut


class FedPool(Executor):
    """A process pool fed by a thread of its own: ``submit`` returns at once.

    ``ProcessPoolExecutor.submit`` hands the job to the pool's management thread and its
    queue's feeder thread; called on the caller's thread it holds the caller up about
    13 ms (median, loaded 2-core machine, 1/8-resolution images; docs/streaming.md). Here
    one thread submits, and the returned future follows the pool's.
    """

    def __init__(self, pool: ProcessPoolExecutor) -> None:
        self.pool = pool
        self._feeder = ThreadPoolExecutor(max_workers=1)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        """Queue ``fn(*args, **kwargs)`` for the pool; its result or exception (or its
        cancellation) is in the returned future."""
        out: Future[Any] = Future()

        def forward() -> None:
            try:
                inner = self.pool.submit(fn, *args, **kwargs)
            except BaseException as exc:  # a broken or shut-down pool: the caller's result()
                out.set_exception(exc)
                return
            inner.add_done_callback(lambda done: _follow(done, out))

        self._feeder.submit(forward)
        return out

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop feeding, then shut the pool down."""
        self._feeder.shutdown(wait=True, cancel_futures=cancel_futures)
        self.pool.shutdown(wait=wait, cancel_futures=cancel_futures)


def _follow(done: Future[Any], out: Future[Any]) -> None:
    """Give ``out`` the outcome of ``done``."""
    if done.cancelled():
        out.cancel()
    elif done.exception() is not None:
        out.set_exception(done.exception())
    else:
        out.set_result(done.result())


def make_executor(
    kind: str, workers: int, measurer: ImageMeasurer
) -> tuple[Executor, Callable[..., dict[str, Any]]]:
    """An executor for the image stage and the function to submit to it.

    Parameters
    ----------
    kind : {"inline", "thread", "process"}
        In the caller, in ``workers`` threads, or in ``workers`` processes (started here,
        each initialised once with the measurer).
    workers : int
        Threads or processes.
    measurer : ImageMeasurer
    """
    if kind == "inline":
        return InlineExecutor(), measurer
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
        # the workers start here, before the caller starts other threads (a process forked
        # while another thread holds a lock can hang) and not at the first image
        pool.submit(_worker_ready).result()
        return FedPool(pool), _worker_call
    raise ValueError(f"executor={kind!r}: expected one of {EXECUTORS}")


@dataclass
class PendingImage:
    """An image between ``NavigationStream.add_image`` and its hand-over to the filter."""

    index: int
    t: float
    item: Any  # raw mosaic, path or bag message; None once dispatched
    sun_n: FloatArray
    future: Future[dict[str, Any]] | None = None
    row: dict[str, Any] | None = None  # the measurement, once known

    @property
    def dispatched(self) -> bool:
        return self.future is not None or self.row is not None

    @property
    def resolved(self) -> bool:
        return self.row is not None or (self.future is not None and self.future.done())


__all__ = [
    "EXECUTORS",
    "FedPool",
    "ImageMeasurer",
    "InlineExecutor",
    "PendingImage",
    "make_executor",
]
