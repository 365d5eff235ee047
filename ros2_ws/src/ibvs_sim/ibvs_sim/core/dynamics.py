"""Rigid-body quadrotor plant and the autopilot's inner attitude loop, paper frame {I}.

Paper eq:system and eq:R ({I} NED-type, z down; body FRD; SI units)::

    xi_dot = v,   m v_dot = -F_T R e3 + m g e3 + Delta,   R_dot = R S(Omega),
    J Omega_dot = -Omega x J Omega + Gamma

plus the simulator's rotors (X frame, first-order lag, limits with thrust priority), rotor
drag, wind (:class:`Wind`), the floor and a semi-implicit Euler integrator at
``physics_rate_hz``: docs/sim.md "Plant" and "Wind".
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field, replace
import math

import numpy as np

from ibvs_common.core.config import VehicleConfig
from ibvs_common.core.frames import cross3, GRAVITY, e3, rot_from_quat, skew

SIM_PLANT_KEY = 'sim_plant'
MAX_SETPOINT_DELAY_S = 0.1            # s, an autopilot slower than this is a config error
N_ROTORS = 4
# X configuration: rotor azimuths from x_B (FRD, clockwise seen from above) and spin senses
# (+1: CCW seen from above, reaction torque +k_m T along z_B; -1: CW).
ROTOR_AZIMUTHS_RAD = (math.pi / 4, 3 * math.pi / 4, 5 * math.pi / 4, 7 * math.pi / 4)
ROTOR_SPIN = (+1.0, -1.0, +1.0, -1.0)   # front-right CCW, rear-right CW, rear-left CCW, ...


class PlantConfigError(ValueError):
    """The ``sim_plant`` section of vehicle.yaml is missing or invalid."""


@dataclass(frozen=True)
class PlantParams:
    """Physical and inner-loop parameters of the plant (SI)."""

    mass: float                       # kg
    inertia_diag: np.ndarray          # kg m^2, J = diag(...), body FRD
    arm_length: float                 # m
    max_thrust_factor: float          # F_max / (m g)
    rotor_thrust_max: float           # N per rotor
    rotor_thrust_min: float           # N per rotor
    tau_up: float                     # s
    tau_down: float                   # s
    moment_constant: float            # m (yaw torque per newton of rotor thrust)
    drag_coefficient: float           # N s/m
    physics_rate_hz: float            # Hz
    attitude_wn: float                # rad/s, roll/pitch
    attitude_zeta: float
    yaw_wn: float                     # rad/s
    envelope_height: float            # m, for the floor contact
    floor_z: float = 0.0              # m, {I}
    yaw_zeta: float = 0.8
    setpoint_delay_s: float = 0.0     # s, the autopilot's setpoint -> inner loop latency

    @property
    def dt(self) -> float:
        """Physics step (s)."""
        return 1.0 / self.physics_rate_hz

    @property
    def inner_wn(self) -> np.ndarray:
        """Inner-loop natural frequency per body axis (roll, pitch, yaw), rad/s."""
        return np.array([self.attitude_wn, self.attitude_wn, self.yaw_wn])

    @property
    def inner_zeta(self) -> np.ndarray:
        """Inner-loop damping ratio per body axis (roll, pitch, yaw)."""
        return np.array([self.attitude_zeta, self.attitude_zeta, self.yaw_zeta])

    @property
    def max_collective_thrust(self) -> float:
        """F_max = max_thrust_factor m g (N), what normalised thrust 1 commands."""
        return self.max_thrust_factor * self.mass * GRAVITY

    @classmethod
    def from_vehicle(cls, vehicle: VehicleConfig, floor_z: float = 0.0) -> 'PlantParams':
        """Build from vehicle.yaml (its ``sim_plant`` section). Raises PlantConfigError."""
        sp = vehicle.raw.get(SIM_PLANT_KEY)
        if not isinstance(sp, dict):
            raise PlantConfigError(f'vehicle.yaml has no {SIM_PLANT_KEY!r} mapping')
        try:
            p = cls(mass=vehicle.mass,
                    inertia_diag=np.array(sp['inertia_diag'], dtype=float).reshape(3),
                    arm_length=vehicle.arm_length,
                    max_thrust_factor=vehicle.max_thrust_factor,
                    rotor_thrust_max=float(sp['rotor_thrust_max']),
                    rotor_thrust_min=float(sp['rotor_thrust_min']),
                    tau_up=float(sp['rotor_time_constant_up']),
                    tau_down=float(sp['rotor_time_constant_down']),
                    moment_constant=float(sp['rotor_moment_constant']),
                    drag_coefficient=float(sp['rotor_drag_coefficient']),
                    physics_rate_hz=float(sp['physics_rate_hz']),
                    attitude_wn=float(sp['attitude_natural_frequency']),
                    attitude_zeta=float(sp['attitude_damping']),
                    yaw_wn=float(sp['yaw_natural_frequency']),
                    yaw_zeta=float(sp['yaw_damping']),
                    setpoint_delay_s=float(sp['setpoint_delay']),
                    envelope_height=vehicle.envelope_height,
                    floor_z=float(floor_z))
        except (KeyError, TypeError, ValueError) as exc:
            raise PlantConfigError(f'{SIM_PLANT_KEY}: {exc!r}') from exc
        if (np.any(p.inertia_diag <= 0) or p.rotor_thrust_max <= p.rotor_thrust_min
                or p.tau_up <= 0 or p.tau_down <= 0 or p.physics_rate_hz < 250.0
                or p.attitude_wn <= 0 or p.yaw_wn <= 0 or p.drag_coefficient < 0
                or not p.attitude_zeta > 0 or not p.yaw_zeta > 0
                or not 0.0 <= p.setpoint_delay_s <= MAX_SETPOINT_DELAY_S):
            raise PlantConfigError(f'{SIM_PLANT_KEY}: values out of range (physics_rate_hz '
                                   f'must be >= 250, setpoint_delay in [0, '
                                   f'{MAX_SETPOINT_DELAY_S}] s, dampings > 0)')
        return p


@dataclass
class State:
    """Plant state: position/velocity of the body origin in {I}, R_IB, body rates, rotors."""

    xi_I: np.ndarray                  # m
    v_I: np.ndarray                   # m/s
    R_IB: np.ndarray                  # body FRD -> {I}
    Omega_B: np.ndarray               # rad/s, body FRD
    rotor_thrust: np.ndarray = field(default_factory=lambda: np.zeros(N_ROTORS))  # N, actual

    @property
    def thrust(self) -> float:
        """Collective thrust F_T (N): the sum of the rotors' actual thrusts."""
        return float(np.sum(self.rotor_thrust))

    def copy(self) -> 'State':
        """Deep copy."""
        return State(self.xi_I.copy(), self.v_I.copy(), self.R_IB.copy(), self.Omega_B.copy(),
                     self.rotor_thrust.copy())


