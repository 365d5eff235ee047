"""Feature-level closed loop of the reference scenario (no images).

Plant: point mass with eq:system, the image-level simulator's inner attitude loop (a
second-order response per axis after a setpoint delay, vehicle.yaml ``sim_plant``: PX4 SIH's
measured response, docs/sim.md "Inner attitude loop"; or a first-order lag ``attitude_tau``
when given) and a first-order thrust lag. Sensors: the features the perception would deliver,
computed from geometry (window corner and pad marker bearings, translational flows v/d), with
the cameras' fields of view (CameraModel projection with distortion) and the wall's occlusion
deciding what is seen; the IMU's specific force v' - g e3, exact, averaged over each frame
(the disturbance observer's input). Controller and supervisor: the ROS-free IBVS core,
exactly as the nodes run it. Used by the tests of issue 2, by ``make run --
--feature-level`` and by the campaigns (``python -m ibvs_harness.campaign``).

Wind: the image-level simulator's model, :class:`ibvs_sim.core.dynamics.Wind` (steady force
plus a seeded sum of sines per axis, docs/sim.md "Wind"). The point mass feels
``a = -F_T R e3 / m + g e3 + Delta(t) / m`` in {I} (x north = window normal, y east, z down),
with ``Delta(t) = m wind_accel_I + Wind(wind).force_I(t)`` (N), evaluated at the start of each
physics step: ``wind_accel_I`` (m/s^2) is a constant wind given as an acceleration (kept for
the callers that set it), ``wind`` a :class:`WindConfig` (newtons), default none.
"""
from __future__ import annotations

import collections

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ibvs_control.core.attitude import attitude_from_force, shutdown_thrust_scale
from ibvs_common.core.config import CameraConfig, PadLayout, VehicleConfig
from ibvs_common.core.lever_arm import camera_bearings_from_body, has_lever_arm
from ibvs_sim.core.world import WorldConfig
from ibvs_control.core.control_laws import CrossingLaw
from ibvs_control.core.controller import (
    ControllerConfig, IbvsController, Measurements, with_crossing_law)
from ibvs_common.core.frames import (
    bearings_C_to_I, bearings_I_to_C, e3, exp_so3, GRAVITY, log_so3, rot_z)
from ibvs_common.core.modes import Mode
from ibvs_control.core.supervisor import ModeSupervisor, SupervisorConfig
from ibvs_sim.core.autopilot.config import AutopilotConfig
from ibvs_sim.core.autopilot.noise import SensorNoise
from ibvs_sim.core.contacts import floor_clearance, obstacle_clearance
from ibvs_sim.core.dynamics import attitude_error, PlantParams, Wind, WindConfig
from ibvs_sim.core.evaluation import evaluate_run, GroundTruthLog

MIN_MARKER_PIXELS = 12.0      # a marker smaller than this (side, px) is not detected
IMAGE_MARGIN_PX = 2.0         # a point this close to the border counts as outside
WINDOW_BORDER_MARGIN_PX = 4.0  # the window detector needs the whole dark band this far inside
BAND_SAMPLES_PER_EDGE = 9      # points per outer band edge checked (distortion curves edges)


