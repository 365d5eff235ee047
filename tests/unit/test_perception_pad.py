"""Pad detector (ibvs_perception.core.pad) on rendered frames of the landing descent.

Ground truth: MarkerGroup.marker_centres_I() seen from the known pose.
"""
import cv2
import numpy as np
import pytest

from ibvs_common.core import frames
from ibvs_common.core.config import load_pad_layout, load_vehicle
from ibvs_sim.core.world import load_world
from ibvs_common.core.cv_compat import aruco_marker_image
from ibvs_perception.core.pad import (PadConfigError, PadDetector, PadDetectorConfig,
                                      aruco_dictionary, layout_errors, marker_centre_normalized)
from ibvs_sim.core.render import SceneRenderer


@pytest.fixture(scope='module')
def setup():
    layout = load_pad_layout()
    cam = load_vehicle().cameras['down']
    return layout, cam, SceneRenderer(load_world(), layout, cam)


def angle_deg(a, b):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def test_marker_centre_is_the_projective_centre_not_the_corner_mean():
    # a square seen obliquely: the image of its centre, by projecting the 3-D centre
    square = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    R = frames.rot_x(0.7)
    P = square @ R.T + np.array([0.3, -0.2, 4.0])
    xy = P[:, :2] / P[:, 2:]
    centre = np.array([0.3, -0.2, 4.0])
    np.testing.assert_allclose(marker_centre_normalized(xy), centre[:2] / centre[2],
                               atol=1e-12)
    assert np.linalg.norm(xy.mean(axis=0) - centre[:2] / centre[2]) > 1e-3


def test_unknown_dictionary_is_refused():
    with pytest.raises(PadConfigError):
        aruco_dictionary('DICT_NOPE')


def test_descent_centroid_direction_and_group_switches(setup):
    """Centroid direction within 0.5 deg from 1.8 m to 0.15 m; no jump > 1 deg at a switch."""
    layout, cam, renderer = setup
    detector = PadDetector(layout, PadDetectorConfig())
    previous, switches = None, 0
    for k, h in enumerate(np.linspace(1.8, 0.15, 60)):
        xi = np.array([0.01, -0.02, -h])
        R_IB = frames.rot_from_euler_zyx(0.04 * np.sin(k / 5), 0.03 * np.cos(k / 7),
                                         0.1 * np.sin(k / 11))
        det = detector.process(renderer.render(R_IB, xi), cam.model)
        assert len(det.bearings_C) == 4 * len(det.group_names) > 0, f'no group at {h:.2f} m'
        assert list(det.group_names) == [g.name for g in layout.groups
                                         if g.name in det.group_names]   # largest first
        p_I = frames.bearings_C_to_I(det.bearings_C, R_IB, cam.R_BC)
        truth = np.concatenate([g.marker_centres_I() for g in layout.groups
                                if g.name in det.group_names]) - xi
        truth /= np.linalg.norm(truth, axis=1, keepdims=True)
        assert angle_deg(p_I.mean(axis=0), truth.mean(axis=0)) <= 0.5
        assert np.max(np.degrees(np.arccos(np.clip(np.sum(p_I * truth, axis=1), -1, 1)))) < 1.0
        if previous is not None and previous != det.group_names:
            # the switch alone, at this pose: new measured set vs the previous set's truth
            switches += 1
            old = np.concatenate([g.marker_centres_I() for g in layout.groups
                                  if g.name in previous]) - xi
            old /= np.linalg.norm(old, axis=1, keepdims=True)
            assert angle_deg(p_I.mean(axis=0), old.mean(axis=0)) <= 1.0
        previous = det.group_names
    assert switches >= 2


def test_no_pad_gives_empty_detection(setup):
    layout, cam, renderer = setup
    det = PadDetector(layout, PadDetectorConfig()).process(
        renderer.render(np.eye(3), np.array([-3.0, 1.5, -1.0])), cam.model)
    assert det.bearings_C.shape == (0, 3) and det.group_names == ()


def test_tracked_region_finds_what_the_whole_image_finds(setup):
    """Tracking (region of interest) gives the groups and bearings of a whole-image search."""
    layout, cam, renderer = setup
    tracked = PadDetector(layout, PadDetectorConfig())
    whole = PadDetector(layout, PadDetectorConfig())
    searches = []
    for k, h in enumerate(np.linspace(1.8, 0.15, 40)):
        img = renderer.render(frames.rot_from_euler_zyx(0.04 * np.sin(k / 5), 0.03, 0.1),
                              np.array([0.01, -0.02, -h]))
        det = tracked.process(img, cam.model)
        searches.append(tracked.last_search)
        whole.reset()
        ref = whole.process(img, cam.model)
        assert whole.last_search == 'full'
        assert det.group_names == ref.group_names, f'{h:.2f} m'
        assert max(angle_deg(a, b) for a, b in zip(det.bearings_C, ref.bearings_C)) < 0.2
    assert searches[0] == 'full' and searches.count('roi') >= 30


