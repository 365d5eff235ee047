"""Lever arms in closed loop: cameras off the body origin, told (vehicle.yaml t_BC) or not.

The feature-level loop's cameras see from their optical centres (xi + R_IB t_BC): a down
camera 8 cm forward of the centre, not told to the controller, lands the camera on the pad
and the body 8 cm off it; told, the features are re-taken from the body origin and the body
lands on the pad as without a lever arm.
"""
import dataclasses

import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_control.config import ForceControllerNodeConfig, ModeSupervisorNodeConfig
from ibvs_harness.feature_sim import FeatureSimConfig, run_feature_scenario
from ibvs_sim.core.world import load_world

WORLD, PAD, VEHICLE = load_world(), load_pad_layout(), load_vehicle()


def with_lever_arms(vehicle, front, down):
    cams = dict(vehicle.cameras)
    cams['front'] = dataclasses.replace(cams['front'], t_BC=np.array(front, float))
    cams['down'] = dataclasses.replace(cams['down'], t_BC=np.array(down, float))
    return dataclasses.replace(vehicle, cameras=cams)


def fly(true_vehicle, onboard_vehicle):
    ctrl = ForceControllerNodeConfig().controller_config(onboard_vehicle, WORLD.window.width,
                                                         PAD)
    sup = ModeSupervisorNodeConfig().supervisor_config(WORLD.window.width, PAD)
    cfg = FeatureSimConfig(initial_position_I=np.asarray(WORLD.initial_position_I, float),
                           initial_yaw=WORLD.initial_yaw, wind_accel_I=np.zeros(3),
                           crossing_law=ctrl.crossing_law, max_time_s=60.0)
    summary, log = run_feature_scenario(WORLD, PAD, true_vehicle, ctrl, sup, cfg)
    return summary, log.truth.arrays()[1][-1]


@pytest.mark.slow
def test_a_down_camera_eight_centimetres_forward_lands_the_body_on_the_pad_only_when_told():
    true = with_lever_arms(VEHICLE, (0.06, 0.0, 0.04), (0.08, 0.0, 0.02))
    told, xi_told = fly(true, true)
    untold, xi_untold = fly(true, VEHICLE)
    print(f"\ntold: landing {told['landing']}, crossing clearance "
          f"{told['window']['min_clearance_m']:.3f} m; not told: {untold['landing']}, "
          f"body at x = {xi_untold[0]:+.3f} m")
    assert told['success'] and told['landing']['error_m'] < 0.03
    # not told, the controller flies the camera onto the pad: the body ~8 cm behind it
    assert untold['landing']['landed'] and xi_untold[0] == pytest.approx(-0.08, abs=0.03)
