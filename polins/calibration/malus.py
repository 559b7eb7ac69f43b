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

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import OptimizeResult, least_squares

from polins.calibration.images import zero_sum_basis
from polins.errors import UserInputError
from polins.models import CameraModel

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

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
    radial_gain, radial_gain_std : (4,)
        Coefficients ``c_k`` [-] of the channel gains' change with the sources' squared
        radius (``source_radius2``) and their standard errors; zeros without it.
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
    radial_gain: FloatArray = field(default_factory=lambda: np.zeros(4))
    radial_gain_std: FloatArray = field(default_factory=lambda: np.zeros(4))


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
    scale_basis: ArrayLike | None = None,
    tilt_terms: bool = False,
    source_radius2: ArrayLike | None = None,
    turn_start: ArrayLike | None = None,
    turn_prior_std: float | None = None,
    source_factors: ArrayLike | None = None,
    max_iterations: int | None = None,
    source_correlation: ArrayLike | None = None,
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
    scale_basis : array_like, (m, p), optional
        Exposure scales that change smoothly: ``log s_j = sum_i B_ji c_i`` with fitted
        ``c`` (with fitted sources, relative to the first image: ``B - B[0]``). A free
        scale per image (the default) lets turn errors trade against the channel gains'
        differential wherever every source has the same normalised polarization (a narrow
        field about the zenith; docs/calibrate.md#sky-rotation); a camera whose exposure is
        fixed brightens smoothly, and the basis keeps that information.
    tilt_terms : bool
        Let each fitted source also change with the turn at the first harmonic in S0
        (``Re(b_r exp(i theta_j))``) and at the first and third in L
        (``d_r exp(i theta_j) + e_r exp(3i theta_j)``): the first-order effect of a turn axis
        tilted from the optical axis. The channel errors show at other harmonics (S0 at the
        second, L at 0 and -2), so they stay identifiable.
    source_radius2 : array_like, (R,), optional
        A coordinate of each source (the rings' mean squared normalised radius): the channel
        gains then change across the sources as ``g_k (1 + c_k (rho2_r - mean rho2))``, with
        ``c`` fitted (zero sum over the channels; the common part is the sources' S0). A
        channel-dependent radial shading makes a camera-fixed polarization growing with the
        field angle, which a turning source does not hide (docs/calibrate.md#sky-rotation).
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
        :func:`polins.calibration.rings.sun_motion_factors`). Default 1.
    max_iterations : int, optional
        Stop after about this many Levenberg-Marquardt iterations (each one Jacobian);
        ``converged`` says whether it met its tolerance. None: scipy's default.
    source_correlation : array_like, (R, R), optional
        Correlation of the noise of the R sources' means within an image and channel (ring
        windows that overlap share pixels): the residuals are whitened with it, so the
        standard errors hold. Default: independent.

    Returns
    -------
    TurnFit
    """
    y_arr = np.asarray(y, dtype=float)
    m, n_src, _ = y_arr.shape
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), y_arr.shape)
    start = _start_values(y_arr, cam, turn, sources, turn_start)
    if constant_scale and sources is None:
        raise ValueError("constant_scale needs known sources")
    basis = _scale_basis(scale_basis, constant_scale, m, sources is None)
    if (tilt_terms or source_radius2 is not None) and sources is not None:
        raise ValueError("tilt_terms and source_radius2 need fitted sources")
    params = _TurnParameters.of(
        cam,
        start,
        (m, n_src),
        fit_turn=turn is None,
        scale_basis=basis,
        tilt_terms=tilt_terms,
        source_factors=source_factors,
        source_radius2=source_radius2,
        source_correlation=source_correlation,
    )
    x0 = params.start_vector(start)
    if y_arr.size <= x0.size:
        raise UserInputError(
            f"Malus fit: {y_arr.size} channel means cannot fix {x0.size} unknowns; add images"
        )
    max_nfev = None if max_iterations is None else max_iterations * (x0.size + 1)
    sol = least_squares(
        params.residual,
        x0,
        method="lm",
        x_scale="jac",
        max_nfev=max_nfev,
        args=(y_arr, sig, turn_prior_std),
    )
    return _turn_fit(params, sol, y_arr)


def _scale_basis(
    scale_basis: ArrayLike | None, constant_scale: bool, m: int, fit_src: bool
) -> FloatArray | None:
    """The basis ``(m, p)`` of the log exposure scales, or None for one free scale per
    image (the first fixed at 1 when the sources are fitted)."""
    if constant_scale:
        return np.ones((m, 1))
    if scale_basis is None:
        return None
    basis = np.asarray(scale_basis, dtype=float).reshape(m, -1)
    if fit_src:  # the sources take the first image's scale
        basis = basis - basis[:1]
        basis = basis[:, np.abs(basis).max(axis=0) > 0]
    return basis


@dataclass(frozen=True)
class _StartValues:
    """Start values of the Malus fit from the base camera's Stokes vectors: the turns
    ``theta0`` [rad], the reference sources ``ref_s0`` [DN], ``ref_lin`` [DN] (given, or
    the first image's), the exposure scales ``s0_scale`` [-] and, for fitted sources, their
    start vector ``src_x0`` (S0 | Re L | Im L; empty for known sources)."""

    theta0: FloatArray
    ref_s0: FloatArray
    ref_lin: ComplexArray
    s0_scale: FloatArray
    src_x0: FloatArray
    fit_src: bool


def _start_values(
    y_arr: FloatArray,
    cam: CameraModel,
    turn: ArrayLike | None,
    sources: ArrayLike | None,
    turn_start: ArrayLike | None,
) -> _StartValues:
    """The start values of :func:`fit_turning_polarization` (its parameters)."""
    n_src = y_arr.shape[1]
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
    src_x0 = np.zeros(0)
    if fit_src:
        s0_scale = s0_scale / s0_scale[0]
        rot = np.exp(-2j * theta0)[:, None]
        src_s0 = (stokes0[..., 0] / s0_scale[:, None]).mean(axis=0)
        src_lin = (lin0 * rot / s0_scale[:, None]).mean(axis=0)
        src_x0 = np.concatenate([src_s0, src_lin.real, src_lin.imag])
    return _StartValues(theta0, ref_s0, ref_lin, s0_scale, src_x0, fit_src)


@dataclass(frozen=True)
class _TurnParameters:
    """The parameter vector of the Malus fit and the channel means it predicts.

    Parameter vector: log-gain (3) | efficiency (3 log, relative; or 4 log) | angle offsets
    (3 relative or 4) | log scale (m - 1 or m, or 1 constant) | turns (m - 1 or m, when
    fitted) | sources (3 R, when fitted) | tilt terms (6 R, optional).
    """

    cam: CameraModel
    start: _StartValues
    m: int
    n_src: int
    fit_turn: bool
    scale_basis: FloatArray | None
    tilt_terms: bool
    n_alpha: int
    cuts: NDArray[np.int_]
    q: FloatArray
    log_eta_base: FloatArray
    factors: ComplexArray
    radius2: FloatArray | None
    whiten: FloatArray | None  # (R, R) inverse Cholesky factor of the sources' correlation

    @classmethod
    def of(
        cls,
        cam: CameraModel,
        start: _StartValues,
        shape: tuple[int, int],
        *,
        fit_turn: bool,
        scale_basis: FloatArray | None,
        tilt_terms: bool,
        source_factors: ArrayLike | None,
        source_radius2: ArrayLike | None = None,
        source_correlation: ArrayLike | None = None,
    ) -> _TurnParameters:
        """The parameters for ``shape`` = (m images, R sources)."""
        m, n_src = shape
        fit_src = start.fit_src
        n_eta = 3 if fit_src else 4
        n_alpha = 3 if (fit_turn or fit_src) else 4  # fitted sources take a common angle too
        n_scale = (m - 1 if fit_src else m) if scale_basis is None else scale_basis.shape[1]
        n_turn = (m - 1 if fit_src else m) if fit_turn else 0
        n_tilt = 6 * n_src if tilt_terms else 0
        n_radial = 0 if source_radius2 is None else 3
        sizes = [3, n_eta, n_alpha, n_scale, n_turn, 3 * n_src if fit_src else 0, n_tilt,
                 n_radial]  # fmt: skip
        radius2 = None
        if source_radius2 is not None:
            radius2 = np.asarray(source_radius2, dtype=float).reshape(n_src)
            radius2 = radius2 - radius2.mean()
        factors = (
            np.ones((m, n_src), dtype=complex)
            if source_factors is None
            else np.broadcast_to(np.asarray(source_factors, dtype=complex), (m, n_src))
        )
        return cls(
            cam,
            start,
            m,
            n_src,
            fit_turn,
            scale_basis,
            tilt_terms,
            n_alpha,
            np.cumsum(sizes)[:-1],
            zero_sum_basis(4),
            np.log(cam.efficiency),
            factors,
            radius2,
            None
            if source_correlation is None
            else np.linalg.inv(np.linalg.cholesky(np.asarray(source_correlation, dtype=float))),
        )

    @property
    def n_tilt(self) -> int:
        """Number of tilt-term parameters."""
        return 6 * self.n_src if self.tilt_terms else 0

    def start_vector(self, start: _StartValues) -> FloatArray:
        """The parameter vector at the start values."""
        fit_src, s0_scale, theta0 = start.fit_src, start.s0_scale, start.theta0
        return np.concatenate(
            [
                np.zeros(3),
                np.zeros(3) if fit_src else self.log_eta_base,
                np.zeros(self.n_alpha),
                self._start_log_scale(s0_scale, fit_src),
                (theta0[1:] if fit_src else theta0) if self.fit_turn else np.zeros(0),
                start.src_x0,
                np.zeros(self.n_tilt),
                np.zeros(0 if self.radius2 is None else 3),
            ]
        )

    def _start_log_scale(self, s0_scale: FloatArray, fit_src: bool) -> FloatArray:
        log_s = np.log(np.maximum(s0_scale, 1e-9))
        if self.scale_basis is None:
            return log_s[1:] if fit_src else log_s
        coef, *_ = np.linalg.lstsq(self.scale_basis, log_s - log_s[0] * fit_src, rcond=None)
        return np.asarray(coef, dtype=float)

    def unpack(self, x: FloatArray) -> tuple[FloatArray, ...]:
        """Gains, efficiencies, angles [rad], exposure scales, turns [rad], source S0 and
        source L of the parameter vector ``x``."""
        fit_src, q, log_eta_base = self.start.fit_src, self.q, self.log_eta_base
        a, b, d, ls, th, sv, _, _ = np.split(x, self.cuts)
        gain = np.exp(q @ a)
        eta = np.exp(log_eta_base - log_eta_base.mean() + q @ b) if fit_src else np.exp(b)
        alpha = self.cam.transmission_angle + (q @ d if self.n_alpha == 3 else d)
        if self.scale_basis is not None:
            scale = np.exp(self.scale_basis @ ls)
        else:
            scale = np.exp(np.concatenate([[0.0], ls]) if fit_src else ls)
        theta = (
            (np.concatenate([[0.0], th]) if fit_src else th) if self.fit_turn else self.start.theta0
        )
        if fit_src:
            n_src = self.n_src
            s0r, lr = sv[:n_src], sv[n_src : 2 * n_src] + 1j * sv[2 * n_src :]
        else:
            s0r, lr = self.start.ref_s0, self.start.ref_lin
        return gain, eta, alpha, scale, theta, s0r, lr

    def model(self, x: FloatArray) -> FloatArray:
        """The dark-subtracted channel means (m, R, 4) [DN] of the parameter vector ``x``."""
        gain, eta, alpha, scale, theta, s0r, lr = self.unpack(x)
        turn_1 = np.exp(1j * theta)[:, None]  # (m, 1)
        lin = lr[None, :] * self.factors * turn_1**2  # (m, R)
        s0 = np.broadcast_to(s0r[None, :], lin.shape)
        if self.tilt_terms:
            tb = x[self.cuts[-2] : self.cuts[-1]].reshape(6, self.n_src)
            s0 = s0 + ((tb[0] + 1j * tb[1]) * turn_1).real
            lin = lin + (tb[2] + 1j * tb[3]) * turn_1 + (tb[4] + 1j * tb[5]) * turn_1**3
        pol = (lin[..., None] * np.exp(-2j * alpha)).real  # (m, R, 4)
        if self.radius2 is not None:
            gain = gain * (1.0 + np.outer(self.radius2, self.radial_gain(x)))  # (R, 4)
        return 0.5 * scale[:, None, None] * gain * (s0[..., None] + eta * pol)

    def radial_gain(self, x: FloatArray) -> FloatArray:
        """The radial gain coefficients ``c_k`` (4,) [-] of ``x`` (zeros without them)."""
        if self.radius2 is None:
            return np.zeros(4)
        return np.asarray(self.q @ x[self.cuts[-1] :], dtype=float)

    def residual(
        self, x: FloatArray, y_arr: FloatArray, sig: FloatArray, turn_prior_std: float | None
    ) -> FloatArray:
        """Normalised residuals of the channel means, the turn prior and the gauge terms."""
        r = (self.model(x) - y_arr) / sig
        if self.whiten is not None:
            r = np.einsum("rs,msk->mrk", self.whiten, r)
        r = r.ravel()
        _, _, _, scale, theta, _, _ = self.unpack(x)
        extra = []
        if turn_prior_std is not None and self.fit_turn:
            extra.append((theta - self.start.theta0) / turn_prior_std)
        if self.tilt_terms and self.scale_basis is None:
            # Free exposure scales that wobble as 1 + Re(c exp(i theta_j)) trade exactly
            # against the tilt terms too: fix that flat direction (the channels do not depend
            # on it).
            wobble = np.sum(np.log(scale) * np.exp(1j * theta)) / self.m * GAUGE_WEIGHT
            extra.append(np.array([wobble.real, wobble.imag]))
        return np.concatenate([r, *extra]) if extra else r


def _turn_fit(params: _TurnParameters, sol: OptimizeResult, y_arr: FloatArray) -> TurnFit:
    """The :class:`TurnFit` of a solved Malus fit: standard errors from the Jacobian scaled
    by chi2/dof when above 1 (never below the declared noise), then the conventions for what
    the data cannot fix (module docstring)."""
    cam, q, m, fit_src = params.cam, params.q, params.m, params.start.fit_src
    gain, eta, alpha, scale, theta, s0r, lr = params.unpack(sol.x)
    dof = y_arr.size - sol.x.size
    chi2_dof = float(np.sum(sol.fun[: y_arr.size] ** 2) / dof)
    jac = sol.jac
    cov = np.linalg.pinv(jac.T @ jac) * max(chi2_dof, 1.0)  # never below the declared noise
    blocks = np.split(np.arange(sol.x.size), params.cuts)

    def std_of(jac_block: FloatArray, idx: NDArray[np.int_]) -> FloatArray:
        c = cov[np.ix_(idx, idx)]
        return np.sqrt(np.maximum(np.diag(jac_block @ c @ jac_block.T), 0.0))

    gain_std = gain * std_of(q, blocks[0])
    eta_std = eta * std_of(q if fit_src else np.eye(4), blocks[1])
    alpha_std = std_of(q if params.n_alpha == 3 else np.eye(4), blocks[2])
    turn_std = np.zeros(m)
    if params.fit_turn:
        n_turn = blocks[4].size
        turn_std[-n_turn:] = np.sqrt(np.maximum(np.diag(cov[np.ix_(blocks[4], blocks[4])]), 0.0))

    # Conventions for what the data cannot fix (module docstring).
    g_factor = float(np.mean(cam.gain) / np.mean(gain))
    e_factor = float(np.max(cam.efficiency) / np.max(eta)) if fit_src else 1.0
    residuals = (params.model(sol.x) - y_arr) * -1.0
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
        radial_gain=params.radial_gain(sol.x),
        radial_gain_std=std_of(q, blocks[-1]) if params.radius2 is not None else np.zeros(4),
    )
