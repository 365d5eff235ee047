"""The paper's outer-loop force laws (section 4) and the blind crossing of docs/spec.md section 3.

Sign convention (eq:system): ``m v_dot = -F + m g e3 + Delta`` in {I} (NED-type, z down), so a
force law ``F = m g e3 + m k(.)`` commands the acceleration ``v_dot = -k(.)``. Gains are
mass-normalised as in docs/spec.md section 2: ``F = m (...) + m g e3``. Forces are newtons.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from ibvs_common.core.params import param
from ibvs_common.core.frames import GRAVITY, e3, proj_orth


class GainError(ValueError):
    """A gain set that breaks the conditions of the paper's theorem/propositions."""


class CrossingLaw(str, Enum):
    """Mode 2 (blind crossing) law, selectable for comparison (docs/spec.md section 3)."""

    CLOSED = 'closed'        # intended push + loop closed on the down camera's flow (default)
    INTENDED = 'intended'    # F = m g e3 - eta_w |eta_w^T (F_w(T2-) - m g e3)|, open loop
    SEED = 'seed'            # the seed's literal F = eta_w |eta_w^T F_w(T2-)| (defective)


class DisturbanceLaw(str, Enum):
    """How the window and landing laws treat a steady force disturbance (docs/design.md)."""

    PAPER = 'paper'          # the paper's proportional laws: a steady image offset remains
    INTEGRAL = 'integral'    # plus integral action on the image errors (anti-windup clamp)
    OBSERVER = 'observer'    # plus a disturbance observer: IMU specific force + commanded F
    # both: the observer for the wind, the integrals for what it cannot tell from a
    # disturbance (accelerometer bias, attitude-estimate error; docs/design.md)
    OBSERVER_INTEGRAL = 'observer_integral'

    @property
    def uses_integral(self) -> bool:
        """Integral action on the image errors (IntegralGains)."""
        return self in (DisturbanceLaw.INTEGRAL, DisturbanceLaw.OBSERVER_INTEGRAL)

    @property
    def uses_observer(self) -> bool:
        """The disturbance observer on the IMU's specific force (ObserverGains)."""
        return self in (DisturbanceLaw.OBSERVER, DisturbanceLaw.OBSERVER_INTEGRAL)


@dataclass(frozen=True)
class LandingGains:
    """K_p^t = kp_xy pi_eta + kp_z eta eta^T, K_d^t likewise (1/s^2, 1/s); phi*_t (1/s)."""

    kp_xy: float = param(4.0, '1/s^2, K_p^t horizontal (mass-normalised), > 0', 0.0)
    kp_z: float = param(1.75, '1/s^2, K_p^t along eta_t (mass-normalised), > 0', 0.0)
    kd_xy: float = param(4.0, '1/s, K_d^t horizontal (mass-normalised), > 0', 0.0)
    kd_z: float = param(4.0, '1/s, K_d^t along eta_t (mass-normalised), > 0', 0.0)
    phi_t_star: float = param(0.0, '1/s, phi*_t: eq:FT2 robust variant when > 0', 0.0)
    # Below these image-estimated heights (m) the in-plane and the vertical gains shrink in
    # proportion to the height, so that K/d stays within what the attitude and thrust loops
    # and the graph's delay allow (0 disables; docs/design.md "low-altitude gain schedule").
    lateral_schedule_height_m: float = param(
        1.5, 'm, below this pad-image height the lateral gains scale with the height (0: off)',
        0.0)
    lateral_scale_min: float = param(
        0.1, 'lower bound of that lateral gain scale, (0, 1]', 0.0, 1.0)
    vertical_schedule_height_m: float = param(
        0.8, 'm, below this pad-image height the gains along eta_t scale with the height (0: off)',
        0.0)
    vertical_scale_min: float = param(
        0.1, 'lower bound of that vertical gain scale, (0, 1]', 0.0, 1.0)
    # s (ROS clock, from the last pad frame's stamp): without a complete group, fly on the pad
    # centre carried by the floor flow this long (pad_prediction.py); 0 = hold the last force
    pad_prediction_s: float = param(
        1.5,
        "s (ROS clock, from the last pad frame's stamp): LANDING frames without a complete pad "
        'group fly on the pad centre carried by the floor flow this long, then hold the last '
        'force; 0 = hold at once, >= 0 (pad_prediction.py)', 0.0)

    def validate(self) -> None:
        """Raise GainError unless K_p^t, K_d^t are positive definite and phi*_t >= 0."""
        if min(self.kp_xy, self.kp_z, self.kd_xy, self.kd_z) <= 0.0:
            raise GainError(f'landing gains must be positive (K_p^t, K_d^t > 0): {self}')
        if self.phi_t_star < 0.0:
            raise GainError(f'phi*_t must be >= 0: {self.phi_t_star}')
        for axis in ('lateral', 'vertical'):
            height, low = (getattr(self, f'{axis}_schedule_height_m'),
                           getattr(self, f'{axis}_scale_min'))
            if height < 0.0 or not 0.0 < low <= 1.0:
                raise GainError(f'{axis}_schedule_height_m >= 0 and 0 < {axis}_scale_min <= 1')
        if not (np.isfinite(self.pad_prediction_s) and self.pad_prediction_s >= 0.0):
            raise GainError(f'pad_prediction_s must be >= 0: {self.pad_prediction_s}')

    def lateral_scale(self, height_m: float | None) -> float:
        """Factor on K_p^t, K_d^t in the landing plane for an estimated height (m)."""
        return _schedule(height_m, self.lateral_schedule_height_m, self.lateral_scale_min)

    def vertical_scale(self, height_m: float | None) -> float:
        """Factor on K_p^t, K_d^t along eta_t for an estimated height (m)."""
        return _schedule(height_m, self.vertical_schedule_height_m, self.vertical_scale_min)


