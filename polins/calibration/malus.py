"""Malus-law fit: channel gains, efficiencies and angles from a polarization turning in the image.

Both the rotating-polarizer and the sky-rotation calibrations observe, image after image,
sources whose linear polarization turns in the image plane by an angle ``theta_j`` (the
polarizer's angle; minus the camera's turn about its axis). Channel ``k`` of source ``r``
in image ``j`` reads, dark offset subtracted (docs/model.md §6.2)::

    y_jrk = s_j g_k / 2 [S0_r + eta_k Re(L_r exp(2i theta_j) exp(-2i alpha_k))]

with ``L_r = S1_r + i S2_r`` the source's linear polarization at ``theta = 0`` and ``s_j``
the image's exposure scale. :func:`fit_turning_polarization` fits it by nonlinear least
squares (``scipy.optimize.least_squares``). What cannot be identified is fixed by
construction, as docs/calibrate.md states:

* the common gain (it trades against ``s_j S0_r``): the fitted gains keep the base
  camera's mean gain;
* with unknown turns or unknown sources, the common angle offset (it trades against
  ``theta_j``, or against the phase of every ``L_r``): the transmission angles keep the
  base camera's mean offset from the nominal labels;
* with unknown sources, the common efficiency (it trades against the DoP of the sources):
  the efficiencies keep the base camera's largest efficiency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from polins.calibration.images import zero_sum_basis
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

GAUGE_WEIGHT = 1e4  # weight of the residuals that fix the flat directions of the tilt terms

__all__ = ["TurnFit", "base_stokes", "fit_turning_polarization"]


@dataclass(frozen=True)
class TurnFit:
    """Result of :func:`fit_turning_polarization`, in the conventions of the module docstring.

    Attributes
    ----------
    gain, gain_std : (4,)
        Channel gains g_k [-] and standard errors.
    efficiency, efficiency_std : (4,)
        Channel efficiencies eta_k [-] and standard errors.
    angle, angle_std : (4,)
        Transmission angles alpha_k [rad] and standard errors.
    turn, turn_std : (m,)
        Turn angles theta_j of the polarization in the image [rad] (given or fitted).
    scale : (m,)
        Exposure scales s_j [-] (first image 1 when the sources are fitted).
    sources : (R, 3)
        Source Stokes vectors (S0, S1, S2) at theta = 0 [DN].
    residuals : (m, R, 4)
        Data minus model [DN].
    chi2_dof : float
        Sum of squared normalised residuals per degree of freedom (about 1 when the model
        and the declared noise hold).
    converged : bool
        The least-squares fit met its tolerance within ``max_iterations``.
    """

    gain: FloatArray
    gain_std: FloatArray
    efficiency: FloatArray
    efficiency_std: FloatArray
    angle: FloatArray
    angle_std: FloatArray
    turn: FloatArray
    turn_std: FloatArray
    scale: FloatArray
    sources: FloatArray
    residuals: FloatArray
    chi2_dof: float
    converged: bool = True


def base_stokes(y: ArrayLike, cam: CameraModel) -> FloatArray:
    """Least-squares Stokes ``(..., 3)`` [DN] of dark-subtracted channels ``(..., 4)`` under the
    base camera's gains, efficiencies and angles (docs/model.md §7.2)."""
    two_a = 2.0 * cam.transmission_angle
    a = (
        0.5
        * cam.gain[:, None]
        * np.stack([np.ones(4), cam.efficiency * np.cos(two_a), cam.efficiency * np.sin(two_a)], -1)
    )
    return np.asarray(y, dtype=float) @ np.linalg.pinv(a).T


