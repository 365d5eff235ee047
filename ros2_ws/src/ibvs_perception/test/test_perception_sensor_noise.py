"""Camera read noise of the sim and its camera faults: deterministic, zero-mean, cheap."""

import numpy as np
import pytest

from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_perception.core.freeze import FrozenImageCheck
from ibvs_sim.core.sensor_noise import BANK_MARGIN_PX, ReadNoise
from ibvs_sim.core.faults import CameraFaults, fault_windows
from ibvs_sim.core.pacing import Pacing
from ibvs_sim.core.sim_core import SimConfig, Simulation

from ibvs_sim.testing import HoverAutopilot

SHAPE = (480, 752)


def scene(seed=0):
    return np.random.default_rng(seed).integers(0, 256, SHAPE, dtype=np.uint8)


def test_noise_is_zero_mean_with_the_set_std_and_saturates():
    noise = ReadNoise(1.5, SHAPE, seed=0, camera='front')
    grey = np.full(SHAPE, 128, np.uint8)
    d = np.stack([noise.apply(grey, k).astype(float) - 128 for k in range(8)])
    print(f'read noise: mean {d.mean():+.4f}, std {d.std():.3f} grey levels (sigma 1.5, '
          'rounded: sqrt(1.5^2 + 1/12) = 1.53)')
    assert abs(d.mean()) < 0.01 and d.std() == pytest.approx(np.hypot(1.5, 1 / np.sqrt(12)),
                                                             rel=0.02)
    # saturation: exactly clip(image + noise), as the sensor's ADC clips
    img = scene()
    img[:10] = 255
    img[10:20] = 0
    b, dy, dx = noise.pick(5)
    n = noise._pos[b].astype(int) - noise._neg[b].astype(int)
    expected = np.clip(img.astype(int) + n[dy:dy + SHAPE[0], dx:dx + SHAPE[1]], 0, 255)
    assert np.array_equal(noise.apply(img, 5), expected)


def test_noise_is_deterministic_per_seed_camera_and_frame():
    img = scene()
    a = ReadNoise(1.5, SHAPE, seed=3, camera='front')
    b = ReadNoise(1.5, SHAPE, seed=3, camera='front')
    assert all(np.array_equal(a.apply(img, k), b.apply(img, k)) for k in (0, 1, 17, 10_000))
    assert not np.array_equal(a.apply(img, 4), ReadNoise(1.5, SHAPE, 4, 'front').apply(img, 4))
    assert not np.array_equal(a.apply(img, 4), ReadNoise(1.5, SHAPE, 3, 'down').apply(img, 4))
    assert 0 <= min(a.pick(7)[1:]) and max(a.pick(7)[1:]) < BANK_MARGIN_PX


def test_consecutive_frames_of_a_still_scene_are_never_identical():
    noise = ReadNoise(1.5, SHAPE, seed=0, camera='down')
    check = FrozenImageCheck(1)
    img = scene()
    picks = [noise.pick(k) for k in range(500)]
    assert all(p[0] % 2 == k % 2 for k, p in enumerate(picks))   # banks alternate parity
    assert not any(check.check(noise.apply(img, k)) for k in range(500))


def test_zero_sigma_is_off_and_bad_values_are_refused():
    img = scene()
    assert ReadNoise(0.0, SHAPE, 0, 'front').apply(img, 3) is img
    for bad in (-1.0, float('nan'), 100.0):
        with pytest.raises(ValueError, match='sigma'):
            ReadNoise(bad, SHAPE, 0, 'front')
    with pytest.raises(ValueError, match='uint8'):
        ReadNoise(1.5, SHAPE, 0, 'front').apply(img[:10], 0)


def test_simulation_frames_of_a_still_vehicle_differ_only_with_noise():
    world, pad, vehicle = load_world(), load_pad_layout(), load_vehicle()

    def first_frames(sigma):
        sim = Simulation(world, pad, vehicle, HoverAutopilot(),
                         SimConfig(pacing=Pacing.LOCKSTEP, read_noise_std=sigma, noise_seed=0))
        return [sim.step_frame().images for _ in range(2)]

    plain = first_frames(0.0)
    # the vehicle hovers: the plain renders repeat (a deadlock for a frozen-camera check)
    assert np.array_equal(plain[0]['front'], plain[1]['front'])
    noisy, again = first_frames(1.5), first_frames(1.5)
    for cam in ('front', 'down'):
        assert not np.array_equal(noisy[0][cam], noisy[1][cam])
        assert all(np.array_equal(noisy[k][cam], again[k][cam]) for k in range(2))
        assert np.abs(noisy[0][cam].astype(int) - plain[0][cam]).max() <= 12


def test_camera_faults_off_and_frozen_windows():
    faults = CameraFaults(off_s={'down': (0.04, 0.08)}, frozen_s={'front': (0.02, 0.06)})
    frames = {t: {'front': np.full((2, 2), k, np.uint8), 'down': np.full((2, 2), 9 - k, np.uint8)}
              for k, t in enumerate((0.0, 0.02, 0.04, 0.06, 0.08))}
    out = {}
    for t, images in frames.items():
        out[t] = faults.apply(t, images)
        if t == 0.04:
            assert faults.held['front'][0] == 0.02
    assert out[0.0][1:] == ([], [])
    assert out[0.02][1:] == ([], ['front']) and out[0.04][1:] == (['down'], ['front'])
    # frozen: the image of the window's first frame again (the very same array)
    assert out[0.02][0]['front'] is frames[0.02]['front']
    assert out[0.04][0]['front'] is frames[0.02]['front'] and 'down' not in out[0.04][0]
    # after the window (end excluded): live again, nothing held
    assert out[0.06][0]['front'] is frames[0.06]['front'] and out[0.06][1:] == (['down'], [])
    assert out[0.08][0]['down'] is frames[0.08]['down'] and faults.held == {}
    with pytest.raises(ValueError, match='start <= end'):
        CameraFaults(frozen_s={'front': (2.0, 1.0)})


def test_camera_faults_several_windows_flat_or_as_pairs():
    """Two off windows of one camera, given flat (a ROS parameter) or as pairs (the same)."""
    for windows in ((0.02, 0.04, 0.08, 0.12), ((0.02, 0.04), (0.08, 0.12))):
        faults = CameraFaults(off_s={'down': windows})
        withheld = [t for t in (0.0, 0.02, 0.04, 0.06, 0.08, 0.1, 0.12)
                    if faults.apply(t, {'down': np.zeros((2, 2), np.uint8)})[1] == ['down']]
        assert withheld == [0.02, 0.08, 0.1]          # each [start, end): the ends excluded
    for bad in ((1.0,), (), (0.0, 1.0, 3.0, 2.0)):
        with pytest.raises(ValueError, match='fault_down'):
            fault_windows('fault_down', bad)