@dataclass(frozen=True)
class FeatureSimConfig:
    """Run options; defaults are the reference scenario."""

    initial_position_I: np.ndarray
    initial_yaw: float = 0.0
    wind_accel_I: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s^2 (Delta/m)
    wind: WindConfig | None = None     # N, {I}: steady + gusts, added to m wind_accel_I
    crossing_law: CrossingLaw = CrossingLaw.CLOSED
    physics_dt: float = 0.004          # s (250 Hz)
    camera_dt: float = 0.02            # s (50 Hz)
    attitude_tau: float | None = None  # s: a first-order inner loop instead of vehicle.yaml's
    command_delay_s: float = 0.0       # s, frame stamp -> setpoint applied (graph + link)
    accel_bias_B: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s^2, body FRD
    # rad (roll, pitch): static error of the autopilot's attitude estimate R_IB R_err, which
    # the graph reads (bearings, flows, specific force into {I}) and the inner loop flies (it
    # holds the estimate at R_d, so the truth at R_d R_err^T), as the image-level sim's
    # autopilot (ibvs_sim.core.autopilot.noise); PX4 SIH showed 1.5-1.8 deg in one axis
    attitude_estimate_offset_rad: tuple = (0.0, 0.0)
    # rad, std per axis of the estimate's wandering error (first-order Gauss-Markov, time
    # constant attitude_noise_tau_s), composed with the offset: the image-level sim's model
    # (noise.SensorNoise, seeded with ``seed``); 0 here (exact features for the tests), the
    # campaigns take params.yaml's sim values (PX4 SIH's fit, 0.7 deg and 2 s)
    attitude_noise_std: float = 0.0
    attitude_noise_tau_s: float = 2.0
    thrust_tau: float = 0.03           # s
    shutdown_ramp_s: float = 2.0       # s, mode 4 thrust ramp
    max_time_s: float = 60.0
    flow_noise: float = 0.0            # 1/s, white noise std on each flow component
    # frames: each flow measured on every Nth frame only and held on the others (the graph
    # shedding that flow's work on a slow computer: the force answers with a flow up to N - 1
    # frames old); 1 = every frame
    flow_stride_front: int = 1
    flow_stride_down: int = 1
    bearing_noise_rad: float = 0.0     # white noise on each bearing
    # m/s^2, std per body axis (FRD) of one accelerometer sample, white between samples (PX4
    # SIH's as the bridge receives it: 0.28 0.95 0.80, docs/sim_autopilot.md "How it differs
    # from real PX4"); the graph averages imu_rate_hz * camera_dt samples a frame (the frame
    # mean's std is std / sqrt(n))
    accel_noise_std_B: tuple = (0.0, 0.0, 0.0)
    imu_rate_hz: float = 100.0         # Hz, the accelerometer samples the graph receives
    seed: int = 0


@dataclass
class FeatureSimLog:
    """Time series for plots: ground truth, commands and the features used."""

    truth: GroundTruthLog = field(default_factory=GroundTruthLog)
    t_ctrl: list = field(default_factory=list)
    F_I: list = field(default_factory=list)
    mode: list = field(default_factory=list)
    q_w_bar: list = field(default_factory=list)
    q_t: list = field(default_factory=list)
    phi_t: list = field(default_factory=list)
    phi_w: list = field(default_factory=list)
    transitions: list = field(default_factory=list)   # the supervisor's: (to mode, t s, reason)
    R_IB: list = field(default_factory=list)          # true attitude at each frame (t_ctrl)
    Omega_B: list = field(default_factory=list)       # true body rates at each frame, rad/s


