"""Pad detector (ibvs_perception.core.pad) on rendered frames of the landing descent.

Ground truth: MarkerGroup.marker_centres_I() seen from the known pose.
"""
import cv2
import numpy as np
import pytest

from ibvs_common.core import frames
from ibvs_common.core.features import centroid_feature, pad_feature
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
    """Landmarks within 0.5 deg from 1.8 m to 0.15 m; q_t (pad_feature) does not jump.

    q_t is the pad centre's direction seen through every complete group
    (features.pad_feature): the same vector whatever the groups, so at a switch it moves
    only by the groups' measurement error (here <= 0.15 deg from the truth xi / |xi| on
    every frame), not by the ring geometry of the old centroid of the groups' own centres.
    """
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
        assert angle_deg(pad_feature(p_I), xi) <= 0.15
        switches += previous is not None and previous != det.group_names
        previous = det.group_names
    assert switches >= 2


def group_centre_tolerance_deg(truth_C: np.ndarray, measured_C: np.ndarray) -> float:
    """Bound (deg) on the error of a group's centre from its marker centres' errors.

    In undistorted normalised coordinates, the centre is the crossing of the diagonals
    m0-m2 and m1-m3, each between its ends. Each end moved by at most d moves the line at
    the centre by at most d (to first order), and two lines crossing at theta, moved by at
    most d each, cross at most d sqrt(2 (1 + |cos theta|)) / sin theta away. A displacement
    in normalised coordinates turns a bearing by no more than its length (radians).
    """
    m, m_hat = truth_C[:, :2] / truth_C[:, 2:], measured_C[:, :2] / measured_C[:, 2:]
    d = np.max(np.linalg.norm(m_hat - m, axis=1))
    u, v = m[2] - m[0], m[3] - m[1]
    cos_t = abs(u @ v) / np.linalg.norm(u) / np.linalg.norm(v)
    return float(np.degrees(1.02 * d * np.sqrt(2.0 * (1.0 + cos_t)) / np.sqrt(1.0 - cos_t ** 2)))


def test_each_complete_group_alone_gives_the_feature_of_all_groups(setup):
    """Same frame: q_t from one group, from all groups and from the truth agree within the
    bound that the group's marker-centre errors allow (geometry, group_centre_tolerance_deg).

    The centroid of the groups' own marker centres (the feature before) differs between
    groups by far more, which a group switch turned into a jump of q_t.
    """
    layout, cam, renderer = setup
    by_name = {g.name: g for g in layout.groups}
    checked, old_jumps = 0, []
    for xi, euler in (((0.25, -0.1, -1.3), (0.2, -0.15, 0.3)),
                      ((-0.2, 0.3, -0.9), (-0.1, 0.2, 0.0)),
                      ((0.15, 0.1, -0.6), (0.1, 0.05, 0.0)),
                      ((0.05, -0.15, -0.45), (0.0, -0.2, 0.6)),
                      ((0.05, 0.1, -0.3), (0.1, -0.2, 0.6)),
                      ((0.0, 0.0, -1.1), (0.0, 0.0, 0.0))):
        xi, R_IB = np.array(xi), frames.rot_from_euler_zyx(*euler)
        det = PadDetector(layout, PadDetectorConfig()).process(renderer.render(R_IB, xi),
                                                               cam.model)
        assert len(det.group_names) >= 2, det.group_names
        R_CI = (R_IB @ cam.R_BC).T
        centre_C = R_CI @ -xi / np.linalg.norm(xi)             # true bearing of the pad centre
        q_all = pad_feature(det.bearings_C)
        tolerances = {}
        for k, name in enumerate(det.group_names):
            measured = det.bearings_C[4 * k:4 * k + 4]
            truth = (by_name[name].marker_centres_I() - xi) @ R_CI.T
            truth /= np.linalg.norm(truth, axis=1, keepdims=True)
            tolerances[name] = group_centre_tolerance_deg(truth, measured)
            assert tolerances[name] < 0.3                       # sub-pixel marker centres
            assert angle_deg(-pad_feature(measured), centre_C) <= tolerances[name]
            old_jumps.append((angle_deg(centroid_feature(measured),
                                        centroid_feature(det.bearings_C)),
                              np.linalg.norm(centroid_feature(measured)
                                             - centroid_feature(det.bearings_C))))
        for k, name in enumerate(det.group_names):
            one = pad_feature(det.bearings_C[4 * k:4 * k + 4])
            bound = tolerances[name] + max(tolerances.values())      # deg: both near the truth
            assert angle_deg(one, q_all) <= bound
            assert np.linalg.norm(one - q_all) <= np.radians(bound)   # |q_t| ~ 1 too
            checked += 1
    assert checked >= 12
    angles, norms = np.array(old_jumps).T
    assert angles.max() > 1.0 and np.median(norms) > 0.01     # what a switch did before


