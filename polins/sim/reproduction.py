"""Simulated turntable runs of the paper's Section 4.1, each image measured with every estimator.

Setup (paper Table 1 and Section 4.1, ambiguities resolved as in docs/model.md §11): the
Table 1 camera (``models/cameras/paper-table1.toml``: gains beta_k = [1.0269, 1.0, 1.038,
1.005], eta_k = 1, ideal angles, Table 1 fisheye), the sun at the paper's site
(:data:`polins.site.PAPER_SITE`, Harbin) on 2023-09-05 15:06 +08:00 from the ephemeris
(azimuth 247.0 deg, zenith 60.2 deg), a single-scattering Rayleigh sky with I_in = 220 DN and
d_max = 0.75, the direct-sunlight term with epsilon = 0.0125 (the paper's k_m = 0.05 in its
Eq. 12), Gaussian noise sigma = 1.5 DN per pixel, a level sensor turning 720 deg in 100 s
about the vertical, and a prior heading = truth + N(0, 0.5 deg).

Every image is measured with each of the estimators in :data:`ESTIMATORS`: the operational
methods of ``polins.measure`` and the paper's Algorithm 1
(:func:`polins.sim.algorithm1.measure_algorithm1`). :data:`PAPER_OCCLUDER` (a world-fixed tree
line, azimuth 260-350 deg, elevation < 40 deg, docs/model.md §12.6) breaks the symmetry of
the level geometry, in which the direct-sunlight term cannot bias the heading.
:mod:`polins.sim.paper` turns the results into the ``polins demo`` report.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.compass.camera import fov_mask, pixel_rays_c
from polins.compass.crlb import yaw_crlb
from polins.compass.measure import Measurement, measure
from polins.errors import UserInputError
from polins.frames import heading_deg_from_yaw, rot_nb_from_euler, wrap_angle
from polins.models import CameraModel, load_camera
from polins.sim.algorithm1 import measure_algorithm1, measure_baseline
from polins.sim.render import azimuth_band, occluded, render_raw
from polins.site import PAPER_SITE
from polins.sky.ephemeris import sun_position, sun_vector_n
from polins.sky.scattering import rayleigh_dop

FloatArray = NDArray[np.float64]

PAPER_EPOCH = "2023-09-05T15:06+08:00"
PAPER_TRADITIONAL_RMSE_DEG = 0.5928
PAPER_PROPOSED_RMSE_DEG = 0.0240

# Table 3 of the paper: outdoor sessions on 2023-09-05 near Harbin (local time +08:00) and
# the reported heading error (RMSE / std) [deg] of the traditional and proposed methods.
TABLE3_SESSIONS: tuple[tuple[str, float, float], ...] = (
    ("11:33", 1.4931, 0.7905),
    ("12:18", 1.3902, 0.8700),
    ("12:56", 1.0988, 0.6574),
    ("13:29", 0.7302, 0.4983),
    ("15:07", 0.3546, 0.2590),
    ("16:29", 0.2418, 0.1843),
)


# docs/model.md §12.6, docs/errata.md §3: a world-fixed occluder (tree line) over azimuths
# 260..350 deg of the ENU directions, measured like the solar azimuth (clockwise from North:
# West to North), below 40 deg elevation. The sun (azimuth 247 deg, elevation 30 deg) stays
# visible just south of it. (Read as counter-clockwise from East, i.e. compass 100..190 deg,
# the bias would be +0.03 deg instead of the -0.1 deg that docs/model.md §12.6 quotes.)
PAPER_OCCLUDER: FloatArray = azimuth_band(260.0, 350.0, elevation_max_deg=40.0)
# The tree line is a dark silhouette (2% of the sky radiance, below the estimator's S0 floor),
# so that the estimators drop it and the bias isolates the sunlight term. (Brighter
# unpolarized occluders leak noise-polarized pixels through the DoP threshold and bias
# the equal-weight SVD on their own.)
OCCLUDER_RADIANCE_FRACTION = 0.02


@dataclass(frozen=True)
class Estimator:
    """One heading estimator of the reproduction: a ``polins.measure`` method and options.

    Attributes
    ----------
    key : str
        Short column name.
    label : str
        Row label of the table.
    method : str
        "traditional" or "compensated" (``polins.measure``; "traditional" with the
        ``gain_correction`` or ``weighted`` switch: :func:`polins.sim.algorithm1.measure_baseline`),
        or "paper" (:func:`polins.sim.algorithm1.measure_algorithm1`, which takes
        ``weighted`` too); a switch the method does not take is refused
        (:class:`polins.errors.UserInputError`).
    options : tuple of (name, value)
        Keyword options: ``MeasureOptions`` fields and the switches of those functions.
    paper_role : str
        What the row stands for in the paper's comparison.
    """

    key: str
    label: str
    method: str
    options: tuple[tuple[str, Any], ...] = ()
    paper_role: str = ""

    def __post_init__(self) -> None:
        switches = {"traditional": {"gain_correction", "weighted"}, "paper": {"weighted"}}
        baseline = {"gain_correction", "weighted"} & dict(self.options).keys()
        wrong = sorted(baseline - switches.get(self.method, set()))
        if wrong:
            raise UserInputError(
                f"Estimator {self.key!r}: {', '.join(wrong)} is no switch of "
                f"method={self.method!r} (measure_baseline takes it with 'traditional')"
            )


ESTIMATORS: tuple[Estimator, ...] = (
    Estimator(
        "trad_nogain",
        "traditional, no gain correction",
        "traditional",
        (("gain_correction", False), ("weighted", False)),
        "the paper's 'traditional' (reported 0.5928 deg)",
    ),
    Estimator(
        "trad",
        "traditional, gain-corrected",
        "traditional",
        (("weighted", False),),
        "paper Eq. 14 + SVD done right",
    ),
    Estimator(
        "trad_weighted",
        "traditional, gain-corrected, p^2-weighted",
        "traditional",
        (),
        "docs/model.md §9.1 recommended weights",
    ),
    Estimator(
        "paper_printed",
        "paper Alg. 1, Eq. 22 as printed",
        "paper",
        (("eq22", "printed"), ("weighted", False)),
        "k_m ~ 150: compensation swamps the sky",
    ),
    Estimator(
        "paper_raw",
        "paper Alg. 1, scale-consistent, Eq. 23 on raw I",
        "paper",
        (("eq22", "scale-consistent"), ("gain_final", False), ("weighted", False)),
        "literal Eq. 23: beta never reaches the AoP",
    ),
    Estimator(
        "paper",
        "paper Alg. 1, scale-consistent, beta applied",
        "paper",
        (("eq22", "scale-consistent"), ("gain_final", True), ("weighted", False)),
        "the paper's 'proposed' (reported 0.0240 deg)",
    ),
    Estimator(
        "compensated",
        "compensated (joint ML sun + epsilon)",
        "compensated",
        (),
        "docs/model.md §9.2, this library's default",
    ),
)


def _measure(
    est: Estimator, raw: NDArray, cam: CameraModel, sun_n: NDArray, rot_prior: Rotation
) -> Measurement:
    """One image measured by the estimator ``est``."""
    options = dict(est.options)
    if est.method == "paper":
        return measure_algorithm1(raw, cam, sun_n=sun_n, rot_nb_prior=rot_prior, **options)[0]
    if {"gain_correction", "weighted"} & options.keys():  # the paper's baselines
        return measure_baseline(raw, cam, sun_n=sun_n, rot_nb_prior=rot_prior, **options)
    return measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot_prior, method=est.method, **options)


@dataclass(frozen=True)
class Scenario:
    """Configuration of one simulated turntable run (defaults: the paper's Section 4.1).

    ``downscale`` images the same lens at ``1/downscale`` resolution (``cam.downscaled``):
    noise-limited errors then grow by about ``downscale`` (1/sqrt(N)), while biases from
    gains or the sunlight term do not change.
    """

    name: str = "paper Sec. 4.1"
    camera: str = "paper-table1"
    downscale: int = 1
    start: str = PAPER_EPOCH
    lat_deg: float = PAPER_SITE.lat_deg
    lon_deg: float = PAPER_SITE.lon_deg
    alt_m: float = PAPER_SITE.alt_m
    duration_s: float = 100.0
    turn_deg: float = 720.0
    n_images: int = 100
    dop_max: float = 0.75
    radiance: float = 220.0
    epsilon: float = 0.0125
    noise_std: float = 1.5
    prior_std_deg: float = 0.5
    occluders: tuple[FloatArray, ...] = ()
    render_options: tuple[tuple[str, Any], ...] = ()
    seed: int = 0

    def with_changes(self, **changes: Any) -> Scenario:
        """A copy with some fields replaced."""
        return replace(self, **changes)


@dataclass
class Reproduction:
    """Results of :func:`run_scenario`: per-image errors and the summary table."""

    scenario: Scenario
    images: pd.DataFrame  # one row per (image, estimator)
    summary: pd.DataFrame  # one row per estimator
    crlb_deg: float  # Cramer-Rao bound of heading [deg] at the first image
    sun_azimuth_deg: float
    sun_zenith_deg: float
    n_pixels: int  # valid superpixels of the compensated estimator (median)
    render_ms: float  # median time per rendered image
    timings_ms: dict[str, float] = field(default_factory=dict)  # median per estimator

    def rmse_deg(self, key: str) -> float:
        """Heading RMSE [deg] of the estimator ``key`` (NaN if it did not run)."""
        row = self.summary[self.summary["key"] == key]
        return float(row["rmse_deg"].iloc[0]) if len(row) else np.nan

    def mean_deg(self, key: str) -> float:
        """Mean heading error (bias) [deg] of the estimator ``key`` (NaN if it did not run)."""
        row = self.summary[self.summary["key"] == key]
        return float(row["mean_deg"].iloc[0]) if len(row) else np.nan


def scenario_camera(scenario: Scenario) -> CameraModel:
    """The scenario's camera model at its resolution."""
    cam = load_camera(scenario.camera)
    return cam.downscaled(scenario.downscale) if scenario.downscale > 1 else cam


def turntable_poses(scenario: Scenario) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Image times [s], true yaw [rad] and ENU sun vectors ``(N, 3)`` of a level turntable
    turning ``turn_deg`` in ``duration_s`` (images at ``k duration / N``)."""
    if scenario.n_images < 1:
        raise ValueError(f"n_images={scenario.n_images} must be >= 1")
    t = scenario.duration_s * np.arange(scenario.n_images) / scenario.n_images
    yaw = wrap_angle(np.radians(scenario.turn_deg) * t / scenario.duration_s)
    times = pd.Timestamp(scenario.start) + pd.to_timedelta(t, unit="s")
    sun = sun_position(pd.DatetimeIndex(times), scenario.lat_deg, scenario.lon_deg, scenario.alt_m)
    return t, yaw, sun_vector_n(sun.azimuth, sun.zenith)


def heading_error_deg(yaw_measured: Any, yaw_true: Any) -> FloatArray:
    """Compass-heading error [deg] (measured - true, wrapped to (-180, 180])."""
    h = heading_deg_from_yaw(yaw_measured) - heading_deg_from_yaw(yaw_true)
    return np.degrees(wrap_angle(np.radians(h)))


def run_scenario(
    scenario: Scenario,
    estimators: Sequence[Estimator] = ESTIMATORS,
    *,
    progress: bool = False,
) -> Reproduction:
    """Render the scenario's images and measure each with every estimator.

    Parameters
    ----------
    scenario : Scenario
        The simulated run.
    estimators : sequence of Estimator
        Methods to compare.
    progress : bool
        Show a tqdm progress bar over the images.
    """
    cam = scenario_camera(scenario)
    rng = np.random.default_rng(scenario.seed)
    t, yaw, sun_n = turntable_poses(scenario)
    render_kw = dict(scenario.render_options)
    rows: list[dict[str, Any]] = []
    render_s: list[float] = []
    measure_s: dict[str, list[float]] = {e.key: [] for e in estimators}
    n_pix: list[int] = []
    iterator: Iterable[int] = range(len(t))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"{scenario.name}", unit="image", leave=False)
    prior_std = np.radians(scenario.prior_std_deg)
    for k in iterator:
        rot_nb = rot_nb_from_euler(yaw[k], 0.0, 0.0)
        tic = time.perf_counter()
        raw = render_raw(
            cam,
            sun_n[k],
            rot_nb,
            dop_max=scenario.dop_max,
            radiance=scenario.radiance,
            epsilon=scenario.epsilon,
            noise_std=scenario.noise_std,
            rng=rng,
            occluders=scenario.occluders,
            **render_kw,
        )
        render_s.append(time.perf_counter() - tic)
        yaw_prior = yaw[k] + prior_std * rng.standard_normal()
        rot_prior = rot_nb_from_euler(yaw_prior, 0.0, 0.0)
        for est in estimators:
            tic = time.perf_counter()
            m = _measure(est, raw, cam, sun_n[k], rot_prior)
            measure_s[est.key].append(time.perf_counter() - tic)
            if est.method == "compensated" and m.ok:
                n_pix.append(int(m.n_pixels))
            rows.append(
                {
                    "image": k,
                    "t": t[k],
                    "estimator": est.key,
                    "heading_true_deg": float(heading_deg_from_yaw(yaw[k])),
                    "heading_prior_deg": float(heading_deg_from_yaw(yaw_prior)),
                    "heading_deg": float(m.heading_deg),
                    "error_deg": float(heading_error_deg(m.yaw, yaw[k])) if m.ok else np.nan,
                    "yaw_std_meas_deg": float(np.degrees(m.yaw_std_meas)),
                    "epsilon": float(m.epsilon),
                    "ok": bool(m.ok),
                    "reason": m.reason,
                }
            )
    images = pd.DataFrame(rows)
    crlb = heading_crlb_deg(cam, sun_n[0], yaw[0], scenario)
    sun0 = sun_position(scenario.start, scenario.lat_deg, scenario.lon_deg, scenario.alt_m)
    return Reproduction(
        scenario=scenario,
        images=images,
        summary=summarize(images, estimators),
        crlb_deg=crlb,
        sun_azimuth_deg=float(np.degrees(sun0.azimuth)),
        sun_zenith_deg=float(np.degrees(sun0.zenith)),
        n_pixels=int(np.median(n_pix)) if n_pix else 0,
        render_ms=1e3 * float(np.median(render_s)),
        timings_ms={key: 1e3 * float(np.median(v)) for key, v in measure_s.items()},
    )


def heading_crlb_deg(cam: CameraModel, sun_n: FloatArray, yaw: float, scenario: Scenario) -> float:
    """Cramer-Rao bound [deg] of the heading of one level image
    (:func:`polins.compass.crlb.yaw_crlb`, docs/errata.md §5) over the pixels the estimator
    uses: field of view, 10 deg sun exclusion, DoP >= 0.03, and not behind the scenario's
    occluders. 0 for noise-free scenarios."""
    if scenario.noise_std == 0:
        return 0.0
    rot_nb = rot_nb_from_euler(yaw, 0.0, 0.0)
    rays_n = pixel_rays_c(cam) @ rot_nb.as_matrix().T
    with np.errstate(invalid="ignore"):
        mask = (
            fov_mask(cam)
            & (rays_n @ sun_n <= np.cos(np.radians(10.0)))
            & (rayleigh_dop(sun_n, rays_n, scenario.dop_max) >= 0.03)
            & ~occluded(rays_n, scenario.occluders)
        )
    crlb = yaw_crlb(
        cam,
        sun_n,
        rot_nb,
        dop_max=scenario.dop_max,
        radiance=scenario.radiance,
        noise_std=scenario.noise_std,
        epsilon=scenario.epsilon,
        pixel_mask=mask,
    )
    return float(np.degrees(crlb))


def summarize(images: pd.DataFrame, estimators: Sequence[Estimator] = ESTIMATORS) -> pd.DataFrame:
    """Heading-error statistics [deg] per estimator: RMSE, mean (bias), sd, max |error|,
    and the number of images measured (ok) out of all."""
    rows = []
    for est in estimators:
        sel = images[images["estimator"] == est.key]
        err = sel["error_deg"].to_numpy(dtype=float)
        good = err[np.isfinite(err)]
        rows.append(
            {
                "key": est.key,
                "estimator": est.label,
                "rmse_deg": float(np.sqrt(np.mean(good**2))) if good.size else np.nan,
                "mean_deg": float(np.mean(good)) if good.size else np.nan,
                "sd_deg": float(np.std(good)) if good.size else np.nan,
                "max_abs_deg": float(np.max(np.abs(good))) if good.size else np.nan,
                "n_ok": int(good.size),
                "n": len(sel),
                "paper_role": est.paper_role,
            }
        )
    return pd.DataFrame(rows)


def gain_pseudo_polarization(cam: CameraModel) -> float:
    """Relative camera-fixed pseudo-polarization of uncorrected channel gains,
    ``|(g_0 - g_90, g_45 - g_135)| / (2 mean g)`` (docs/errata.md §3: about 0.006 for
    Table 1)."""
    g = cam.gain
    idx = {round(a): k for k, a in enumerate(cam.nominal_angle_deg)}
    d1 = g[idx[0]] - g[idx[90]]
    d2 = g[idx[45]] - g[idx[135]]
    return float(np.hypot(d1, d2) / (2.0 * np.mean(g)))


def paper_scenarios(
    *, downscale: int = 1, n_images: int = 100, seed: int = 0
) -> tuple[Scenario, Scenario]:
    """The paper's Section 4.1 scenario and its world-fixed-occluder variant (docs/model.md
    §12.6)."""
    paper = Scenario(downscale=downscale, n_images=n_images, seed=seed)
    occ = paper.with_changes(
        name="paper Sec. 4.1 + world-fixed occluder",
        occluders=(PAPER_OCCLUDER,),
        render_options=(("ground_radiance", OCCLUDER_RADIANCE_FRACTION * paper.radiance),),
        seed=seed + 1,
    )
    return paper, occ


def session_scenarios(
    *, downscale: int = 1, n_images: int = 100, seed: int = 0, **changes: Any
) -> list[Scenario]:
    """The six outdoor sessions of the paper's Table 3 (Harbin, 2023-09-05, +08:00) as
    turntable simulations with the Section 4.1 sensor."""
    return [
        Scenario(
            name=f"session {i + 1} ({hhmm})",
            start=f"2023-09-05T{hhmm}+08:00",
            downscale=downscale,
            n_images=n_images,
            seed=seed + i,
        ).with_changes(**changes)
        for i, (hhmm, _, _) in enumerate(TABLE3_SESSIONS)
    ]


__all__ = [
    "ESTIMATORS",
    "OCCLUDER_RADIANCE_FRACTION",
    "PAPER_EPOCH",
    "PAPER_OCCLUDER",
    "PAPER_PROPOSED_RMSE_DEG",
    "PAPER_TRADITIONAL_RMSE_DEG",
    "TABLE3_SESSIONS",
    "Estimator",
    "Reproduction",
    "Scenario",
    "gain_pseudo_polarization",
    "heading_crlb_deg",
    "heading_error_deg",
    "paper_scenarios",
    "run_scenario",
    "scenario_camera",
    "session_scenarios",
    "summarize",
    "turntable_poses",
]
