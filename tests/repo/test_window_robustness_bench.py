"""Window detector (issue 15 items 2, 3) on degraded renders of the project's own scene.

Frames: ``ibvs_sim.core.render.SceneRenderer`` at random approach poses, with the scenes and
image degradations of ``benchmarks/bench_window_robustness.py`` (imported from there, so that
the tests and the documented table use the same frames): a dim room beyond the window (as
dark as the band), a bright object across one side of the aperture, dark and light posts
beyond the aperture, a high-contrast light-mortar brick wall, noise, motion blur, gain 0.3.
"""
from pathlib import Path

import cv2
import numpy as np
import pytest

from ibvs_common.core.camera import CameraModel
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_perception.core.window import (Reject, WindowDetector, WindowDetectorConfig,
                                         WindowStatus)
from ibvs_sim.core.render import SceneRenderer
from ibvs_sim.core.world import load_world
from script_module import load_script

BENCH = Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_window_robustness.py'
N_POSES = 15
WRONG_PX = 2.0


def _bench():
    return load_script(BENCH, 'bench_window_robustness')


bench = _bench()


@pytest.fixture(scope='module')
def scene():
    world, cam = load_world(), load_vehicle().cameras['front']
    base = SceneRenderer(world, load_pad_layout(), cam)
    poses = bench.random_poses(world, cam, N_POSES, np.random.default_rng(3))
    return world, cam, base, poses


def fresh_results(scene, name, kind=None, value=0.0, seed=0, image=None):
    """(found, wrong, corner errors px) of a fresh detector per pose, one scene/degradation.

    ``image(renderer, R_IB, xi, rng)``: the frame of a pose (default: the degradation's).
    """
    world, cam, base, poses = scene
    renderer, rng = bench.make_scene(base, name), np.random.default_rng(seed)
    found, wrong, errors = 0, 0, []
    for R_IB, xi in poses:
        img = bench.degrade(renderer.render(R_IB, xi), kind, value, rng) if image is None \
            else image(renderer, R_IB, xi, rng)
        result = WindowDetector(WindowDetectorConfig()).process(img, cam.model)
        if result.status != WindowStatus.DETECTED:
            assert result.reason in Reject.ORDER, result.reason
            continue
        found += 1
        err = np.linalg.norm(result.detection.corners_px
                             - bench.true_corners_px(world, cam, R_IB, xi), axis=1)
        wrong += bool(err.max() > WRONG_PX)
        errors.extend(err)
    return found, wrong, np.array(errors)


def test_dark_aperture_dim_room_is_found(scene):
    """Beyond the window as dark as the band: no inner edge; the band's proportions give it.

    Before: 0 of 60 (bench). The aperture corners come from the outer edges and the known band
    rectangle (a homography), checked to be a true view of it.
    """
    found, wrong, errors = fresh_results(scene, 'dim room')
    assert found == N_POSES and wrong == 0
    assert np.median(errors) <= 0.2


def test_bright_object_across_one_side_of_the_aperture(scene):
    found, wrong, errors = fresh_results(scene, 'bright side')
    assert found >= N_POSES - 2 and wrong <= 1
    assert np.median(errors) <= 0.3


def test_one_band_side_covered_by_something_bright(scene):
    """A light-grey blob across one side of the band (issue 51, the bench's ``covered side``):
    the ring is open, its convex hull is the candidate. Before: 0 of 60 (bench)."""
    world, cam = scene[:2]

    def covered(renderer, R_IB, xi, rng):
        return bench.cover_one_side(renderer.render(R_IB, xi), world, cam, R_IB, xi,
                                    bench.COVER_GREY, rng)
    found, wrong, errors = fresh_results(scene, 'sim', seed=51, image=covered)
    assert found >= N_POSES - 2 and wrong == 0
    assert np.median(errors) <= 0.3


def test_partly_occluded_aperture_posts_beyond(scene):
    """Dark and light posts across the aperture: a post beside the band is not its edge.

    Before: 14 of 60 detections had a corner off by up to 21 px (the inner edge taken at the
    far side of a dark post). A measured side that is off its predicted line is replaced.
    """
    found, wrong, errors = fresh_results(scene, 'occluded')
    assert found == N_POSES and wrong == 0
    assert np.median(errors) <= 0.3


def test_underexposed_gain_0_3(scene):
    """Gain 0.3 (band 5, wall ~30 grey levels): thresholds follow the contrast. Before: 0 %."""
    found, wrong, errors = fresh_results(scene, 'sim', 'gain', 0.3)
    assert found == N_POSES and wrong == 0
    assert np.median(errors) <= 0.3


@pytest.mark.parametrize('sigma', [10.0, 15.0])
def test_noise_fresh_detection(scene, sigma):
    """Before: 85 % at sigma 10 and 8 % at 15 (bench, 60 poses)."""
    found, wrong, errors = fresh_results(scene, 'sim', 'noise', sigma, seed=int(sigma))
    assert found >= N_POSES - 1 and wrong == 0
    assert np.median(errors) <= 0.3


@pytest.mark.parametrize('kind, value, least, median_px, max_px', [
    (None, 0.0, N_POSES, 0.2, 1.5), ('noise', 12.0, N_POSES - 1, 0.25, 1.5),
    ('blur', 6.0, N_POSES - 2, 0.6, 3.0)])