def test_small_marker_pass_completes_small_groups(setup):
    """Groups with markers of 11-16 px: completed by the upscaled pass, accurate, checked.

    Without the pass (small_marker_px 0), ArUco misses markers this small; with it, the
    group's landmarks are within 0.25 deg of the truth and pass the layout check, and a
    tracked frame gives what a fresh search of the same image gives.
    """
    layout, cam, renderer = setup
    by_name = {g.name: g for g in layout.groups}
    gained = 0
    for xi, euler, small in (((0.1, -0.05, -1.45), (0.05, -0.05, 0.2), 'C'),
                             ((-0.05, 0.1, -0.7), (-0.08, 0.04, -0.3), 'D'),
                             ((0.15, 0.1, -2.6), (0.02, 0.06, 0.1), 'B')):
        xi, R_IB = np.array(xi), frames.rot_from_euler_zyx(*euler)
        img = renderer.render(R_IB, xi)
        off = PadDetector(layout, PadDetectorConfig(small_marker_px=0.0)).process(img,
                                                                                  cam.model)
        tracked = PadDetector(layout, PadDetectorConfig())
        fresh = tracked.process(img, cam.model)
        again = tracked.process(img, cam.model)
        assert tracked.last_search == 'roi'
        assert again.group_names == fresh.group_names
        np.testing.assert_array_equal(again.bearings_C, fresh.bearings_C)
        assert not fresh.rejected_groups
        if small in off.group_names:
            continue
        gained += 1
        assert small in fresh.group_names
        k = fresh.group_names.index(small)
        truth = frames.bearings_I_to_C(by_name[small].marker_centres_I() - xi, R_IB, cam.R_BC)
        truth /= np.linalg.norm(truth, axis=1, keepdims=True)
        errors = np.degrees(np.arccos(np.clip(np.sum(
            fresh.bearings_C[4 * k:4 * k + 4] * truth, axis=1), -1.0, 1.0)))
        assert errors.max() < 0.25, errors
    assert gained >= 2


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


def test_group_weight_ramps_with_the_border_distance_and_the_marker_size():
    """Closed-form points of the two smoothstep ramps: 0 and 1 at their ends, 1/2 in the
    middle (by symmetry), their product; never below MIN_GROUP_WEIGHT."""
    from ibvs_perception.core.pad import group_weight, MIN_GROUP_WEIGHT

    def group(x0, y0, side, n=4, gap=100.0):     # n axis-aligned square markers in a row
        sq = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
        return np.stack([sq + [x0 + k * gap, y0] for k in range(n)])
    w = lambda c: group_weight(c, 752, 480, 20.0, 8.0, 24.0)   # noqa: E731
    assert w(group(100.0, 100.0, 40.0)) == 1.0                  # far inside, large
    assert w(group(10.0, 100.0, 40.0)) == pytest.approx(0.5)    # 10 px of a 20 px ramp
    assert w(group(100.0, 100.0, 16.0)) == pytest.approx(0.5)   # halfway from 8 to 24 px
    assert w(group(10.0, 100.0, 16.0)) == pytest.approx(0.25)
    assert w(group(0.0, 100.0, 40.0)) == MIN_GROUP_WEIGHT        # on the border
    assert w(group(100.0, 100.0, 7.0)) == MIN_GROUP_WEIGHT       # too small to count
    right = group(752.0 - 1.0 - 10.0 - 3 * 100.0 - 40.0, 100.0, 40.0)   # 10 px from the right
    assert w(right) == pytest.approx(0.5)
    with pytest.raises(ValueError, match='group_weight_min_side_px'):
        PadDetectorConfig(group_weight_min_side_px=30.0, group_weight_full_side_px=24.0)


def test_descent_group_weights_and_q_t_at_the_group_switches(setup):
    """On a descent beside the pad, groups leave the image at its border and appear as their
    markers grow: their weights (pad/groups) are 1 well inside and large, small at the frame a
    group comes or goes; q_t with them moves at a switch no more than between other frames
    (issue 51: <= 0.3 deg)."""
    layout, cam, renderer = setup
    detector = PadDetector(layout, PadDetectorConfig())
    previous, steps, weights_seen = None, {True: [], False: []}, []
    for k, h in enumerate(np.linspace(2.2, 0.15, 110)):
        xi = np.array([0.12 * h, -0.08 * h, -h])          # along one ray: q_t's truth is fixed
        R_IB = frames.rot_from_euler_zyx(0.04 * np.sin(k / 5), 0.03 * np.cos(k / 7), 0.0)
        det = detector.process(renderer.render(R_IB, xi), cam.model)
        assert len(det.group_weights) == len(det.group_names)
        if not det.group_names:
            previous = None
            continue
        weights_seen += list(det.group_weights)
        q = pad_feature(frames.bearings_C_to_I(det.bearings_C, R_IB, cam.R_BC),
                        weights=det.group_weights)
        assert angle_deg(q, xi) <= 0.15
        if previous is not None:
            steps[previous[0] != det.group_names].append(angle_deg(q, previous[1]))
        previous = det.group_names, q
    assert len(steps[True]) >= 5
    assert max(steps[True]) <= 0.3 and max(steps[True]) <= max(steps[False]) + 0.02
    assert max(weights_seen) == 1.0 and min(weights_seen) < 0.5
