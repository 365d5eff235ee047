#!/usr/bin/env python3
"""Attitude step response of the sim's inner loop and of PX4 SIH, each fitted with one model.

The sim's autopilot stands in for PX4 (issue 13: what PX4 does that the emulation does not is
a bug of the emulation). This script measures both the same way: attitude steps (+-5 deg in
roll, then pitch, +-10 deg in yaw, 1.5 s each) and a least-squares fit of

    theta(t) = second-order response (wn, zeta) to the commanded angle, delayed by L

to each axis (grid search: L in 2 ms steps, wn, zeta). The sim's loop is vehicle.yaml's
``sim_plant`` (dynamics.py ``AttitudeController`` on the rigid body with its rotor lags).
PX4: v1.16 SIH from ../shared/px4-sitl with the Pelican's SIH parameters
(``sih_parameters``), PX4's own take-off to 5 m, then OFFBOARD attitude setpoints at 50 Hz
(thrust: hover over cos(tilt) plus a height PD on PX4's own estimate); input = PX4's own
attitude setpoint (ATTITUDE_TARGET) and output = its attitude (ATTITUDE_QUATERNION), both on
PX4's clock (time_boot_ms, 100 Hz), so the link's timing does not enter the fit. Prints one
line per axis and source. Figures: docs/sim.md "Inner attitude loop".

Usage: ``AMENT_PREFIX_PATH=$PWD/.venv .venv/bin/python scripts/attitude_response.py
[--px4-sih] [--smoke]`` (``--smoke``: the sim only, one short step per axis, coarse grid).
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

STEP_S = 1.5                        # s per step
ROLL_PITCH_STEP_RAD = math.radians(5.0)
YAW_STEP_RAD = math.radians(10.0)
FIT_DT_S = 0.004                    # s, resampling of input and output for the fit
STREAM_HZ = 100.0                   # Hz, ATTITUDE_QUATERNION and ATTITUDE_TARGET from PX4
SETPOINT_HZ = 50.0                  # Hz, our SET_ATTITUDE_TARGET
TAKEOFF_ALT_M = 5.0
AXES = ('roll', 'pitch', 'yaw')
PX4_OFFBOARD = 6                    # PX4's main mode number (DO_SET_MODE param 2)


def step_sequence(axis: str, repeats: int = 2) -> list[float]:
    """Commanded angles (rad), one per STEP_S: +A, 0, -A, 0, repeated."""
    a = YAW_STEP_RAD if axis == 'yaw' else ROLL_PITCH_STEP_RAD
    return [a, 0.0, -a, 0.0] * repeats


def second_order(u: np.ndarray, dt: float, delay_s: np.ndarray, wn: np.ndarray,
                 zeta: np.ndarray, y0: float) -> np.ndarray:
    """Return the responses (n_models, n) of every (L, wn, zeta) model to u at once.

    theta'' = wn^2 (u(t - L) - theta) - 2 zeta wn theta', semi-implicit Euler at dt,
    theta(0) = y0, theta'(0) = 0.
    """
    n = len(u)
    shift = np.rint(np.asarray(delay_s) / dt).astype(int)
    idx = np.clip(np.arange(n)[None, :] - shift[:, None], 0, n - 1)
    ud = u[idx]
    th = np.full(len(wn), float(y0))
    om = np.zeros(len(wn))
    out = np.empty((len(wn), n))
    for i in range(n):
        om += (wn * wn * (ud[:, i] - th) - 2.0 * zeta * wn * om) * dt
        th += om * dt
        out[:, i] = th
    return out


def fit(t: np.ndarray, u: np.ndarray, y: np.ndarray, coarse: bool = False) -> dict:
    """Least-squares (delay s, wn rad/s, zeta) of :func:`second_order` to y (t uniform)."""
    dt = float(t[1] - t[0])
    delays = np.arange(0.0, 0.08 + 1e-9, 0.008 if coarse else 0.002)
    wns = np.concatenate([np.arange(1.0, 16.0, 0.5 if coarse else 0.25),
                          np.arange(16.0, 40.0, 4.0 if coarse else 1.0)])
    zetas = np.arange(0.3, 1.5 + 1e-9, 0.1 if coarse else 0.05)
    W, Z = (g.ravel() for g in np.meshgrid(wns, zetas))
    best = None
    for L in delays:
        out = second_order(u, dt, np.full(len(W), L), W, Z, y[0])
        rms = np.sqrt(np.mean((out - y[None, :]) ** 2, axis=1))
        k = int(np.argmin(rms))
        if best is None or rms[k] < best['rms_rad']:
            best = {'delay_s': float(L), 'wn': float(W[k]), 'zeta': float(Z[k]),
                    'rms_rad': float(rms[k])}
    best['signal_rms_rad'] = float(np.std(y))
    return best


def sim_response(axis: str, repeats: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, commanded, actual) angle of ``axis`` of vehicle.yaml's plant, resampled."""
    from ibvs_common.core.config import load_vehicle
    from ibvs_common.core.frames import euler_zyx_from_rot, rot_from_euler_zyx
    from ibvs_sim.core.dynamics import (AttitudeController, hover_state, PlantParams,
                                        QuadrotorPlant)
    p = PlantParams.from_vehicle(load_vehicle())
    plant, inner = QuadrotorPlant(p), AttitudeController(p)
    s = hover_state(p, np.array([0.0, 0.0, -10.0]), np.eye(3))
    k = AXES.index(axis)
    t, cmd, act = [], [], []
    for value in step_sequence(axis, repeats):
        e = np.zeros(3)
        e[k] = value
        R_d = rot_from_euler_zyx(*e)
        u_hover = 1.0 / p.max_thrust_factor / (math.cos(e[0]) * math.cos(e[1]))
        for _ in range(int(round(STEP_S / p.dt))):
            s = plant.step(s, inner.rotor_commands(s, R_d, u_hover), np.zeros(3))
            t.append(len(t) * p.dt)
            cmd.append(value)
            act.append(euler_zyx_from_rot(s.R_IB)[k])
    return resample(np.array(t), np.array(cmd), np.array(t), np.unwrap(act))