def fit_turning_polarization(
    y: ArrayLike,
    sigma: ArrayLike,
    cam: CameraModel,
    *,
    turn: ArrayLike | None = None,
    sources: ArrayLike | None = None,
    constant_scale: bool = False,
    tilt_terms: bool = False,
    turn_start: ArrayLike | None = None,
    turn_prior_std: float | None = None,
    source_factors: ArrayLike | None = None,
    max_iterations: int | None = None,
) -> TurnFit:
    """Fit channel gains, efficiencies and angles to turning polarized sources.

    Parameters
    ----------
    y : array_like, (m, R, 4)
        Dark-subtracted channel means [DN] of R sources in m images.
    sigma : array_like, broadcastable to (m, R, 4)
        Noise standard deviation of ``y`` [DN].
    cam : CameraModel
        Base camera: starting values and the conventions for the unidentifiable parts.
    turn : array_like, (m,), optional
        Known turn angles theta_j [rad]; fitted when None (the first image's is 0 when the
        sources are fitted too).
    sources : array_like, (R, 3), optional
        Known source Stokes vectors up to a common scale; fitted when None.
    constant_scale : bool
        One exposure scale for all images (a stable source). Needed with known, fully
        polarized sources and fitted turns: there, the per-image scales and turns trade
        against the channel parameters (a Lorentz boost of (S0, S1, S2) keeps the light cone).
    tilt_terms : bool
        Let each fitted source also change with the turn at the first harmonic in S0
        (``Re(b_r exp(i theta_j))``) and at the first and third in L
        (``d_r exp(i theta_j) + e_r exp(3i theta_j)``): the first-order effect of a turn axis
        tilted from the optical axis. The channel errors show at other harmonics (S0 at the
        second, L at 0 and -2), so they stay identifiable.
    turn_start : array_like, (m,), optional
        Start values of the fitted turns [rad] (default: from the polarization, modulo pi;
        the tilt terms need them modulo 2 pi).
    turn_prior_std : float, optional
        Standard deviation [rad] of a prior tying the fitted turns to their start values.
        With the tilt terms, turns that wobble as ``Re(c exp(i theta_j))`` trade exactly
        against the first and third harmonics (a tilted axis makes the apparent turn
        uneven); the prior fixes that flat direction, which the channel parameters do not
        depend on. (The same holds for exposure scales wobbling at the first harmonic: with
        the tilt terms their first harmonic is set to zero.)
    source_factors : array_like, (m, R) complex, optional
        Known change of each source's linear polarization from image to image:
        ``L_r`` becomes ``L_r f_jr`` in image j (a sky that changes as the sun moves;
        :func:`polins.calibration.sky_rotation.sun_motion_factors`). Default 1.
    max_iterations : int, optional
        Stop after about this many Levenberg-Marquardt iterations (each one Jacobian);
        ``converged`` says whether it met its tolerance. None: scipy's default.

    Returns
    -------
    TurnFit
    """
    y_arr = np.asarray(y, dtype=float)
    m, n_src, _ = y_arr.shape
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), y_arr.shape)
    q = zero_sum_basis(4)
    fit_turn, fit_src = turn is None, sources is None
    stokes0 = base_stokes(y_arr, cam)  # (m, R, 3)
    lin0 = stokes0[..., 1] + 1j * stokes0[..., 2]
    if fit_src:
        ref_s0, ref_lin = stokes0[0, :, 0], lin0[0]
    else:
        src = np.asarray(sources, dtype=float).reshape(n_src, 3)
        ref_s0, ref_lin = src[:, 0], src[:, 1] + 1j * src[:, 2]
    theta0 = (
        0.5 * np.angle((lin0 * np.conj(ref_lin)).sum(axis=1))
        if fit_turn
        else np.asarray(turn, dtype=float)
    )
    if fit_turn and turn_start is not None:
        theta0 = (
            np.asarray(turn_start, dtype=float)
            - float(np.asarray(turn_start, dtype=float)[0]) * fit_src
        )
    s0_scale = stokes0[..., 0].sum(axis=1) / ref_s0.sum()
    if fit_src:
        s0_scale = s0_scale / s0_scale[0]
        rot = np.exp(-2j * theta0)[:, None]
        src_s0 = (stokes0[..., 0] / s0_scale[:, None]).mean(axis=0)
        src_lin = (lin0 * rot / s0_scale[:, None]).mean(axis=0)

    # Parameter vector: log-gain (3) | efficiency (3 log, relative; or 4 log) | angle offsets
    # (3 relative or 4) | log scale (m - 1 or m) | turns (m - 1 or m, when fitted) | sources.
    n_eta = 3 if fit_src else 4
    n_alpha = 3 if (fit_turn or fit_src) else 4  # fitted sources take a common angle too
    n_scale = 1 if constant_scale else (m - 1 if fit_src else m)
    if constant_scale and fit_src:
        raise ValueError("constant_scale needs known sources")
    n_turn = (m - 1 if fit_src else m) if fit_turn else 0
    if tilt_terms and not fit_src:
        raise ValueError("tilt_terms needs fitted sources")
    n_tilt = 6 * n_src if tilt_terms else 0
    sizes = [3, n_eta, n_alpha, n_scale, n_turn, 3 * n_src if fit_src else 0, n_tilt]
    cuts = np.cumsum(sizes)[:-1]
    log_eta_base = np.log(cam.efficiency)

    def unpack(x: FloatArray) -> tuple[FloatArray, ...]:
        a, b, d, ls, th, sv, _ = np.split(x, cuts)
        gain = np.exp(q @ a)
        eta = np.exp(log_eta_base - log_eta_base.mean() + q @ b) if fit_src else np.exp(b)
        alpha = cam.transmission_angle + (q @ d if n_alpha == 3 else d)
        if constant_scale:
            scale = np.full(m, np.exp(ls[0]))
        else:
            scale = np.exp(np.concatenate([[0.0], ls]) if fit_src else ls)
        theta = (np.concatenate([[0.0], th]) if fit_src else th) if fit_turn else theta0
        if fit_src:
            s0r, lr = sv[:n_src], sv[n_src : 2 * n_src] + 1j * sv[2 * n_src :]
        else:
            s0r, lr = ref_s0, ref_lin
        return gain, eta, alpha, scale, theta, s0r, lr

    factors = (
        np.ones((m, n_src), dtype=complex)
        if source_factors is None
        else np.broadcast_to(np.asarray(source_factors, dtype=complex), (m, n_src))
    )

    def model(x: FloatArray) -> FloatArray:
        gain, eta, alpha, scale, theta, s0r, lr = unpack(x)
        turn_1 = np.exp(1j * theta)[:, None]  # (m, 1)
        lin = lr[None, :] * factors * turn_1**2  # (m, R)
        s0 = np.broadcast_to(s0r[None, :], lin.shape)
        if tilt_terms:
            tb = x[cuts[-1] :].reshape(6, n_src)
            s0 = s0 + ((tb[0] + 1j * tb[1]) * turn_1).real
            lin = lin + (tb[2] + 1j * tb[3]) * turn_1 + (tb[4] + 1j * tb[5]) * turn_1**3
        pol = (lin[..., None] * np.exp(-2j * alpha)).real  # (m, R, 4)
        return 0.5 * scale[:, None, None] * gain * (s0[..., None] + eta * pol)

    def residual(x: FloatArray) -> FloatArray:
        r = ((model(x) - y_arr) / sig).ravel()
        _, _, _, scale, theta, _, _ = unpack(x)
        extra = []
        if turn_prior_std is not None and fit_turn:
            extra.append((theta - theta0) / turn_prior_std)
        if tilt_terms:
            # Exposure scales that wobble as 1 + Re(c exp(i theta_j)) trade exactly against
            # the tilt terms too: fix that flat direction (the channels do not depend on it).
            wobble = np.sum(np.log(scale) * np.exp(1j * theta)) / m * GAUGE_WEIGHT
            extra.append(np.array([wobble.real, wobble.imag]))
        return np.concatenate([r, *extra]) if extra else r

    x0 = np.concatenate(
        [
            np.zeros(3),
            np.zeros(3) if fit_src else log_eta_base,
            np.zeros(n_alpha),
            np.log(np.maximum(s0_scale[1:] if fit_src else s0_scale, 1e-9))
            if not constant_scale
            else np.log([max(float(np.mean(s0_scale)), 1e-9)]),
            (theta0[1:] if fit_src else theta0) if fit_turn else np.zeros(0),
            np.concatenate([src_s0, src_lin.real, src_lin.imag]) if fit_src else np.zeros(0),
            np.zeros(n_tilt),
        ]
    )
    if y_arr.size <= x0.size:
        raise UserInputError(
            f"Malus fit: {y_arr.size} channel means cannot fix {x0.size} unknowns; add images"
        )
    max_nfev = None if max_iterations is None else max_iterations * (x0.size + 1)
    sol = least_squares(residual, x0, method="lm", x_scale="jac", max_nfev=max_nfev)
    gain, eta, alpha, scale, theta, s0r, lr = unpack(sol.x)
    dof = y_arr.size - x0.size
    chi2_dof = float(np.sum(sol.fun[: y_arr.size] ** 2) / dof)
    jac = sol.jac
    cov = np.linalg.pinv(jac.T @ jac) * max(chi2_dof, 1e-12)
    blocks = np.split(np.arange(x0.size), cuts)

    def std_of(jac_block: FloatArray, idx: NDArray[np.int_]) -> FloatArray:
        c = cov[np.ix_(idx, idx)]
        return np.sqrt(np.maximum(np.diag(jac_block @ c @ jac_block.T), 0.0))

    gain_std = gain * std_of(q, blocks[0])
    eta_std = eta * std_of(q if fit_src else np.eye(4), blocks[1])
    alpha_std = std_of(q if n_alpha == 3 else np.eye(4), blocks[2])
    turn_std = np.zeros(m)
    if fit_turn:
        turn_std[-n_turn:] = np.sqrt(np.maximum(np.diag(cov[np.ix_(blocks[4], blocks[4])]), 0.0))

    # Conventions for what the data cannot fix (module docstring).
    g_factor = float(np.mean(cam.gain) / np.mean(gain))
    e_factor = float(np.max(cam.efficiency) / np.max(eta)) if fit_src else 1.0
    residuals = (model(sol.x) - y_arr) * -1.0
    sources_out = np.stack(
        [s0r / g_factor, (lr / g_factor / e_factor).real, (lr / g_factor / e_factor).imag], -1
    )
    return TurnFit(
        gain=gain * g_factor,
        gain_std=gain_std * g_factor,
        efficiency=eta * e_factor,
        efficiency_std=eta_std * e_factor,
        angle=alpha,
        angle_std=alpha_std,
        turn=np.asarray(theta, dtype=float),
        turn_std=turn_std,
        scale=scale,
        sources=sources_out,
        residuals=residuals,
        chi2_dof=chi2_dof,
        converged=bool(sol.status > 0),
    )