def _schedule(height_m: float | None, below_m: float, low: float) -> float:
    """clip(h / below_m, low, 1); 1 without a height or with the schedule off (0)."""
    if height_m is None or below_m <= 0.0:
        return 1.0
    return float(np.clip(height_m / below_m, low, 1.0))


@dataclass(frozen=True)
class WindowGains:
    """Gains of eq:Fw (k_p^w 1/s^2, k_d^w 1/s, k_phi^w 1/s, phi*_w 1/s) and eq:alphaw."""

    kp: float = param(
        1.0, '1/s^2, k_p^w (k_d^w^2 / k_p^w > r_w / 2: Proposition prop:window)', 0.0)
    kd: float = param(0.8, '1/s, k_d^w, > 0', 0.0)
    k_phi: float = param(1.0, '1/s, k_phi^w, > 0', 0.0)
    phi_star: float = param(0.3, '1/s, phi*_w, > 0', 0.0)
    eps: float = param(0.2, 'alpha_w threshold epsilon (dimensionless), > 0', 0.0)
    delta: float = param(0.05, 'alpha_w threshold delta (dimensionless), > 0', 0.0)

    def validate(self, r_w: float) -> None:
        """Proposition prop:window: k_d^2/k_p > r_w/2, positive gains, phi*_w > 0."""
        if min(self.kp, self.kd, self.k_phi) <= 0.0:
            raise GainError(f'window gains k_p^w, k_d^w, k_phi^w must be positive: {self}')
        if self.phi_star <= 0.0:
            raise GainError(f'phi*_w must be > 0 (Proposition prop:window): {self.phi_star}')
        if self.kd ** 2 / self.kp <= r_w / 2.0:
            raise GainError(f'k_d^w^2 / k_p^w = {self.kd ** 2 / self.kp:.3f} must exceed '
                            f'r_w / 2 = {r_w / 2.0:.3f} (Proposition prop:window)')
        if self.eps <= 0.0 or self.delta <= 0.0:
            raise GainError(f'alpha_w thresholds eps, delta must be > 0: {self}')


@dataclass(frozen=True)
class CrossingGains:
    """Mode 2 closed on the down camera's translational flow phi_t = v/d_t.

    Commanded acceleration (orthogonal to eta_w): a_ff - kv pi phi_t - ks pi s, with
    s = integral of pi phi_t dt (the displacement since T2 over the height); along eta_w:
    kf (phi_fwd_ref - eta^T phi_t), phi_fwd_ref = max(eta^T phi_t(T2), phi_fwd_min).
    """

    kv: float = param(4.0, '1/s, mode 2 flow damping (as K_d^t), > 0', 0.0)
    ks: float = param(2.0, '1/s^2, mode 2 flow-integral stiffness, > 0', 0.0)
    kf: float = param(2.0, '1/s, mode 2 forward-flow tracking, > 0', 0.0)
    phi_fwd_min: float = param(0.15, '1/s, minimum forward flow through the window, > 0', 0.0)

    def validate(self) -> None:
        """Raise GainError unless every gain is positive."""
        if min(self.kv, self.ks, self.kf, self.phi_fwd_min) <= 0.0:
            raise GainError(f'crossing gains must be positive: {self}')


