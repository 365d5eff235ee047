"""The outer-loop IBVS controller: measurements + mode -> the paper's force F and a yaw.

ROS-free. One ``IbvsController.step`` per camera frame. It never moves the plant: it only turns
image features, translational flows and the IMU attitude into F (newtons, {I}) and the desired
yaw that faces the forward camera to the window normal eta_w (paper section 5).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import TYPE_CHECKING

import numpy as np

from ibvs_control.core.attitude import yaw_facing
from ibvs_common.core.config import PadLayout, VehicleConfig
from ibvs_control.core.control_laws import (
    clamp_norm, CrossingGains, CrossingLaw, DisturbanceLaw, force_crossing_closed,
    force_crossing_intended, force_crossing_seed, force_landing, force_window, GainError,
    IntegralGains, LandingGains, ObserverGains, sigma, WindowGains)
from ibvs_common.core.features import (
    compute_window_features, distance_to_window_plane, pad_feature, pad_height_estimate,
    window_flow, WindowFeatures)
from ibvs_common.core.frames import bearings_C_to_I, e3, euler_zyx_from_rot, GRAVITY, proj_orth
from ibvs_common.core.lever_arm import (E3, flow_from_body, has_lever_arm, pad_height_from_groups,
                                        pad_landmarks_from_body, window_corners_from_body,
                                        window_plane)
from ibvs_common.core.modes import Mode
from ibvs_control.core.observer import DisturbanceObserver
from ibvs_control.core.pad_prediction import PadPrediction

if TYPE_CHECKING:
    from typing import TypeVar
    GainsT = TypeVar('GainsT')     # one of the *Gains dataclasses (ControllerConfig.from_params)

MAX_INTEGRATION_STEP_S = 0.1   # a longer gap between frames is not integrated as flow
# m, the window-plane distances at which d_o times the wall flow is taken as the velocity
# (closer, the corners leave the image; farther, the window is a few pixels)
MIN_VELOCITY_DISTANCE_M, MAX_VELOCITY_DISTANCE_M = 0.2, 10.0
MIN_LANDING_HEIGHT_M = 0.05     # m, pad-image heights below this give no landing velocity


@dataclass(frozen=True)
class ControllerConfig:
    """Everything the controller needs: vehicle mass, gains, camera mounts, window width."""

    mass: float                           # kg
    r_w: float                            # m, known window width (gain condition only)
    R_BC_front: np.ndarray                # forward camera optical -> body FRD
    R_BC_down: np.ndarray                 # down camera optical -> body FRD
    landing: LandingGains = field(default_factory=LandingGains)
    window: WindowGains = field(default_factory=WindowGains)
    crossing: CrossingGains = field(default_factory=CrossingGains)
    crossing_law: CrossingLaw = CrossingLaw.CLOSED
    disturbance_law: DisturbanceLaw = DisturbanceLaw.PAPER
    integral: IntegralGains = field(default_factory=IntegralGains)
    observer: ObserverGains = field(default_factory=ObserverGains)
    eta_t: np.ndarray = field(default_factory=lambda: e3.copy())   # landing plane normal
    group_half_sides: dict = field(default_factory=dict)   # pad group name -> c (m)
    t_BC_front: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m, lever arms in
    t_BC_down: np.ndarray = field(default_factory=lambda: np.zeros(3))   # body FRD

    def validate(self) -> None:
        """Raise GainError for gains that break the paper's conditions."""
        if self.mass <= 0.0:
            raise GainError(f'mass must be positive: {self.mass}')
        self.landing.validate()
        self.window.validate(self.r_w)
        self.crossing.validate()
        if self.disturbance_law.uses_integral:
            self.integral.validate(self.window, self.landing)
        if self.disturbance_law.uses_observer:
            self.observer.validate()

    @classmethod
    def from_params(cls, params: dict, vehicle: VehicleConfig, r_w: float,
                    pad: PadLayout | None = None) -> 'ControllerConfig':
        """Build from a flat parameter dict (names as in params.yaml) and validate it.

        Keys (all optional, the paper's values by default): landing.kp_xy, landing.kp_z,
        landing.kd_xy, landing.kd_z, landing.phi_t_star, window.kp, window.kd, window.k_phi,
        window.phi_star, window.eps, window.delta, crossing.kv, crossing.ks, crossing.kf,
        crossing.phi_fwd_min, crossing_law, landing.lateral_schedule_height_m,
        landing.lateral_scale_min, landing.vertical_schedule_height_m,
        landing.vertical_scale_min, landing.pad_prediction_s, disturbance_law, integral.ki_w,
        integral.ki_phi, integral.ki_t, integral.xi_max, integral.d_max, observer.tau_s,
        observer.d_max, observer.bias_tau_s, observer.bias_max, observer.landing_bias_tau_s.
        ``pad`` gives the group sizes for the
        height estimate.
        Raises GainError (a ValueError).
        """
        def group(prefix: str, kind: type[GainsT]) -> GainsT:
            known = {f.name for f in kind.__dataclass_fields__.values()}
            vals = {k[len(prefix) + 1:]: float(v) for k, v in params.items()
                    if k.startswith(prefix + '.')}
            unknown = set(vals) - known
            if unknown:
                raise GainError(f'unknown {prefix} parameter(s): {sorted(unknown)}')
            return kind(**vals)

        try:
            law = CrossingLaw(params.get('crossing_law', CrossingLaw.CLOSED.value))
        except ValueError as exc:
            raise GainError(f'crossing_law must be one of {[x.value for x in CrossingLaw]}'
                            ) from exc
        try:
            disturbance = DisturbanceLaw(params.get('disturbance_law',
                                                    DisturbanceLaw.PAPER.value))
        except ValueError as exc:
            raise GainError(f'disturbance_law must be one of '
                            f'{[x.value for x in DisturbanceLaw]}') from exc
        cfg = cls(mass=vehicle.mass, r_w=float(r_w),
                  R_BC_front=vehicle.cameras['front'].R_BC,
                  R_BC_down=vehicle.cameras['down'].R_BC,
                  landing=group('landing', LandingGains), window=group('window', WindowGains),
                  crossing=group('crossing', CrossingGains), crossing_law=law,
                  disturbance_law=disturbance, integral=group('integral', IntegralGains),
                  observer=group('observer', ObserverGains),
                  group_half_sides={} if pad is None else {g.name: g.c for g in pad.groups},
                  t_BC_front=vehicle.cameras['front'].t_BC,
                  t_BC_down=vehicle.cameras['down'].t_BC)
        cfg.validate()
        return cfg


