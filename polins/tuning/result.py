"""The result of a noise tuning: the tuned values, their identifiability, the innovations before and after, and its report."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import pandas as pd

from polins.fusion import FuseConfig, FusionResult
from polins.models import ImuModel
from polins.tuning.innovations import InnovationStats
from polins.tuning.parameters import IMU_PARAMS, OPTION_KIND


@dataclass(frozen=True, eq=False)
class TuneResult:
    """What :func:`tune` returns.

    Attributes
    ----------
    params : tuple of str
        The tuned parameters (:data:`PARAMETERS`).
    initial, estimate, values : dict of str to float
        Start values; the maximum-likelihood estimates (of every parameter, identifiable or
        not); the values of the tuned run (the estimate if identifiable or on its bound,
        else the start).
    cr_sigma_log : dict of str to float
        Cramér-Rao sigma of each parameter's natural logarithm (inf: no information): the
        precision under the filter's model.
    robust_sigma_log : dict of str to float
        The sandwich sigma of the same (:func:`sandwich_sigma`), honest when the model is
        wrong or the innovations are not white; at least the Cramér-Rao sigma.
    identifiable : dict of str to bool
        ``robust_sigma_log <= max_log_sigma`` and not on the search bound.
    at_bound : dict of str to int
        -1 / +1: the estimate is on the search's lower / upper bound (the log asks for a
        smaller / larger value); 0: inside.
    nll_before, nll_after : float
        Negative log-likelihood (ungated) at the start and at ``values``, both with the
        standstill detector held at the tuned values (the rest epochs of the tuned file).
    stats_before, stats_after : dict of str to InnovationStats
        Innovation statistics per kind with the start and the tuned values (gated as
        ``config``).
    config : FuseConfig
        The tuned configuration (its IMU model carries the tuned densities).
    measurements : DataFrame
        The measurements table (the tuned noise options act through ``config``).
    before, after : FusionResult
        The two runs the statistics come from.
    n_evaluations : int
        Filter runs spent on the likelihood.
    """

    params: tuple[str, ...]
    initial: dict[str, float]
    estimate: dict[str, float]
    values: dict[str, float]
    cr_sigma_log: dict[str, float]
    robust_sigma_log: dict[str, float]
    identifiable: dict[str, bool]
    at_bound: dict[str, int]
    nll_before: float
    nll_after: float
    stats_before: dict[str, InnovationStats]
    stats_after: dict[str, InnovationStats]
    config: FuseConfig
    measurements: pd.DataFrame
    before: FusionResult
    after: FusionResult
    n_evaluations: int

    def moved(self, p: str, n_sigma: float = 3.0) -> bool:
        """Whether an identified IMU term left its start by more than ``n_sigma`` robust
        sigmas: the innovations ask for another value than the model file's."""
        if p not in IMU_PARAMS or not self.identifiable[p]:
            return False
        step = abs(math.log(self.values[p] / self.initial[p]))
        return step > n_sigma * self.robust_sigma_log[p]

    def notes(self) -> list[str]:
        """What an identified value means when it moved far from the model file's."""
        tuned_kinds = {OPTION_KIND[p] for p in self.params if p in OPTION_KIND}
        if "gyro_arw" in self.params:
            tuned_kinds.add("zaru")  # the zero-rate sigma is the gyro's white noise
        untuned = [kind for kind, st in self.stats_before.items()
                   if not st.consistent and kind not in tuned_kinds]  # fmt: skip
        out = []
        for p in self.params:
            if not self.moved(p):
                continue
            ratio = self.values[p] / self.initial[p]
            note = (
                f"{p} moved x{ratio:.3g} from the start, beyond its interval: the interval is "
                "the log's precision, not the sensor's truth. Either the start (the model "
                "file) is wrong (compare with polins imu-model on a static record), or the "
                "filter lacks an error source (vibration, an unfused aiding, mounting, scale "
                "factors) or holds a sigma far from the log's, that this term now absorbs: the "
                "tuned value is then an effective one for this vehicle"
            )
            if untuned:
                note += (f"; the {', '.join(untuned)} updates are inconsistent and their sigmas "
                         "were not tuned: tune them with it (polins tune --params auto)")  # fmt: skip
            out.append(note)
        return out

    def fuse_options(self) -> dict[str, float]:
        """The tuned measurement-noise values, as ``polins fuse --set`` / ``[filter]`` options."""
        return {p: self.values[p] for p in self.params if p not in IMU_PARAMS}

    def tuned_model(self, options: Mapping[str, Any] | None = None, **fields: Any) -> ImuModel:
        """The tuned file's model: the tuned IMU terms, and a ``filter_options`` table of
        ``options`` (the other options the tuned filter ran with) and the tuned noise
        options; ``fields`` replace others (``name``, ``description``). Every
        configuration built with it runs the tuned filter (``polins fuse --imu``)."""
        table = {**dict(self.config.imu.filter_options), **(options or {}),
                 **self.fuse_options()}  # fmt: skip
        return dataclasses.replace(self.config.imu, filter_options=tuple(table.items()), **fields)

    def _identified_word(self, p: str) -> str:
        """The report's identifiability column of ``p``."""
        if not self.identifiable[p]:
            return "no: " + self._not_identified(p)
        return "yes, an effective value (note)" if self.moved(p) else "yes"

    def _not_identified(self, p: str) -> str:
        """Why a parameter is not identified, and the value it takes."""
        if self.at_bound[p]:
            side = "smaller" if self.at_bound[p] < 0 else "larger"
            return f"on the search bound, the log asks for a {side} value"
        return "kept at start"

    @property
    def unidentifiable(self) -> list[str]:
        """The parameters the log cannot identify (kept at their start values)."""
        return [p for p in self.params if not self.identifiable[p]]

    def comment_lines(self) -> list[str]:
        """The tuning as comment lines of a tuned IMU model file (``polins tune --out``)."""
        lines = ["tuned by maximum likelihood of the filter's innovations (polins.tuning.tune):"]
        for p in self.params:
            state = (f"identified, x/÷ {math.exp(self.robust_sigma_log[p]):.3g}"
                     if self.identifiable[p] else self._not_identified(p))  # fmt: skip
            where = "" if p in IMU_PARAMS else f"; [filter] option of the {OPTION_KIND[p]} updates"
            lines.append(f"  {p} = {self.values[p]:.6g} (start {self.initial[p]:.6g}; {state}"
                         f"{where})")  # fmt: skip
        lines += [f"  note: {n}" for n in self.notes()]
        for kind, st in self.stats_after.items():
            lines.append(f"  {kind}: mean NIS {st.nis_mean:.3g} in {st.nis_band[0]:.3g} .. "
                         f"{st.nis_band[1]:.3g} ({st.verdict})")  # fmt: skip
        return lines

    def report(self) -> str:
        """A few lines: per parameter start -> tuned (CR sigma), then NIS before/after."""
        lines = ["parameter        start        tuned        x/÷ CR   robust  identifiable"]
        for p in self.params:
            cr, robust = (_factor(s[p]) for s in (self.cr_sigma_log, self.robust_sigma_log))
            lines.append(
                f"{p:<16} {self.initial[p]:<12.4g} {self.values[p]:<12.4g} {cr:<8} "
                f"{robust:<7} {self._identified_word(p)}"
            )
        lines += [f"note: {n}" for n in self.notes()]
        lines.append(f"negative log-likelihood {self.nll_before:.1f} -> {self.nll_after:.1f}")
        for kind, after in self.stats_after.items():
            b = self.stats_before.get(kind)
            start = f"{b.nis_mean:.3g} ({b.verdict})" if b else "-"
            lines.append(
                f"{kind} NIS mean {start} -> {after.nis_mean:.3g} ({after.verdict}); "
                f"band {after.nis_band[0]:.3g} .. {after.nis_band[1]:.3g} from "
                f"{after.n_eff:.0f} independent of {after.n}; lag-1 autocorr "
                f"{after.autocorr[0] if after.autocorr.size else math.nan:.3f} "
                f"(white within ±{after.autocorr_band:.3f})"
            )
            if after.cause:
                lines.append(f"  likely cause: {after.cause}")
        return "\n".join(lines)


def _factor(sigma_log: float) -> str:
    """A log-space sigma as its factor ``x/÷ exp(sigma)``."""
    return f"{math.exp(sigma_log):.3g}" if sigma_log < math.log(1e3) else "> 1000"


__all__ = ["TuneResult"]
