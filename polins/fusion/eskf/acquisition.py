"""Robust start and recovery of the ESKF: the yaw acquired by consensus of the heading measurements, re-acquired after consecutive gate rejections, and the covariance inflated over an IMU gap.

A single heading fixes the yaw only if it is right: a first measurement 180 deg off used
to set the yaw with the measurement's small sigma, and the gate then rejected every good
heading after it. So the yaw is set only when the headings agree (docs/filter.md, "Yaw
acquisition and recovery"):

* every yaw / sun measurement gives the yaw rotation that zeroes its residual at the
  estimate of its time (:func:`~polins.fusion.acquisition.yaw_offset`); the gyro carries
  the estimate between them, so the offsets of measurements at different times compare
  directly (the offset does not change while the filter only propagates);
* :func:`~polins.fusion.acquisition.consensus` (shared with the graph): when at least
  ``acquire_k`` of the last ``acquire_n`` offsets agree within 3 sigma with one of them
  (the group's seed), their weighted mean sets the yaw, with the mean's sigma;
* after ``reacquire_after`` consecutive gate rejections of headings the rejected ones are
  candidates again: when ``acquire_k`` of the last ``acquire_n`` agree, the yaw is
  re-acquired from them (update reason and event ``re-acquired: N consecutive
  rejections``). Sporadic outliers (an accepted heading between them) never trigger it.

An IMU gap longer than ``max_gap_s`` is propagated across with the rates interpolated
linearly; the motion that the interpolation cannot see is covered by
:func:`~polins.fusion.faults.gap_variance`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from polins.fusion.acquisition import consensus, yaw_offset
from polins.fusion.eskf.alignment import rotate_yaw
from polins.fusion.eskf.blocks import Layout, inject_nav
from polins.fusion.faults import FusionEvent
from polins.fusion.items import MeasurementItem, UpdateRecord

FloatArray = NDArray[np.float64]

HELD = "held for the yaw acquisition"


@dataclass(frozen=True)
class Candidate:
    """A heading held for the acquisition: time [s], yaw offset and its 1-sigma [rad], its
    update record, its tilt gain [-] and the 1-sigma of its own noise [rad]
    (:func:`~polins.fusion.acquisition.yaw_offset`)."""

    t: float
    offset: float
    std: float
    record: UpdateRecord
    gain: FloatArray
    noise_std: float


@dataclass
class Acquisition:
    """The headings held for a (re-)acquisition of the yaw and the count of consecutive
    gate rejections (the configuration's ``acquire_k``, ``acquire_n``, ``reacquire_after``)."""

    k: int
    n: int
    after: int
    held: list[Candidate] = field(default_factory=list)
    rejections: int = 0  # consecutive gate rejections of headings (yaw aligned)

    def hold(self, candidate: Candidate) -> list[Candidate]:
        """Hold a heading; returns those that left the window of the last ``n``."""
        self.held.append(candidate)
        dropped, self.held = self.held[: -self.n], self.held[-self.n :]
        return dropped

    def found(self, aligned: bool) -> tuple[float, float, list[Candidate]] | None:
        """The consensus ``(offset, std, members)`` of the held headings, if there is one
        and it is due (aligned: after ``after`` consecutive rejections)."""
        if aligned and self.rejections < self.after:
            return None
        res = consensus(
            np.array([c.offset for c in self.held]), np.array([c.std for c in self.held]), self.k
        )
        if res is None:
            return None
        mean, std, members = res
        return mean, std, [self.held[i] for i in members.tolist()]

    def clear(self) -> None:
        """Forget the held headings and the rejection count (a heading was accepted)."""
        self.held = []
        self.rejections = 0


class Filter(Protocol):
    """What the acquisition uses of the filter (:class:`~polins.fusion.eskf.filter.ESKF`)."""

    acquisition: Acquisition
    records: list[UpdateRecord]
    events: list[FusionEvent]
    layout: Layout
    tilt_coupling: bool
    yaw_aligned: bool
    yaw_epoch: int
    x: FloatArray
    P: FloatArray
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: float
    lon: float
    alt_m: float

    def reject(self, item: MeasurementItem, reason: str) -> UpdateRecord: ...
    def reset(self) -> None: ...


def hold_heading(filt: Filter, item: MeasurementItem, rec: UpdateRecord | None) -> UpdateRecord:
    """Hold a heading for the yaw (re-)acquisition (``rec``: its gate rejection, None before
    the first acquisition) and (re-)acquire the yaw when the held headings agree
    (:meth:`Acquisition.found`): reset, turn the yaw by the consensus, amend the records.

    Returns
    -------
    UpdateRecord
        The heading's record.
    """
    mat = inject_nav(filt.mat_nb, filt.vel_n, filt.lat, filt.lon, filt.alt_m, filt.x[:9])[0]
    offset, std, gain = yaw_offset(item, mat, filt.vel_n, filt.tilt_coupling, filt.P[0:2, 0:2])
    rec = rec or filt.reject(item, HELD)
    acq, records = filt.acquisition, filt.records
    noise_std = item.std if item.kind == "yaw" else std
    for c in acq.hold(Candidate(item.t, offset, std, rec, gain, noise_std)):
        if c.record.reason == HELD:
            _amend(records, c.record, False, f"{HELD}: no consensus of {acq.k} in {acq.n}")
    found = acq.found(filt.yaw_aligned)
    if found is None:
        return rec
    delta, _, members = found
    # the weighted mean's error: -gain . dtheta (the tilt part is common to the members)
    # plus the mean of their own noises
    w = np.array([1.0 / c.std**2 for c in members])
    w /= w.sum()
    gain = w @ np.array([c.gain for c in members])
    noise_std = math.sqrt(float(np.sum((w * np.array([c.noise_std for c in members])) ** 2)))
    filt.reset()
    filt.mat_nb, filt.vel_n, filt.P = rotate_yaw(
        delta, noise_std, filt.mat_nb, filt.vel_n, filt.P, filt.layout, item.sun_n, gain
    )
    if filt.yaw_aligned:
        reason = f"re-acquired: {acq.rejections} consecutive rejections"
        detail = f"{reason}; yaw turned by {math.degrees(delta):.1f} deg"
        filt.events.append(FusionEvent(item.t, "yaw-reacquired", detail))
        _amend(records, rec, True, reason)
    else:
        for c in acq.held:
            used = c in members
            reason = f"used for the yaw acquisition ({len(members)} of {len(acq.held)} agree)"
            _amend(records, c.record, used, reason if used else f"{HELD}: disagrees")
    filt.yaw_aligned = True
    filt.yaw_epoch += 1
    acq.clear()
    return records[-1]


def _amend(records: list[UpdateRecord], rec: UpdateRecord, accepted: bool, reason: str) -> None:
    """Change the outcome of a held heading's update record ``rec`` (found from the end of
    ``records``; absent from the log of a copied filter: nothing to change)."""
    for i in range(len(records) - 1, -1, -1):
        if records[i] is rec:
            records[i] = dataclasses.replace(rec, accepted=accepted, reason=reason)
            return