class FeatureSensors:
    """Geometric stand-in for the perception nodes.

    Each camera sees from its optical centre, ``xi + R_IB t_BC`` (the vehicle's lever arms),
    and its flow is its own velocity over its own distance to the plane.
    """

    def __init__(self, world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                 rng: np.random.Generator, bearing_noise: float, flow_noise: float) -> None:
        self.world, self.pad, self.vehicle = world, pad, vehicle
        self.rng, self.bearing_noise, self.flow_noise = rng, bearing_noise, flow_noise
        self.corners_I = world.window.corners_I()
        outer = world.window.outer_corners_I()
        s = np.linspace(0.0, 1.0, BAND_SAMPLES_PER_EDGE)[:, None]
        self.band_outline_I = np.vstack([(1.0 - s) * outer[i] + s * outer[(i + 1) % 4]
                                         for i in range(4)])

    @staticmethod
    def camera_position(cam: CameraConfig, R_IB: np.ndarray, xi_I: np.ndarray) -> np.ndarray:
        """Return the camera's optical centre in {I} (the body origin without a lever arm)."""
        return xi_I + R_IB @ cam.t_BC if has_lever_arm(cam.t_BC) else xi_I

    def _visible_C(self, cam: CameraConfig, R_IB: np.ndarray, points_I: np.ndarray,
                   xi_I: np.ndarray, margin_px: float = IMAGE_MARGIN_PX
                   ) -> tuple[np.ndarray, bool]:
        P = points_I - self.camera_position(cam, R_IB, xi_I)
        P_C = bearings_I_to_C(P, R_IB, cam.R_BC)
        uv, ok = cam.model.bearings_to_pixels(P_C)
        m = margin_px
        ok &= (uv[:, 0] >= m) & (uv[:, 0] <= cam.model.width - 1 - m) \
            & (uv[:, 1] >= m) & (uv[:, 1] <= cam.model.height - 1 - m)
        return P_C / np.linalg.norm(P_C, axis=1, keepdims=True), bool(np.all(ok))

    def _noisy(self, b: np.ndarray) -> np.ndarray:
        if self.bearing_noise <= 0.0:
            return b
        b = b + self.rng.normal(0.0, self.bearing_noise, b.shape)
        return b / np.linalg.norm(b, axis=1, keepdims=True)

    def window(self, R_IB: np.ndarray, xi_I: np.ndarray) -> np.ndarray | None:
        """Corner bearings (4, 3) in the front optical frame when the whole window is in view.

        As the window detector sees it: the aperture corners and the whole outline of the dark
        band around them (sampled, since distortion curves its edges) at least
        WINDOW_BORDER_MARGIN_PX inside the image.
        """
        if xi_I[0] >= self.world.wall_x:
            return None
        cam = self.vehicle.cameras['front']
        b, ok = self._visible_C(cam, R_IB, self.corners_I, xi_I)
        _, band_ok = self._visible_C(cam, R_IB, self.band_outline_I, xi_I,
                                     WINDOW_BORDER_MARGIN_PX)
        return self._noisy(b) if ok and band_ok else None

    def _occluded_by_wall(self, xi_I: np.ndarray, s_I: np.ndarray) -> bool:
        wx = self.world.wall_x
        if (xi_I[0] - wx) * (s_I[0] - wx) >= 0.0:
            return False
        a = (wx - xi_I[0]) / (s_I[0] - xi_I[0])
        y, z = xi_I[1:] + a * (s_I[1:] - xi_I[1:])
        win = self.world.window
        return not (abs(y - win.center_I[1]) < win.width / 2.0
                    and abs(z - win.center_I[2]) < win.height / 2.0)

    def pad_landmarks(self, R_IB: np.ndarray, xi_I: np.ndarray) -> tuple[np.ndarray | None,
                                                                         list[str]]:
        """Marker-centre bearings of complete groups (down optical frame) and group names."""
        cam = self.vehicle.cameras['down']
        f = cam.model.K[0, 0]
        xi_C = self.camera_position(cam, R_IB, xi_I)
        out, names = [], []
        for g in self.pad.groups:
            centres = g.marker_centres_I()
            h = g.side / 2.0
            corners = np.concatenate([centres + [dx, dy, 0.0] for dx in (-h, h)
                                      for dy in (-h, h)])
            dist = np.linalg.norm(centres - xi_C, axis=1)
            if np.any(g.side * f / dist < MIN_MARKER_PIXELS):
                continue
            if any(self._occluded_by_wall(xi_C, c) for c in corners):
                continue
            _, ok = self._visible_C(cam, R_IB, corners, xi_I)
            if not ok:
                continue
            b, _ = self._visible_C(cam, R_IB, centres, xi_I)
            out.append(self._noisy(b))
            names.append(g.name)
        return (np.concatenate(out) if out else None), names

    def _flow(self, v_I: np.ndarray, d: float) -> np.ndarray:
        phi = np.asarray(v_I) / d
        if self.flow_noise > 0.0:
            phi = phi + self.rng.normal(0.0, self.flow_noise, 3)
        return phi

    def _camera_motion(self, name: str, xi_I: np.ndarray, v_I: np.ndarray,
                       R_IB: np.ndarray | None, omega_B: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) of a camera: its lever arm moves it with the body's rotation."""
        t_BC = self.vehicle.cameras[name].t_BC
        if R_IB is None or not has_lever_arm(t_BC):
            return xi_I, v_I
        omega = np.zeros(3) if omega_B is None else np.asarray(omega_B, dtype=float)
        return xi_I + R_IB @ t_BC, v_I + R_IB @ np.cross(omega, t_BC)

    def flow_down(self, xi_I: np.ndarray, v_I: np.ndarray, R_IB: np.ndarray | None = None,
                  omega_B: np.ndarray | None = None) -> np.ndarray | None:
        """v/d_t over the floor (the down camera always sees the textured floor)."""
        xi_C, v_C = self._camera_motion('down', xi_I, v_I, R_IB, omega_B)
        d_t = self.world.floor_z - xi_C[2]
        return self._flow(v_C, d_t) if d_t > 0.05 else None

    def flow_front(self, xi_I: np.ndarray, v_I: np.ndarray, R_IB: np.ndarray | None = None,
                   omega_B: np.ndarray | None = None) -> np.ndarray | None:
        """v/d_o over the wall while it is ahead."""
        xi_C, v_C = self._camera_motion('front', xi_I, v_I, R_IB, omega_B)
        d_o = self.world.wall_x - xi_C[0]
        return self._flow(v_C, d_o) if d_o > 0.05 else None