@dataclass(frozen=True)
class IntegralGains:
    """Integral action of DisturbanceLaw.INTEGRAL and OBSERVER_INTEGRAL (mass-normalised).

    Window (mode 1): xi_w' = ki_w pi_eta q_bar_w (1/s^3), zeta_w' = ki_phi (eta^T phi_w -
    phi*_w) (1/s^2); landing (mode 3): xi_t' = ki_t s(h) pi_e3 q_t (1/s^3), s(h) the lateral
    gain schedule (LandingGains.lateral_scale). Each term is added to
    its law's acceleration command and clamped to ``xi_max`` (m/s^2, anti-windup). The
    frozen-distance linearisation (docs/design.md "Disturbance rejection") is stable for
    ki_w < k_p^w k_d^w / d_max and ki_t < k_p^t k_d^t / d_max (horizontal gains).
    """

    ki_w: float = param(
        0.2, '1/s^3, window image-error integral (disturbance_law integral; '
        '< k_p^w k_d^w / d_max)', 0.0)
    ki_phi: float = param(0.5, '1/s^2, window forward-flow-error integral, > 0', 0.0)
    ki_t: float = param(
        1.0, '1/s^3, landing horizontal image-error integral (< k_p^t k_d^t / d_max)', 0.0)
    xi_max: float = param(
        2.0, 'm/s^2, largest integral acceleration per law (anti-windup), > 0', 0.0)
    d_max: float = param(
        3.0, 'm, largest window / pad distance of the integral gains condition, > 0', 0.0)

    def validate(self, window: 'WindowGains', landing: LandingGains) -> None:
        """Raise GainError unless positive and within the frozen-distance conditions."""
        if min(self.ki_w, self.ki_phi, self.ki_t, self.xi_max, self.d_max) <= 0.0:
            raise GainError(f'integral gains, xi_max and d_max must be positive: {self}')
        if self.ki_w >= window.kp * window.kd / self.d_max:
            raise GainError(f'ki_w = {self.ki_w} must be < k_p^w k_d^w / d_max = '
                            f'{window.kp * window.kd / self.d_max:.3f} (docs/design.md)')
        if self.ki_t >= landing.kp_xy * landing.kd_xy / self.d_max:
            raise GainError(f'ki_t = {self.ki_t} must be < k_p^t k_d^t / d_max = '
                            f'{landing.kp_xy * landing.kd_xy / self.d_max:.3f}')


@dataclass(frozen=True)
class ObserverGains:
    """Disturbance observer of DisturbanceLaw.OBSERVER and OBSERVER_INTEGRAL (docs/design.md).

    d_hat' = (f_I + F_prev / m - d_hat) / tau_s: the IMU's specific force f_I (m/s^2, {I},
    mean over the frame) plus the force commanded over that frame, i.e. Delta / m for
    m v' = -F + m g e3 + Delta, low-passed; |d_hat| <= d_max. With bias_tau_s > 0, the
    flow's velocity corrects what the IMU cannot see (an attitude-estimate error's push),
    low-passed with bias_tau_s in WINDOW and landing_bias_tau_s in LANDING, |.| <= bias_max,
    held where no velocity is measured (observer.py).
    """

    tau_s: float = param(
        0.5, 's, disturbance observer time constant (disturbance_law observer), > 0', 0.0)
    d_max: float = param(3.0, 'm/s^2, largest disturbance the observer compensates, > 0', 0.0)
    bias_tau_s: float = param(
        0.2,
        "s, time constant of the flow-velocity channel's correction of what the IMU cannot see "
        '(an attitude-estimate error); 0 = IMU only, >= 0', 0.0)
    bias_max: float = param(1.0, 'm/s^2, largest such correction, > 0', 0.0)
    landing_bias_tau_s: float = param(
        0.1,
        's, the same correction in LANDING, from the floor flow times the pad-image height; 0 = '
        'held from WINDOW, >= 0', 0.0)

    def validate(self) -> None:
        """Raise GainError unless tau_s, d_max, bias_max > 0 and both bias time constants >= 0."""
        if min(self.tau_s, self.d_max, self.bias_max) <= 0.0 \
                or not (self.bias_tau_s >= 0.0 and self.landing_bias_tau_s >= 0.0):
            raise GainError(f'observer tau_s, d_max, bias_max must be positive and '
                            f'bias_tau_s, landing_bias_tau_s >= 0: {self}')


def clamp_norm(v: np.ndarray, limit: float) -> np.ndarray:
    """Return v scaled down to norm ``limit`` when longer (the integrators' anti-windup)."""
    n = float(np.linalg.norm(v))
    return v if n <= limit else v * (limit / n)


def gain_matrix(k_xy: float, k_z: float, eta: np.ndarray = e3) -> np.ndarray:
    """K = k_xy pi_eta + k_z eta eta^T (Theorem th:landing's form)."""
    eta = np.asarray(eta, dtype=float)
    return k_xy * proj_orth(eta) + k_z * np.outer(eta, eta)