def resample(t_u, u, t_y, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Input held (zero-order) and output interpolated on a FIT_DT_S grid over both."""
    t = np.arange(max(t_u[0], t_y[0]), min(t_u[-1], t_y[-1]), FIT_DT_S)
    i = np.clip(np.searchsorted(t_u, t, side='right') - 1, 0, len(t_u) - 1)
    return t, np.asarray(u)[i], np.interp(t, t_y, y)


def px4_response() -> dict:
    """{axis: (t, PX4's setpoint angle, PX4's angle)} from one PX4 SIH flight."""
    import os
    os.environ.setdefault('MAVLINK20', '1')
    from pymavlink import mavutil
    from ibvs_harness.px4_sih import free_instance, Pilot, Px4Sitl, px4_boot_parameters
    from ibvs_common.core.config import load_vehicle
    from ibvs_common.core.frames import (euler_zyx_from_rot, quat_from_rot, rot_from_euler_zyx,
                                         rot_from_quat)
    from ibvs_sim.core.px4_plant import sih_parameters
    mav = mavutil.mavlink
    sih = sih_parameters(load_vehicle())
    px4 = Px4Sitl(instance=free_instance(), params=px4_boot_parameters(sih, TAKEOFF_ALT_M))
    px4.start()
    pilot = Pilot(px4.instance)
    link = mavutil.mavlink_connection(f'udpin:0.0.0.0:{14540 + px4.instance}',
                                      source_system=1, source_component=191)
    state = {'z': None, 'vz': 0.0, 'yaw': None, 'target': None, 'sp': [], 'att': []}

    def read() -> None:
        pilot.poll()
        while (m := link.recv_match(blocking=False)) is not None:
            kind = m.get_type()
            if kind == 'HEARTBEAT' and state['target'] is None \
                    and m.autopilot == mav.MAV_AUTOPILOT_PX4:
                state['target'] = (m.get_srcSystem(), m.get_srcComponent())
            elif kind == 'LOCAL_POSITION_NED':
                state['z'], state['vz'] = m.z, m.vz
            elif kind == 'ATTITUDE_QUATERNION':
                R = rot_from_quat(np.array([m.q1, m.q2, m.q3, m.q4]))
                state['att'].append((m.time_boot_ms * 1e-3, euler_zyx_from_rot(R)))
                state['yaw'] = state['att'][-1][1][2]
            elif kind == 'ATTITUDE_TARGET':
                state['sp'].append((m.time_boot_ms * 1e-3, euler_zyx_from_rot(rot_from_quat(
                    np.array(m.q, dtype=float)))))

    def run_for(seconds: float, angles: np.ndarray, z_ref: float) -> None:
        hover = float(sih['MPC_THR_HOVER'])
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            read()
            z = state['z'] if state['z'] is not None else z_ref
            tilt = math.cos(angles[0]) * math.cos(angles[1])
            thrust = hover * (1.0 + 0.3 * (z - z_ref) + 0.3 * state['vz']) / tilt
            q = quat_from_rot(rot_from_euler_zyx(*angles))
            link.mav.set_attitude_target_send(0, *state['target'], 0b00000111,
                                              [float(x) for x in q], 0.0, 0.0, 0.0,
                                              float(np.clip(thrust, 0.1, 0.9)))
            time.sleep(1.0 / SETPOINT_HZ)

    try:
        err = pilot.take_off(60.0, TAKEOFF_ALT_M - 0.5)
        if err:
            raise RuntimeError(err)
        while state['target'] is None or state['yaw'] is None or state['z'] is None:
            read()
            time.sleep(0.01)
        for msg_id in (mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mav.MAVLINK_MSG_ID_ATTITUDE_TARGET):
            link.mav.command_long_send(*state['target'], mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                       msg_id, 1e6 / STREAM_HZ, 0, 0, 0, 0, 0)
        z_ref, yaw0 = state['z'], state['yaw']
        level = np.array([0.0, 0.0, yaw0])
        run_for(1.0, level, z_ref)                       # a setpoint stream before OFFBOARD
        link.mav.command_long_send(*state['target'], mav.MAV_CMD_DO_SET_MODE, 0,
                                   mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_OFFBOARD,
                                   0, 0, 0, 0, 0)
        run_for(2.0, level, z_ref)
        first_sp = {}                   # axis -> index of its first PX4 setpoint
        for k, axis in enumerate(AXES):
            first_sp[axis] = len(state['sp'])
            for value in step_sequence(axis):
                angles = level.copy()
                angles[k] += value
                run_for(STEP_S, angles, z_ref)
        out = {}
        for k, axis in enumerate(AXES):
            sp = state['sp'][first_sp[axis]:]
            t_sp = np.array([s[0] for s in sp])
            end = t_sp[0] + STEP_S * len(step_sequence(axis))
            keep = t_sp < end
            t_att = np.array([a[0] for a in state['att']])
            sel = (t_att >= t_sp[0]) & (t_att <= end)
            u = np.unwrap([s[1][k] for s in sp])[keep]
            y = np.unwrap([a[1][k] for a in state['att']])[sel]
            out[axis] = resample(t_sp[keep], u, t_att[sel], y)
        return out
    finally:
        link.close()
        pilot.close()
        px4.stop()


def report(source: str, axis: str, r: dict) -> str:
    """One line of the table."""
    return (f'{source:8s} {axis:5s} delay {1e3 * r["delay_s"]:4.0f} ms  wn {r["wn"]:5.2f} rad/s'
            f'  zeta {r["zeta"]:.2f}  fit rms {math.degrees(r["rms_rad"]):.3f} deg of '
            f'{math.degrees(r["signal_rms_rad"]):.2f}')


def main(argv: list | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--px4-sih', action='store_true', help='also fly PX4 SIH (../shared)')
    p.add_argument('--smoke', action='store_true', help='CI: the sim only, short and coarse')
    a = p.parse_args(argv)
    for axis in AXES:
        t, u, y = sim_response(axis, repeats=1 if a.smoke else 2)
        print(report('sim', axis, fit(t, u, y, coarse=a.smoke)), flush=True)
    if a.px4_sih and not a.smoke:
        from ibvs_harness.px4_sih import find_px4_sitl
        try:
            find_px4_sitl()
        except (FileNotFoundError, RuntimeError) as exc:
            print(f'attitude_response: no PX4 SITL ({exc}); PX4 not measured')
            return 0
        for axis, (t, u, y) in px4_response().items():
            print(report('px4-sih', axis, fit(t, u, y)), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