def test_light_mortar_brick_wall_fresh_search(scene, kind, value, least, median_px, max_px):
    """High-contrast light-mortar bricks: a fresh (full) search finds the window.

    Before: 11, 10 and 7 of these 15 frames (clean, sigma 12, blur 6; bench, 60 poses: 61.7,
    53.3, 23.3 %), reason "no candidate": dark bricks touching the band joined its dark
    component, whose outer boundary was no quadrilateral, and beside a black brick and the dim
    top of the room the band itself was not darker than its threshold window's mean minus
    0.15 of its contrast (a gap in the ring). Now the aperture (the ring's hole, intact) and
    the band's proportions give the outer quad, and the dark offset is at most half the local
    mean's depth above the local minimum. Corners against the projected true aperture; with
    blur the ramp biases them (a corner up to ~2.3 px off, as on the sim's own wall).
    """
    found, wrong, errors = fresh_results(scene, 'brick', kind, value, seed=int(value))
    assert found >= least
    if kind is None or kind == 'noise':
        assert wrong == 0
    assert np.median(errors) <= median_px and errors.max() <= max_px


def test_light_mortar_brick_wall_tracked_approach(scene):
    """High-contrast light-mortar bricks: no wrong corners on a tracked approach.

    On this 30-frame approach 19 frames were found before the contrast-relative thresholds,
    21 after them, 30 with the aperture-based candidates.
    """
    world, cam, base, _ = scene
    renderer = bench.make_scene(base, 'brick')
    detector, found, poses = WindowDetector(WindowDetectorConfig()), 0, \
        bench.approach(world, cam, 30)
    for R_IB, xi in poses:
        result = detector.process(renderer.render(R_IB, xi), cam.model)
        if result.detection is not None:
            found += 1
            err = np.linalg.norm(result.detection.corners_px
                                 - bench.true_corners_px(world, cam, R_IB, xi), axis=1)
            assert err.max() <= WRONG_PX
    assert found >= len(poses) - 1


@pytest.mark.parametrize('kind, value', [('noise', 15.0), ('blur', 8.0)])
def test_tracking_is_kept_under_noise_and_motion_blur(scene, kind, value):
    """One detector along an approach: a bad frame is rejected, the track is kept.

    Before: 8 % (sigma 15) and 80 % (blur 8) of the approach frames. A frame the fast path
    cannot refine keeps the tracked outline for the next (until reacquire_after_frames).
    """
    world, cam, base, _ = scene
    rng, detector = np.random.default_rng(5), WindowDetector(WindowDetectorConfig())
    poses = bench.approach(world, cam, 30)
    statuses = [detector.process(bench.degrade(base.render(R_IB, xi), kind, value, rng),
                                 cam.model).status for R_IB, xi in poses]
    assert statuses.count(WindowStatus.DETECTED) >= 0.9 * len(poses)


@pytest.mark.parametrize('first, then', [('sim', 'dim room'), ('dim room', 'sim'),
                                         ('sim', 'occluded'), ('sim', 'brick')])
def test_a_tracked_aperture_whose_view_changes_is_searched_again(scene, first, then):
    """Along one tracked approach the scene changes half-way: the room beyond the window goes
    dark (the aperture's edges change polarity, or vanish), comes back, posts appear beside the
    band, the wall turns to bricks. Before and after, the aperture takes one refine pass from
    where the band's proportions put it (single_pass_tracking); at the change that pass fails
    its checks and the aperture is searched as on a fresh frame, so no corner is wrong, and the
    one pass resumes (a dark room gives no edge at all: its aperture comes from the
    proportions, and stays searched)."""
    world, cam, base, _ = scene
    renderers = {name: bench.make_scene(base, name) for name in (first, then)}
    detector, poses = WindowDetector(WindowDetectorConfig()), bench.approach(world, cam, 40)
    inner = []
    for k, (R_IB, xi) in enumerate(poses):
        result = detector.process(renderers[first if k < 20 else then].render(R_IB, xi),
                                  cam.model)
        assert result.detection is not None, (k, result.reason)
        err = np.linalg.norm(result.detection.corners_px
                             - bench.true_corners_px(world, cam, R_IB, xi), axis=1)
        assert err.max() <= 1.0, (k, err)
        inner.append(detector.inner_single_passes)
    one_pass = np.diff(inner)                   # 1 where the frame's aperture took one pass
    if first != 'dim room':
        assert one_pass[5:19].all()             # tracked in the first scene
    if then != 'dim room':
        assert one_pass[30:].all()              # and again in the second
    if then == 'dim room':
        assert not one_pass[20:].any()
    if first == 'dim room':
        assert not one_pass[:19].any()           # no edge to refine: searched every frame


def _flat_camera() -> CameraModel:
    return CameraModel.from_camera_info(752, 480, [366.667, 0, 375.5, 0, 366.667, 239.5, 0, 0,
                                                   1], [0.0] * 5, 'plumb_bob')


def test_a_filled_dark_quad_is_not_a_window():
    """No aperture edge and not a view of the band's rectangle: rejected with a reason.

    A dark square on a lighter wall is a ring to the contour search (its flat inside is not
    darker than its own mean), but its inner edge is absent and a square is no perspective
    view of the 1.36 x 1.16 band rectangle, so the proportions may not stand in for it.
    """
    img = np.full((480, 752), 140, np.uint8)
    cv2.rectangle(img, (226, 90), (526, 390), 20, -1)
    result = WindowDetector(WindowDetectorConfig()).process(img, _flat_camera())
    assert result.status == WindowStatus.NOT_FOUND and result.reason == Reject.INNER_EDGES


@pytest.mark.parametrize('fill', ['zeros', 'white', 'noise'])
def test_featureless_or_random_frames_give_a_reason_and_no_window(fill):
    img = {'zeros': np.zeros((480, 752), np.uint8),
           'white': np.full((480, 752), 255, np.uint8),
           'noise': np.random.default_rng(0).integers(0, 256, (480, 752)).astype(np.uint8)}[fill]
    result = WindowDetector(WindowDetectorConfig()).process(img, _flat_camera())
    assert result.detection is None and result.reason in Reject.ORDER