@dataclass(frozen=True)
class Measurements:
    """What one control step sees; bearings in camera optical frames, flows in {I}."""

    t: float                                  # s, the image stamp this step answers
    R_IB: np.ndarray                          # IMU attitude at t (body FRD -> {I})
    window_bearings_C: np.ndarray | None      # (4, 3) TL TR BR BL, or None
    pad_bearings_C: np.ndarray | None         # (N, 3) landmarks of complete groups, or None
    phi_front_I: np.ndarray | None            # wall flow v/d_o (1/s), or None
    phi_down_I: np.ndarray | None             # floor flow v/d_t (1/s), or None
    pad_groups: tuple | None = None           # names of the groups in pad_bearings_C, in order
    pad_group_weights: tuple | None = None    # their weights in q_t (pad/groups; None: equal)
    specific_force_I: np.ndarray | None = None  # m/s^2, IMU's, mean since the last step
    omega_B: np.ndarray | None = None         # rad/s, body rate (FRD) at t: lever-arm flows


@dataclass(frozen=True)
class FeatureSnapshot:
    """The features used for one step (None = not available), for plots and diagnosis."""

    q_w: np.ndarray | None = None
    q_w_bar: np.ndarray | None = None
    q_t: np.ndarray | None = None
    phi_w: np.ndarray | None = None
    phi_t: np.ndarray | None = None
    alpha_w: float | None = None
    eta_w: np.ndarray | None = None
    d_hat: np.ndarray | None = None     # disturbance observer's Delta / m (m/s^2), else None
    pad_predicted: bool = False         # q_t carried on the floor flow (pad_prediction.py)


@dataclass(frozen=True)
class ControlOutput:
    """One step's answer: force F (N, {I}), desired NED yaw (rad), features used."""

    F_I: np.ndarray
    yaw_des: float
    features: FeatureSnapshot
    valid: bool = True       # False: inputs missing, F is the last valid (or hover) force


