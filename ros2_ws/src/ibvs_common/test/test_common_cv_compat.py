"""cv_compat: the ArUco calls work on the installed OpenCV (CI runs this on 4.6 and on >= 4.7)."""
import cv2
import numpy as np

from ibvs_common.core.cv_compat import (aruco_marker_image, aruco_parameters,
                                        ArucoMarkerDetector, has_aruco_detector)

SIDE_PX = 120
MARGIN_PX = 40


def dictionary():
    return cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)


def scene(marker_id: int) -> np.ndarray:
    """One marker on white, at (MARGIN_PX, MARGIN_PX)."""
    img = np.full((SIDE_PX + 2 * MARGIN_PX,) * 2, 255, np.uint8)
    img[MARGIN_PX:MARGIN_PX + SIDE_PX, MARGIN_PX:MARGIN_PX + SIDE_PX] = aruco_marker_image(
        dictionary(), marker_id, SIDE_PX)
    return img


def test_the_api_is_the_one_this_opencv_has():
    assert has_aruco_detector() == hasattr(cv2.aruco, 'ArucoDetector')
    print(f'OpenCV {cv2.__version__}: ArucoDetector API {has_aruco_detector()}')


def test_a_drawn_marker_is_black_bordered_and_read_back_with_its_id_and_corners():
    img = aruco_marker_image(dictionary(), 7, SIDE_PX)
    assert img.shape == (SIDE_PX, SIDE_PX) and img.dtype == np.uint8
    cell = SIDE_PX // 6                                     # 4x4 bits + a 1-cell black border
    assert img[:cell].max() == 0 and img[:, :cell].max() == 0
    corners, ids = ArucoMarkerDetector(dictionary(), aruco_parameters()).detect(scene(7))
    assert ids is not None and ids.ravel().tolist() == [7]
    # the outer corners of the black border, clockwise from top-left, within a pixel
    expected = np.array([[0, 0], [SIDE_PX, 0], [SIDE_PX, SIDE_PX], [0, SIDE_PX]], float) \
        + MARGIN_PX - 0.5
    assert np.abs(np.asarray(corners[0]).reshape(4, 2) - expected).max() < 1.0


def test_changed_parameters_apply_to_the_next_detection():
    params = aruco_parameters()
    detector = ArucoMarkerDetector(dictionary(), params)
    assert detector.detect(scene(3))[1] is not None
    params.minMarkerPerimeterRate = 3.9              # a marker would need 4 x the image side
    detector.set_parameters(params)
    assert detector.detect(scene(3))[1] is None