class InnerLoop:
    """The autopilot's attitude loop on the point mass: R_d -> R, one physics step at a time.

    Default: the image-level plant's closed loop without its rigid body (dynamics.py
    ``AttitudeController``): per axis ``theta'' + 2 zeta wn theta' + wn^2 theta = 0`` on the
    SO(3) error ``e_R`` (dynamics.attitude_error), i.e. ``Omega' = -wn^2 e_R - 2 zeta wn
    Omega`` (body FRD, rad/s), ``R+ = R exp(S(Omega+) dt)``; the setpoint applied
    ``delay_s`` (vehicle.yaml ``setpoint_delay``) after it is given. With ``tau`` (s): the
    first-order lag ``R+ = R exp(log(R^T R_d) min(dt / tau, 1))`` and no delay.
    """

    def __init__(self, plant: PlantParams, tau: float | None = None) -> None:
        if tau is not None and not tau > 0.0:
            raise ValueError(f'attitude_tau must be > 0 s, got {tau}')
        self.tau = tau
        self.wn, self.zeta = plant.inner_wn, plant.inner_zeta
        self.delay_s = 0.0 if tau is not None else plant.setpoint_delay_s

    def step(self, R: np.ndarray, Omega_B: np.ndarray, R_d: np.ndarray,
             dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Return (R_IB, Omega_B) after dt (s) towards R_d."""
        if self.tau is not None:
            return R @ exp_so3(log_so3(R.T @ R_d) * min(dt / self.tau, 1.0)), Omega_B
        e_R = attitude_error(R, R_d)
        Omega_B = Omega_B + (-self.wn ** 2 * e_R - 2.0 * self.zeta * self.wn * Omega_B) * dt
        return R @ exp_so3(Omega_B * dt), Omega_B


def estimate_error_model(config: FeatureSimConfig) -> Callable[[float], np.ndarray | None]:
    """Return t (s) -> R_err (the autopilot's estimate is R_IB R_err), or None when exact.

    The image-level sim autopilot's model (``noise.SensorNoise``): the static offset composed
    with the Gauss-Markov error; t must not go back.
    """
    roll, pitch = (float(a) for a in config.attitude_estimate_offset_rad)
    if not (roll or pitch or config.attitude_noise_std > 0.0):
        return lambda t: None
    return SensorNoise(AutopilotConfig(
        attitude_noise_std=config.attitude_noise_std,
        attitude_noise_tau_s=config.attitude_noise_tau_s,
        attitude_estimate_offset_rad=(roll, pitch), noise_seed=int(config.seed))).attitude_error


def accel_noise_model(config: FeatureSimConfig) -> Callable[[np.ndarray], np.ndarray]:
    """Return R_est -> the frame mean's accelerometer noise in {I} (m/s^2).

    One draw per frame: each body axis's std over sqrt(the samples a frame averages), put into
    {I} with the attitude estimate R_est (as the graph puts the IMU's specific force). Its own
    random stream (seed, 3): runs without accelerometer noise draw exactly as before.
    """
    std_B = np.asarray(config.accel_noise_std_B, dtype=float).reshape(3)
    if np.any(std_B < 0.0) or not np.all(np.isfinite(std_B)) or not config.imu_rate_hz > 0.0:
        raise ValueError(f'accelerometer noise std >= 0 and IMU rate > 0, got {std_B}, '
                         f'{config.imu_rate_hz}')
    if not np.any(std_B > 0.0):
        return lambda R_est: np.zeros(3)
    n = max(1.0, config.imu_rate_hz * config.camera_dt)
    rng = np.random.default_rng([int(config.seed), 3])
    return lambda R_est: R_est @ (rng.standard_normal(3) * std_B / np.sqrt(n))


def run_feature_scenario(world: WorldConfig, pad: PadLayout, vehicle: VehicleConfig,
                         controller_config: ControllerConfig,
                         supervisor_config: SupervisorConfig,
                         config: FeatureSimConfig,
                         onboard_vehicle: VehicleConfig | None = None
                         ) -> tuple[dict, FeatureSimLog]:
    """Fly one run; return (SPEC section 5 summary, time series).

    ``vehicle`` is the truth the cameras see with (mounts, lever arms); ``onboard_vehicle``
    the calibration the supervisor reads them with (default: the truth; the controller's is
    in ``controller_config``).
    """
    onboard = vehicle if onboard_vehicle is None else onboard_vehicle
    rng = np.random.default_rng(config.seed)
    sensors = FeatureSensors(world, pad, vehicle, rng, config.bearing_noise_rad,
                             config.flow_noise)
    controller = IbvsController(with_crossing_law(controller_config, config.crossing_law))
    supervisor = ModeSupervisor(supervisor_config)
    m, g = vehicle.mass, GRAVITY
    xi = np.asarray(config.initial_position_I, dtype=float).copy()
    v = np.zeros(3)
    R = rot_z(config.initial_yaw)
    R_d, thrust_d, thrust = R.copy(), m * g, m * g
    log = FeatureSimLog()
    t, t_shutdown = 0.0, None
    started = False
    n_sub = int(round(config.camera_dt / config.physics_dt))
    R_BC_front, R_BC_down = onboard.cameras['front'].R_BC, onboard.cameras['down'].R_BC
    t_BC = {cam: onboard.cameras[cam].t_BC for cam in ('front', 'down')}
    front_model = onboard.cameras['front'].model     # the supervisor's image border margin
    wind = Wind(config.wind or WindConfig())
    wind_accel_steady = np.asarray(config.wind_accel_I, dtype=float).reshape(3)
    f_I_mean = None             # no IMU specific force before the first frame's physics
    pending: collections.deque = collections.deque()   # (t applied, R_d, thrust_d)
    loop = InnerLoop(PlantParams.from_vehicle(vehicle), config.attitude_tau)
    Omega_B = np.zeros(3)
    accel_bias_B = np.asarray(config.accel_bias_B, dtype=float).reshape(3)
    estimate_error = estimate_error_model(config)
    if min(config.flow_stride_front, config.flow_stride_down) < 1:
        raise ValueError('flow strides must be >= 1')
    held = {'front': None, 'down': None}    # the last measured flows ({I}), shed frames reuse
    accel_noise = accel_noise_model(config)
    frame = 0
    while t <= config.max_time_s:
        R_err = estimate_error(t)
        # --- one camera frame: sense, supervise, control ---------------------------------
        win_C = sensors.window(R, xi)
        pad_C, groups = sensors.pad_landmarks(R, xi)
        phi_down = sensors.flow_down(xi, v, R, Omega_B)
        phi_front = sensors.flow_front(xi, v, R, Omega_B)
        R_est = R if R_err is None else R @ R_err       # the attitude the graph reads
        if R_err is not None:   # flows measured in the cameras, put into {I} with R_est
            rot_I = R_est @ R.T
            phi_down = None if phi_down is None else rot_I @ phi_down
            phi_front = None if phi_front is None else rot_I @ phi_front
        if frame % config.flow_stride_front:
            phi_front = held['front']
        if frame % config.flow_stride_down:
            phi_down = held['down']
        held['front'], held['down'] = phi_front, phi_down
        frame += 1
        supervisor.on_imu(t, R_est)
        supervisor.on_window(t, None if win_C is None else camera_bearings_from_body(
            'front', bearings_C_to_I(win_C, R_est, R_BC_front), R_est @ t_BC['front'],
            supervisor_config.r_w, supervisor_config.group_half_sides),
            None if win_C is None else front_model.border_margin_px(win_C))
        supervisor.on_pad(t, None if pad_C is None else camera_bearings_from_body(
            'down', bearings_C_to_I(pad_C, R_est, R_BC_down), R_est @ t_BC['down'],
            supervisor_config.r_w, supervisor_config.group_half_sides, tuple(groups)), groups)
        supervisor.on_flow(t, 'front', phi_front)
        supervisor.on_flow(t, 'down', phi_down)
        if not started:
            started, _ = supervisor.start(t)
        supervisor.end_frame(t)             # the frame closed, as the supervisor node does
        mode = supervisor.mode
        out = controller.step(mode, Measurements(t, R_est, win_C, pad_C, phi_front, phi_down,
                                                 tuple(groups), specific_force_I=f_I_mean,
                                                 omega_B=Omega_B))   # the gyro, as onboard
        sp = attitude_from_force(out.F_I, out.yaw_des, m, vehicle.hover_thrust,
                                 vehicle.max_thrust_factor)
        thrust_new = sp.thrust_N
        if mode == Mode.SHUTDOWN:
            t_shutdown = t if t_shutdown is None else t_shutdown
            thrust_new *= shutdown_thrust_scale(t - t_shutdown, config.shutdown_ramp_s)
        pending.append((t + config.command_delay_s + loop.delay_s, sp.R_IB_des, thrust_new))
        log.t_ctrl.append(t)
        log.R_IB.append(R.copy())
        log.Omega_B.append(np.array(Omega_B, dtype=float))
        log.F_I.append(out.F_I)
        log.mode.append(int(mode))
        log.q_w_bar.append(out.features.q_w_bar)
        log.q_t.append(out.features.q_t)
        log.phi_t.append(out.features.phi_t)
        log.phi_w.append(out.features.phi_w)
        if mode == Mode.FAILSAFE or not started:
            break
        # --- physics substeps until the next frame ---------------------------------------
        done = False
        f_I_sum = np.zeros(3)       # the IMU's specific force v' - g e3, mean over the frame
        for _ in range(n_sub):
            dt = config.physics_dt
            while pending and pending[0][0] <= t + 1e-9:   # the setpoint reaches the vehicle
                _, R_d, thrust_d = pending.popleft()
            R_err = estimate_error(t)
            # the loop holds the estimate R R_err at R_d: the truth goes to R_d R_err^T
            R, Omega_B = loop.step(R, Omega_B, R_d if R_err is None else R_d @ R_err.T, dt)
            thrust += (thrust_d - thrust) * min(dt / config.thrust_tau, 1.0)
            a = -thrust * (R @ e3) / m + g * e3 + wind_accel_steady + wind.force_I(t) / m
            if R_err is None:
                f_I_sum += a - g * e3 + R @ accel_bias_B     # what the IMU reports, in {I}
            else:       # the IMU's specific force (FRD), put into {I} with the estimate
                f_I_sum += R @ R_err @ (R.T @ (a - g * e3) + accel_bias_B)
            v = v + a * dt
            xi = xi + v * dt
            t += dt
            log.truth.append(t, xi, v)
            if floor_clearance(xi, world, vehicle.envelope_height) <= 0.0 or \
                    obstacle_clearance(xi, world, vehicle.envelope_radius,
                                       vehicle.envelope_height)[0] <= 0.0:
                done = True
                break
        if done:
            break
        f_I_mean = f_I_sum / n_sub + accel_noise(R if R_err is None else R @ R_err)
    modes = [(int(tr.to_mode), tr.t) for tr in supervisor.transitions]
    log.transitions = [(int(tr.to_mode), float(tr.t), tr.reason)
                       for tr in supervisor.transitions]
    tt, xx, vv = log.truth.arrays()
    if len(tt) == 0:
        log.truth.append(t, xi, v)
        tt, xx, vv = log.truth.arrays()
    summary = evaluate_run(tt, xx, vv, world, vehicle.envelope_radius, vehicle.envelope_height,
                           [(0, 0.0)] + modes)
    return summary, log