class IbvsController:
    """Mode-dependent force laws with the little state they need.

    State: the latched window normal eta_w (continuity), the last window force F_w(T2-) and the
    yaw facing the window, and in mode 2 the forward-flow reference and the flow integral.
    """

    def __init__(self, config: ControllerConfig) -> None:
        config.validate()
        self.config = config
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt during a flight."""
        self._eta_w: np.ndarray | None = None
        self._F_last = self._hover()
        self._F_w_T2: np.ndarray | None = None
        self._yaw_des: float | None = None
        self._mode: Mode = Mode.IDLE
        self._t_prev: float | None = None
        self._phi_fwd_ref = self.config.crossing.phi_fwd_min
        self._s_perp = np.zeros(3)
        # DisturbanceLaw.INTEGRAL (m/s^2, {I}): window lateral/vertical and forward, landing
        self._xi_w = np.zeros(3)
        self._zeta_w = 0.0
        self._xi_t = np.zeros(3)
        # DisturbanceLaw.OBSERVER: Delta / m (m/s^2, {I}) and the force it was measured with
        self._observer = DisturbanceObserver(self.config.observer, self.config.mass)
        self._d_hat_T2 = np.zeros(3)          # its value with the last window force
        self._F_cmd = self._hover()
        self._pad_prediction = PadPrediction(self.config.landing.pad_prediction_s,
                                             self.config.eta_t)

    def _hover(self) -> np.ndarray:
        return self.config.mass * GRAVITY * e3

    def _window_bearings_I(self, meas: Measurements, R_IB: np.ndarray) -> np.ndarray | None:
        """Return the window corner bearings (4, 3) in {I} from the body origin, or None.

        With a lever arm (t_BC_front) the bearings are re-taken from the body origin
        (lever_arm.py); a view too degenerate for the window plane keeps the camera's.
        """
        if meas.window_bearings_C is None:
            return None
        p_I = bearings_C_to_I(meas.window_bearings_C, R_IB, self.config.R_BC_front)
        if has_lever_arm(self.config.t_BC_front):
            try:
                p_I = window_corners_from_body(p_I, R_IB @ self.config.t_BC_front,
                                               self.config.r_w, self._eta_w)
            except ValueError:
                pass
        return p_I

    def _pad_bearings_I(self, meas: Measurements, R_IB: np.ndarray) -> np.ndarray | None:
        """Return the pad landmarks' bearings in {I} from the body origin, or None."""
        if meas.pad_bearings_C is None or len(meas.pad_bearings_C) == 0:
            return None
        p_I = bearings_C_to_I(meas.pad_bearings_C, R_IB, self.config.R_BC_down)
        if has_lever_arm(self.config.t_BC_down) and meas.pad_groups:
            try:
                body = pad_landmarks_from_body(p_I, list(meas.pad_groups),
                                               self.config.group_half_sides,
                                               R_IB @ self.config.t_BC_down)
            except ValueError:
                body = None
            p_I = p_I if body is None else body
        return p_I

    def _flows_from_body(self, meas: Measurements, R_IB: np.ndarray, p_w_I, pad_I
                         ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Return (wall flow, floor flow) at the body origin (the camera's without lever arm).

        The wall's distance from the window's corners (camera bearings), the floor's from the
        pad's smallest group; a flow whose plane distance is not known is the camera's. With
        the body rate (``meas.omega_B``) the camera's velocity from the rotation is removed too.
        """
        cfg = self.config
        phi_w, phi_t = meas.phi_front_I, meas.phi_down_I
        omega_I = None if meas.omega_B is None else R_IB @ np.asarray(meas.omega_B, float)
        if phi_w is not None and meas.window_bearings_C is not None \
                and has_lever_arm(cfg.t_BC_front):
            try:
                eta, d_o = window_plane(bearings_C_to_I(meas.window_bearings_C, R_IB,
                                                        cfg.R_BC_front), cfg.r_w, self._eta_w)
                phi_w = flow_from_body(phi_w, eta, d_o, R_IB @ cfg.t_BC_front, omega_I)
            except ValueError:
                pass
        if phi_t is not None and meas.pad_bearings_C is not None and meas.pad_groups \
                and has_lever_arm(cfg.t_BC_down):
            h_C = pad_height_from_groups(bearings_C_to_I(meas.pad_bearings_C, R_IB,
                                                         cfg.R_BC_down),
                                         list(meas.pad_groups), cfg.group_half_sides)
            if h_C is not None:
                try:
                    phi_t = flow_from_body(phi_t, E3, h_C, R_IB @ cfg.t_BC_down, omega_I)
                except ValueError:
                    pass
        return phi_w, phi_t

    def _window_features(self, p_I: np.ndarray | None) -> WindowFeatures | None:
        if p_I is None:
            return None
        try:
            return compute_window_features(p_I, self.config.window.eps,
                                           self.config.window.delta, self._eta_w)
        except ValueError:
            return None

    def step(self, mode: Mode, meas: Measurements) -> ControlOutput:
        """Compute F and the yaw for one frame in the given mode."""
        cfg = self.config
        R_IB = np.asarray(meas.R_IB, dtype=float)
        dt = 0.0 if self._t_prev is None else float(np.clip(meas.t - self._t_prev, 0.0,
                                                            MAX_INTEGRATION_STEP_S))
        self._t_prev = meas.t
        entering = mode != self._mode
        self._mode = mode

        p_w_I = self._window_bearings_I(meas, R_IB)
        win = self._window_features(p_w_I)
        pad_I = self._pad_bearings_I(meas, R_IB)
        phi_front, phi_t = self._flows_from_body(meas, R_IB, p_w_I, pad_I)
        q_t = None
        if pad_I is not None:
            try:        # eq:q_t on the pad centre, seen through every complete group
                q_t = pad_feature(pad_I, weights=meas.pad_group_weights)
            except ValueError:          # not 4 bearings per group, or no usable group
                q_t = None
        phi_w = None
        if win is not None and phi_front is not None:
            phi_w = window_flow(phi_front, win.eta_w, win.l_e, win.alpha_w)
        if self._yaw_des is None:
            self._yaw_des = euler_zyx_from_rot(R_IB)[2]
        height, pad_predicted = None, False
        if mode == Mode.LANDING:
            if entering:
                self._pad_prediction.reset()
            pad = self._pad_prediction.step(meas.t, q_t, self._pad_height(meas, R_IB, pad_I),
                                            phi_t)
            if pad is not None:
                q_t, height, pad_predicted = pad.q_t, pad.height_m, pad.predicted
        observer = cfg.disturbance_law.uses_observer
        if observer:
            v_I, bias_tau_s = None, None
            if mode == Mode.WINDOW:
                v_I = self._window_velocity(phi_front, p_w_I, win)
            elif mode == Mode.LANDING:
                v_I = self._landing_velocity(phi_t, height)
                bias_tau_s = cfg.observer.landing_bias_tau_s
            self._observe(dt, meas.specific_force_I, R_IB, v_I, bias_tau_s)
        feats = FeatureSnapshot(
            q_w=None if win is None else win.q_w, q_w_bar=None if win is None else win.q_w_bar,
            q_t=q_t, phi_w=phi_w, phi_t=phi_t, alpha_w=None if win is None else win.alpha_w,
            eta_w=self._eta_w if win is None else win.eta_w,
            d_hat=self._d_hat if observer else None, pad_predicted=pad_predicted)
        F, valid = self._force(mode, entering, dt, win, q_t, phi_w, phi_t, height)
        if valid:
            self._F_last = F
        self._F_cmd = F if valid else self._F_last
        return ControlOutput(self._F_cmd, self._yaw_des, feats, valid)

    def _observe(self, dt: float, f_I: np.ndarray | None, R_IB: np.ndarray,
                 v_I: np.ndarray | None = None, bias_tau_s: float | None = None) -> None:
        """One step of the disturbance observer (observer.py): Delta/m = f_I + F_app / m.

        F_app, the force the vehicle applied over the interval, is the previous command's
        magnitude along the body's thrust axis R_IB e3 (the attitude measured, not the one
        commanded): while the attitude loop lags a new command, the commanded direction is
        not yet the applied one, and their difference would read as a disturbance that the
        law then feeds back (measured on PX4 SIH: a growing oscillation in LANDING). v_I:
        the metric velocity for the velocity channel (WINDOW, LANDING), or None; bias_tau_s
        its correction's time constant there (None: observer.bias_tau_s, WINDOW's).
        """
        F_app = float(np.linalg.norm(self._F_cmd)) * (R_IB @ e3)
        self._observer.update(dt, f_I, F_app, v_I, bias_tau_s)

    @property
    def _d_hat(self) -> np.ndarray:
        """The observer's current Delta / m (m/s^2, {I}; a new array)."""
        return self._observer.estimate

    def _window_velocity(self, phi_front_I: np.ndarray | None, p_I: np.ndarray | None,
                         win: WindowFeatures | None) -> np.ndarray | None:
        """Return v (m/s, {I}) = d_o times the wall flow v / d_o (d_o: corners p_I and r_w).

        None without the velocity channel, a window, a wall flow or a plausible distance.
        """
        if (not self._observer.velocity_aided or win is None or phi_front_I is None
                or p_I is None):
            return None
        with np.errstate(divide='ignore', invalid='ignore'):
            d_o = distance_to_window_plane(p_I, win.eta_w, self.config.r_w)
        if not (math.isfinite(d_o) and MIN_VELOCITY_DISTANCE_M <= d_o <= MAX_VELOCITY_DISTANCE_M):
            return None
        return d_o * np.asarray(phi_front_I, dtype=float)

    def _landing_velocity(self, phi_t_I: np.ndarray | None,
                          height: float | None) -> np.ndarray | None:
        """Return v (m/s, {I}) = h times the floor flow v / d_t (h: the pad-image height).

        The markers lie on the floor, so the pad's height estimate is the flow's depth d_t.
        None without the velocity channel, a floor flow or a plausible height.
        """
        if not self.config.observer.landing_bias_tau_s > 0.0 or phi_t_I is None \
                or height is None:
            return None
        if not (math.isfinite(height)
                and MIN_LANDING_HEIGHT_M <= height <= MAX_VELOCITY_DISTANCE_M):
            return None
        return height * np.asarray(phi_t_I, dtype=float)

    @property
    def disturbance_estimate(self) -> np.ndarray:
        """The observer's Delta / m (m/s^2, {I}); zero unless disturbance_law is observer."""
        return self._d_hat

    def _pad_height(self, meas: Measurements, R_IB: np.ndarray,
                    pad_I: np.ndarray | None = None) -> float | None:
        """Height (m) of the body origin from the smallest complete pad group, or None.

        ``pad_I``: the landmarks from the body origin (needed with a lever arm; without one
        the group's bearings are rotated on their own, as they always were).
        """
        groups, p_C = meas.pad_groups, meas.pad_bearings_C
        if not groups or p_C is None or len(p_C) != 4 * len(groups):
            return None
        if pad_I is None:
            pad_I = self._pad_bearings_I(meas, R_IB)
        sizes = [(self.config.group_half_sides[g], i) for i, g in enumerate(groups)
                 if g in self.config.group_half_sides]
        if not sizes:
            return None
        c, i = min(sizes)
        p_I = pad_I[4 * i:4 * i + 4] if has_lever_arm(self.config.t_BC_down) else \
            bearings_C_to_I(p_C[4 * i:4 * i + 4], R_IB, self.config.R_BC_down)
        try:
            return pad_height_estimate(p_I, c, self.config.eta_t)
        except ValueError:                      # a marker not towards the floor
            return None

    def _force(self, mode: Mode, entering: bool, dt: float, win: WindowFeatures | None,
               q_t: np.ndarray | None, phi_w: np.ndarray | None,
               phi_t: np.ndarray | None, height: float | None) -> tuple[np.ndarray, bool]:
        cfg = self.config
        integral = cfg.disturbance_law.uses_integral
        observer = self._d_hat if cfg.disturbance_law.uses_observer else None
        if mode == Mode.WINDOW:
            if entering:
                self._xi_w, self._zeta_w = np.zeros(3), 0.0
            if win is None or phi_w is None:
                return self._F_last, False
            self._eta_w = win.eta_w
            self._yaw_des = yaw_facing(win.eta_w, cfg.R_BC_front)
            F = force_window(win.q_w, win.q_w_bar, phi_w, win.eta_w, cfg.window, cfg.mass,
                             _sum_terms(self._window_integral(win.eta_w) if integral else None,
                                        observer))
            if integral:
                self._integrate_window(dt, win, phi_w)
            self._F_w_T2, self._d_hat_T2 = F, self._d_hat
            return F, True
        if mode == Mode.CROSSING:
            return self._crossing_force(entering, dt, phi_t)
        if mode == Mode.LANDING:
            if entering and integral and self._eta_w is not None:
                # bumpless: the wind the window law had learnt, in the landing plane
                self._xi_t = proj_orth(cfg.eta_t) @ self._window_integral(self._eta_w)
            if q_t is None or phi_t is None:
                return self._F_last, False
            lateral = cfg.landing.lateral_scale(height)
            F = force_landing(q_t, phi_t, cfg.landing, cfg.mass, cfg.eta_t, lateral,
                              _sum_terms(self._xi_t if integral else None, observer),
                              cfg.landing.vertical_scale(height))
            if integral:        # scheduled as K_p^t: ki_t q_t would grow as 1/h near the floor
                self._xi_t = clamp_norm(self._xi_t + cfg.integral.ki_t * lateral * dt
                                        * (proj_orth(cfg.eta_t) @ q_t), cfg.integral.xi_max)
            return F, True
        # IDLE (the autopilot holds), SHUTDOWN (level, the bridge ramps thrust down) and
        # FAILSAFE (level hover, the bridge/autopilot descend): a level attitude.
        return self._hover(), True

    def _window_integral(self, eta_w: np.ndarray) -> np.ndarray:
        """Window integral term (m/s^2, {I}): pi_eta xi_w + eta zeta_w."""
        return proj_orth(eta_w) @ self._xi_w + eta_w * self._zeta_w

    def _integrate_window(self, dt: float, win: WindowFeatures, phi_w: np.ndarray) -> None:
        """One Euler step of the window integrators, frozen once the window is crossed."""
        if sigma(win.q_w, win.eta_w) == 0.0:
            return
        g = self.config.integral
        pi = proj_orth(win.eta_w)
        self._xi_w = clamp_norm(pi @ (self._xi_w + g.ki_w * dt * win.q_w_bar), g.xi_max)
        self._zeta_w = float(np.clip(
            self._zeta_w + g.ki_phi * dt * (float(win.eta_w @ phi_w)
                                            - self.config.window.phi_star),
            -g.xi_max, g.xi_max))

    def _crossing_force(self, entering: bool, dt: float,
                        phi_t: np.ndarray | None) -> tuple[np.ndarray, bool]:
        cfg = self.config
        if self._eta_w is None or self._F_w_T2 is None:
            return self._hover(), False       # never saw the window: nothing to push along
        eta = self._eta_w
        if cfg.crossing_law == CrossingLaw.SEED:
            return force_crossing_seed(self._F_w_T2, eta), True
        if cfg.crossing_law == CrossingLaw.INTENDED:
            return force_crossing_intended(self._F_w_T2, eta, cfg.mass), True
        if entering:
            self._s_perp = np.zeros(3)
            fwd = float(eta @ phi_t) if phi_t is not None else 0.0
            self._phi_fwd_ref = max(fwd, cfg.crossing.phi_fwd_min)
        if phi_t is None:
            return self._F_last, False
        self._s_perp = self._s_perp + proj_orth(eta) @ np.asarray(phi_t) * dt
        F = force_crossing_closed(self._F_w_T2, eta, phi_t, self._s_perp, self._phi_fwd_ref,
                                  cfg.crossing, cfg.mass)
        if cfg.disturbance_law.uses_observer:
            # F_w(T2-) held pi d_hat(T2); compensate the current estimate instead, along eta too
            F = F + cfg.mass * (self._d_hat - proj_orth(eta) @ self._d_hat_T2)
            if cfg.disturbance_law.uses_integral:
                # and the forward-flow integral's correction of it (an accelerometer bias
                # along eta) carries on: the blind crossing has no image error of its own
                F = F + cfg.mass * self._zeta_w * eta
        return F, True


def _sum_terms(*terms: np.ndarray | None) -> np.ndarray | None:
    """Sum of the disturbance terms given (m/s^2, {I}); None when none is."""
    given = [np.asarray(t, dtype=float) for t in terms if t is not None]
    return sum(given[1:], given[0]) if given else None


def with_crossing_law(config: ControllerConfig, law: CrossingLaw) -> ControllerConfig:
    """Return a copy of config using another mode-2 law (for comparisons)."""
    return replace(config, crossing_law=law)