def hover_state(params: PlantParams, xi_I: np.ndarray, R_IB: np.ndarray) -> State:
    """State at rest at ``xi_I``, attitude ``R_IB``, rotors at hover thrust m g / 4."""
    return State(np.asarray(xi_I, float).copy(), np.zeros(3), np.asarray(R_IB, float).copy(),
                 np.zeros(3), np.full(N_ROTORS, params.mass * GRAVITY / N_ROTORS))


def rodrigues(w: np.ndarray) -> np.ndarray:
    """Return exp(S(w)), the rotation by angle |w| about w (rad)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3) + skew(w)
    K = skew(np.asarray(w) / th)
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


class Mixer:
    """X-configuration allocation: rotor thrusts <-> (F_T, Gamma_B)."""

    def __init__(self, params: PlantParams) -> None:
        L = params.arm_length
        rows = [np.ones(N_ROTORS), np.zeros(N_ROTORS), np.zeros(N_ROTORS), np.zeros(N_ROTORS)]
        for i, (a, s) in enumerate(zip(ROTOR_AZIMUTHS_RAD, ROTOR_SPIN)):
            r = L * np.array([math.cos(a), math.sin(a), 0.0])
            tau = np.cross(r, -e3) + s * params.moment_constant * e3   # per newton of T_i
            rows[1][i], rows[2][i], rows[3][i] = tau
        self.M = np.array(rows)               # [F_T; Gamma] = M T
        self.M_inv = np.linalg.inv(self.M)
        self.t_min, self.t_max = params.rotor_thrust_min, params.rotor_thrust_max

    def wrench(self, rotor_thrust: np.ndarray) -> tuple[float, np.ndarray]:
        """(F_T, Gamma_B) produced by rotor thrusts (N)."""
        w = self.M @ rotor_thrust
        return float(w[0]), w[1:]

    def allocate(self, F_T: float, Gamma_B: np.ndarray) -> np.ndarray:
        """Rotor thrusts for (F_T, Gamma_B) within limits: thrust first, torque scaled down."""
        F_T = float(np.clip(F_T, N_ROTORS * self.t_min, N_ROTORS * self.t_max))
        base = np.full(N_ROTORS, F_T / N_ROTORS)
        delta = self.M_inv[:, 1:] @ np.asarray(Gamma_B, float)
        s = 1.0
        for b, d in zip(base, delta):
            if d > 1e-12:
                s = min(s, (self.t_max - b) / d)
            elif d < -1e-12:
                s = min(s, (self.t_min - b) / d)
        return np.clip(base + max(s, 0.0) * delta, self.t_min, self.t_max)


def attitude_error(R: np.ndarray, R_d: np.ndarray) -> np.ndarray:
    """SO(3) attitude error ``e_R = vee(R_d^T R - R^T R_d) / 2`` (Lee et al. 2010), body axes.

    ``sin(theta) n`` for a rotation by theta about n from R_d to R: the angle itself for small
    errors.
    """
    E = R_d.T @ R - R.T @ R_d
    return 0.5 * np.array([E[2, 1], E[0, 2], E[1, 0]])


class AttitudeController:
    """Inner attitude loop of the autopilot: (q_IB desired, normalised thrust) -> rotor thrusts.

    PD on SO(3) (Lee, Leok, McClamroch 2010): ``e_R = vee(R_d^T R - R^T R_d) / 2``,
    ``Gamma = -K_R e_R - K_Omega Omega + Omega x J Omega`` with per-axis ``K_R = J wn^2`` and
    ``K_Omega = 2 zeta wn J`` (roll/pitch ``attitude_wn`` / ``attitude_zeta``, yaw ``yaw_wn`` /
    ``yaw_zeta``), so that small errors follow ``theta'' + 2 zeta wn theta' + wn^2 theta = 0``
    (the closed loop of an angle P loop ``K`` over a rate loop of bandwidth ``b``, as PX4's and
    ArduPilot's: ``wn^2 = K b``, ``2 zeta wn = b``). Thrust: ``F_T = u F_max``.

    The setpoint (R_d, u) reaches the loop ``setpoint_delay_s`` after it was given (rounded
    to whole physics steps; the autopilot's own latency: message handling, estimator and
    controller scheduling); until the first one arrives the loop holds the attitude it
    started from, at the first thrust. Every call is one physics step. vehicle.yaml's values
    are PX4 v1.16 SIH's measured response (docs/sim.md "Inner attitude loop").
    """

    def __init__(self, params: PlantParams) -> None:
        J = params.inertia_diag
        self.J = J
        self.K_R = J * params.inner_wn ** 2
        self.K_Omega = 2.0 * params.inner_zeta * params.inner_wn * J
        self.F_max = params.max_collective_thrust
        self.mixer = Mixer(params)
        self.delay_steps = int(round(params.setpoint_delay_s / params.dt))
        self._pending: collections.deque = collections.deque()   # (R_d, u), oldest first
        self._applied: tuple[np.ndarray, float] | None = None     # what the loop tracks

    def rotor_commands(self, state: State, R_d: np.ndarray, thrust_norm: float) -> np.ndarray:
        """Rotor thrusts (N) of one physics step, given desired attitude R_d (R_IB) and u."""
        u = float(np.clip(thrust_norm, 0.0, 1.0)) if math.isfinite(thrust_norm) else 0.0
        self._pending.append((R_d, u))
        if len(self._pending) > self.delay_steps:
            self._applied = self._pending.popleft()
        elif self._applied is None:                 # before the first setpoint arrives: hold
            self._applied = (state.R_IB.copy(), u)
        R_d, u = self._applied
        e_R = attitude_error(state.R_IB, R_d)
        Om = state.Omega_B
        Gamma = -self.K_R * e_R - self.K_Omega * Om + cross3(Om, self.J * Om)
        return self.mixer.allocate(u * self.F_max, Gamma)

    def rotor_commands_q(self, state: State, q_IB_wxyz: np.ndarray,
                         thrust_norm: float) -> np.ndarray:
        """Like :meth:`rotor_commands` with the desired attitude as a (w, x, y, z) quaternion."""
        return self.rotor_commands(state, rot_from_quat(q_IB_wxyz), thrust_norm)


@dataclass(frozen=True)
class WindConfig:
    """Disturbance Delta (N, {I}): steady force plus gusts (default: off). See :class:`Wind`.

    ``steady_force_I`` (N, {I}: x north = window normal, y east, z down), ``gust_amplitude_N``
    (N, the amplitude ``A`` of the gust of each horizontal axis, half of it vertically),
    ``gust_frequency_hz`` (Hz of sim time, the base frequency ``f``), ``gust_components``
    (``K``, sines per axis; 1 is the single sine per axis of the first model), ``seed`` (the
    random phases). Build one from campaign-style magnitudes with :meth:`from_level`.
    """

    steady_force_I: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_amplitude_N: float = 0.0
    gust_frequency_hz: float = 0.5
    seed: int = 0
    gust_components: int = 1

    @classmethod
    def from_level(cls, level_mps2: float, direction_rad: float, mass_kg: float,
                   vertical_factor: float = 0.0, gust_level: float = 0.0,
                   gust_frequency_hz: float = 0.5, gust_components: int = 1,
                   seed: int = 0) -> 'WindConfig':
        """Wind from a campaign's magnitudes: level, direction, vertical factor, gust level.

        Horizontal magnitude ``level_mps2`` (m/s^2, |Delta_h| / m), blowing TOWARDS
        ``direction_rad`` (rad from north, +x_I, towards east, +y_I; 0: a force along +x_I,
        i.e. a wind from the south). Steady force ``m a (cos psi, sin psi, vertical_factor)``
        (N, {I}; a positive vertical factor pushes down, +z_I), gust amplitude
        ``A = gust_level m a`` (N).
        """
        if not (math.isfinite(level_mps2) and level_mps2 >= 0.0 and mass_kg > 0.0
                and gust_level >= 0.0 and gust_components >= 1):
            raise ValueError('wind: level >= 0, mass > 0, gust level >= 0, components >= 1')
        f = mass_kg * level_mps2
        return cls(steady_force_I=(f * math.cos(direction_rad), f * math.sin(direction_rad),
                                   f * vertical_factor),
                   gust_amplitude_N=gust_level * f, gust_frequency_hz=gust_frequency_hz,
                   seed=int(seed), gust_components=int(gust_components))


class Wind:
    """Evaluate the disturbance force of :class:`WindConfig` at sim time t (s): N in {I}.

    ``Delta(t) = Delta_s + g(t)``, the steady force ``Delta_s`` plus, on each axis j of {I}
    (x, y, z), a sum of ``K`` sines::

        g_j(t) = A w_j / sqrt(K) sum_{k=0}^{K-1} sin(2 pi f r_j c_k t + p_jk)

    with axis weights ``w = (1, 1, 0.5)``, axis frequency ratios ``r = (1, 1.37, 0.71)``,
    component ratios ``c_k = 2^(k - (K - 1) / 2)`` (octaves centred on f; ``c_0 = 1`` for
    K = 1) and phases ``p_jk`` uniform in [0, 2 pi) from ``numpy.random.default_rng(seed)``
    (drawn as a (K, 3) array: K = 1 gives the phases of the first model). All frequencies are
    distinct, so over a long window each ``g_j`` has mean 0 and standard deviation
    ``A w_j / sqrt(2)`` whatever K (peak ``A w_j`` for K = 1, up to ``A w_j sqrt(K)``).
    Smooth, deterministic, reproducible from the seed.
    """

    FREQ_RATIOS = np.array([1.0, 1.37, 0.71])
    AXIS_WEIGHTS = np.array([1.0, 1.0, 0.5])

    def __init__(self, config: WindConfig) -> None:
        self.config = config
        self.steady = np.asarray(config.steady_force_I, float).reshape(3)
        K = int(config.gust_components)
        if K < 1:
            raise ValueError(f'wind: gust_components must be >= 1, got {K}')
        self.phases = np.random.default_rng(config.seed).uniform(0, 2 * math.pi, (K, 3))
        c = 2.0 ** (np.arange(K) - (K - 1) / 2.0)
        self.omega = 2 * math.pi * config.gust_frequency_hz * c[:, None] * self.FREQ_RATIOS
        self.amplitude = config.gust_amplitude_N * self.AXIS_WEIGHTS / math.sqrt(K)

    def force_I(self, t: float) -> np.ndarray:
        """Delta(t) in {I}, newtons."""
        if self.config.gust_amplitude_N == 0.0:
            return self.steady.copy()
        return self.steady + self.amplitude * np.sin(self.omega * t + self.phases).sum(axis=0)


class QuadrotorPlant:
    """Integrates the plant one physics step at a time (see the module docstring)."""

    def __init__(self, params: PlantParams) -> None:
        self.p = params
        self.mixer = Mixer(params)
        self.J = params.inertia_diag
        self.z_rest = params.floor_z - params.envelope_height / 2.0
        self.last_accel_I = np.zeros(3)       # m/s^2, kinematic acceleration of the last step
        self.last_specific_force_B = np.array([0.0, 0.0, -GRAVITY])  # what an IMU measures
        self.last_impact_speed = 0.0          # m/s, downward speed when the floor stopped it

    def step(self, s: State, rotor_cmd: np.ndarray, Delta_I: np.ndarray) -> State:
        """Advance one step dt with rotor commands (N) held, disturbance Delta_I (N)."""
        p, dt = self.p, self.p.dt
        cmd = np.clip(np.asarray(rotor_cmd, float), p.rotor_thrust_min, p.rotor_thrust_max)
        tau = np.where(cmd > s.rotor_thrust, p.tau_up, p.tau_down)
        T = s.rotor_thrust + (cmd - s.rotor_thrust) * (1.0 - np.exp(-dt / tau))
        F_T, Gamma = self.mixer.wrench(T)
        R = s.R_IB
        v_B = R.T @ s.v_I
        drag_I = R @ (-p.drag_coefficient * np.array([v_B[0], v_B[1], 0.0]))
        f_I = -F_T * R[:, 2] + drag_I + np.asarray(Delta_I, float)   # all but gravity
        a_I = f_I / p.mass + GRAVITY * e3
        v = s.v_I + a_I * dt
        xi = s.xi_I + 0.5 * (s.v_I + v) * dt
        Om = s.Omega_B
        Om_dot = (-cross3(Om, self.J * Om) + Gamma) / self.J
        Om = Om + Om_dot * dt
        R = R @ rodrigues(Om * dt)
        new = State(xi, v, R, Om, T)
        on_floor = xi[2] >= self.z_rest
        if on_floor:
            if s.xi_I[2] < self.z_rest and new.v_I[2] > 0.0:    # airborne before this step
                self.last_impact_speed = float(new.v_I[2])
            self._rest_on_floor(new, F_T)
        self.last_accel_I = (new.v_I - s.v_I) / dt
        self.last_specific_force_B = new.R_IB.T @ (self.last_accel_I - GRAVITY * e3)
        return new

    def _rest_on_floor(self, s: State, F_T: float) -> None:
        """Inelastic floor: stop at the floor; level and still unless thrust lifts off."""
        s.xi_I[2] = self.z_rest
        lifting = F_T * s.R_IB[2, 2] > self.p.mass * GRAVITY
        if not lifting:
            yaw = math.atan2(s.R_IB[1, 0], s.R_IB[0, 0])
            c, sn = math.cos(yaw), math.sin(yaw)
            s.R_IB = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
            s.v_I = np.zeros(3)
            s.Omega_B = np.zeros(3)
        elif s.v_I[2] > 0.0:
            s.v_I[2] = 0.0


def with_position(state: State, xi_I: np.ndarray) -> State:
    """Copy of ``state`` moved to ``xi_I``."""
    return replace(state.copy(), xi_I=np.asarray(xi_I, float).copy())