def force_landing(q_t: np.ndarray, phi_t: np.ndarray, gains: LandingGains, mass: float,
                  eta_t: np.ndarray = e3, lateral_scale: float = 1.0,
                  xi_I: np.ndarray | None = None, vertical_scale: float = 1.0) -> np.ndarray:
    """Landing force eq:FT (eq:FT2 when phi*_t > 0), newtons in {I}.

    F_t = m (K_p^t q_t + K_d^t (phi_t - eta_t phi*_t) + xi) + m g e3, with the in-plane gains
    k_xy multiplied by ``lateral_scale`` and k_z by ``vertical_scale`` (1 = the paper's law;
    LandingGains.lateral_scale / vertical_scale) and xi the integral term of
    :attr:`DisturbanceLaw.INTEGRAL` or the observer's estimate (m/s^2; None = 0, the paper's
    law).
    """
    Kp = gain_matrix(gains.kp_xy * lateral_scale, gains.kp_z * vertical_scale, eta_t)
    Kd = gain_matrix(gains.kd_xy * lateral_scale, gains.kd_z * vertical_scale, eta_t)
    phi = np.asarray(phi_t, dtype=float) - np.asarray(eta_t) * gains.phi_t_star
    a = Kp @ np.asarray(q_t, dtype=float) + Kd @ phi
    if xi_I is not None:
        a = a + np.asarray(xi_I, dtype=float)
    return mass * a + mass * GRAVITY * e3


def sigma(q_w: np.ndarray, eta_w: np.ndarray) -> float:
    """eq:sigma: 1 while eta_w^T q_w < 0 (window still ahead), 0 once crossed."""
    return 1.0 if float(eta_w @ q_w) < 0.0 else 0.0


def force_window(q_w: np.ndarray, q_w_bar: np.ndarray, phi_w: np.ndarray, eta_w: np.ndarray,
                 gains: WindowGains, mass: float, xi_I: np.ndarray | None = None) -> np.ndarray:
    """Window force eq:Fw, newtons in {I}.

    F_w = sigma(q_w) m (k_p pi_eta q_bar_w + k_d pi_eta phi_w + k_phi eta (eta^T phi_w -
    phi*_w) + xi) + m g e3, xi the integral term of :attr:`DisturbanceLaw.INTEGRAL` (m/s^2;
    None = 0, the paper's law). Deviation from the literal eq:Fw (documented): sigma
    multiplies the feedback terms only, so gravity stays compensated once the window is
    crossed.
    """
    pi = proj_orth(eta_w)
    fb = gains.kp * pi @ q_w_bar + gains.kd * pi @ phi_w \
        + gains.k_phi * eta_w * (float(eta_w @ phi_w) - gains.phi_star)
    if xi_I is not None:
        fb = fb + np.asarray(xi_I, dtype=float)
    return sigma(q_w, eta_w) * mass * fb + mass * GRAVITY * e3


def force_crossing_seed(F_w_T2: np.ndarray, eta_w: np.ndarray) -> np.ndarray:
    """Return the seed's literal mode-2 force F = eta_w |eta_w^T F_w(T2-)| (defective).

    docs/spec.md section 3: it drops gravity compensation and, since the dynamics use -F, brakes
    along eta_w.
    Kept only for comparison.
    """
    return np.asarray(eta_w) * abs(float(eta_w @ F_w_T2))


def force_crossing_intended(F_w_T2: np.ndarray, eta_w: np.ndarray, mass: float) -> np.ndarray:
    """Open-loop mode-2 law as intended: F = m g e3 - eta_w |eta_w^T (F_w(T2-) - m g e3)|.

    Keeps gravity compensation and pushes along eta_w (acceleration +eta_w |.| / m).
    """
    g_comp = mass * GRAVITY * e3
    return g_comp - np.asarray(eta_w) * abs(float(eta_w @ (np.asarray(F_w_T2) - g_comp)))


def force_crossing_closed(F_w_T2: np.ndarray, eta_w: np.ndarray, phi_t: np.ndarray,
                          s_perp: np.ndarray, phi_fwd_ref: float, gains: CrossingGains,
                          mass: float) -> np.ndarray:
    """Mode-2 law closed on the down camera's translational flow phi_t = v/d_t.

    Desired acceleration a = a_ff - kv pi phi_t - ks s_perp + kf eta (phi_fwd_ref - eta^T phi_t)
    where pi = pi_{eta_w}, a_ff = -pi (F_w(T2-) - m g e3) / m holds the lateral/vertical
    command that balanced the vehicle just before the window was lost (e.g. a steady wind), and
    s_perp = integral of pi phi_t dt since T2 (the displacement over the height, which stays
    nearly constant while crossing). F = m g e3 - m a.
    """
    pi = proj_orth(eta_w)
    g_comp = mass * GRAVITY * e3
    a_ff = -pi @ (np.asarray(F_w_T2) - g_comp) / mass
    phi_t = np.asarray(phi_t, dtype=float)
    a = a_ff - gains.kv * pi @ phi_t - gains.ks * np.asarray(s_perp) \
        + gains.kf * np.asarray(eta_w) * (phi_fwd_ref - float(eta_w @ phi_t))
    return g_comp - mass * a