def test_loss_in_region_searches_the_whole_image_at_once(setup):
    layout, cam, renderer = setup
    detector = PadDetector(layout, PadDetectorConfig())
    R_IB = frames.rot_from_euler_zyx(0.0, 0.0, 0.2)
    assert detector.process(renderer.render(R_IB, np.array([0.0, 0.0, -1.2])),
                            cam.model).group_names
    detector.process(renderer.render(R_IB, np.array([0.0, 0.0, -1.2])), cam.model)
    assert detector.last_search == 'roi'
    # the pad moved far in the image (new pose): the region misses it, the same frame recovers
    img = renderer.render(R_IB, np.array([0.5, 0.6, -1.2]))
    det = detector.process(img, cam.model)
    assert detector.last_search == 'roi+full'
    ref = PadDetector(layout, PadDetectorConfig()).process(img, cam.model)
    assert det.group_names == ref.group_names != ()


def test_replay_is_exact_and_opencv_settings_are_restored(setup):
    """Same frames, fresh detector: bit-identical output; OpenCV's IPP/threads left as found."""
    layout, cam, renderer = setup
    imgs = [renderer.render(frames.rot_from_euler_zyx(0.04 * np.sin(k), 0.03, 0.1),
                            np.array([0.01, -0.02, -h]))
            for k, h in enumerate(np.linspace(1.5, 0.3, 8))]
    ipp, threads = cv2.ipp.useIPP(), cv2.getNumThreads()
    runs = []
    for _ in range(2):
        detector = PadDetector(layout, PadDetectorConfig())
        runs.append([detector.process(img, cam.model) for img in imgs])
        assert cv2.ipp.useIPP() == ipp and cv2.getNumThreads() == threads
    for a, b in zip(*runs):
        assert a.group_names == b.group_names != ()
        assert np.array_equal(a.bearings_C, b.bearings_C)


def test_layout_errors_of_an_exact_view_are_zero_and_a_moved_centre_is_seen():
    """layout_errors against an independent projection of the group's squares."""
    group = load_pad_layout().groups[1]                     # B: side 0.10 m, c 0.20 m
    R, t, f = frames.rot_x(0.3) @ frames.rot_z(0.4), np.array([0.05, -0.1, 1.5]), 400.0
    h = 0.5 * group.side
    corners = []
    for c in group.marker_centres_I():
        P = (c + np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])) @ R.T + t
        corners.append(P[:, :2] / P[:, 2:])                  # other corner order than the test
    centres = np.array([marker_centre_normalized(xy) for xy in corners])
    errors, sides = layout_errors(group, corners, centres, f)
    assert np.all(errors < 1e-3) and np.all(sides > 20.0)     # px (float32 homography)
    moved = [xy + (np.array([0.05, 0.0]) if k == 2 else 0.0) for k, xy in enumerate(corners)]
    centres = np.array([marker_centre_normalized(xy) for xy in moved])
    errors, _ = layout_errors(group, moved, centres, f)
    assert errors.max() > 5.0                                # 0.05 x 400 = 20 px moved


def test_a_foreign_marker_with_a_pad_id_does_not_complete_its_group(setup):
    """Group B's marker 5 covered, a marker 5 of another size pasted beside the pad.

    Without the layout check the foreign marker completes B and moves the landmarks'
    centroid; with it, B is rejected (and named) and A's landmarks are unchanged.
    """
    layout, cam, renderer = setup
    img = renderer.render(np.eye(3), np.array([0.0, 0.0, -1.3]))
    detector = PadDetector(layout, PadDetectorConfig())
    clean = detector.process(img, cam.model)
    assert {'A', 'B'} <= set(clean.group_names) and not clean.rejected_groups
    corners = detector.detect_markers(img)[5]
    centre, radius = corners.mean(axis=0), 0.6 * np.ptp(corners, axis=0).max()
    cv2.rectangle(img, tuple(int(v) for v in centre - radius),
                  tuple(int(v) for v in centre + radius), 255, -1)         # marker 5 covered
    side = int(round(0.6 * np.ptp(corners, axis=0).max()))
    foreign = cv2.copyMakeBorder(aruco_marker_image(aruco_dictionary(layout.dictionary), 5,
                                                    side), side // 3, side // 3, side // 3,
                                 side // 3, cv2.BORDER_CONSTANT, value=255)
    y0, x0 = 20, 20                                           # top-left corner of the frame
    img[y0:y0 + foreign.shape[0], x0:x0 + foreign.shape[1]] = foreign
    assert 5 in PadDetector(layout, PadDetectorConfig()).detect_markers(img)
    unchecked = PadDetector(layout, PadDetectorConfig(max_layout_error=1e9)).process(
        img, cam.model)
    assert 'B' in unchecked.group_names                       # what the check prevents
    checked = PadDetector(layout, PadDetectorConfig()).process(img, cam.model)
    assert 'B' not in checked.group_names and checked.rejected_groups == ('B',)
    a_clean = clean.bearings_C[:4]
    np.testing.assert_allclose(checked.bearings_C[:4], a_clean, atol=1e-5)
    shift = angle_deg(unchecked.bearings_C.mean(axis=0), clean.bearings_C.mean(axis=0))
    assert shift > 1.0, shift                                 # the centroid it would move
