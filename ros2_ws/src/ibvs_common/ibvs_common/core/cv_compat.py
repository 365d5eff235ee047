"""OpenCV 4.6 and >= 4.7 behind one small API: the ArUco calls of the pad detector and the sim.

Ubuntu 24.04's python3-opencv (what rosdep installs for ``python3-opencv`` on Jazzy) is
OpenCV 4.6, whose ArUco module is the old contrib one; the PyPI wheels of this project are
>= 4.7, where ArUco moved into the main module with a new object API. The differences this
project meets:

=======================  =======================================  =============================
what                     OpenCV 4.6 (contrib aruco)               OpenCV >= 4.7
=======================  =======================================  =============================
detector parameters      ``DetectorParameters_create()``          ``DetectorParameters()``
                         (``DetectorParameters()`` segfaults on
                         use: an uninitialised C++ object)
detect markers           ``detectMarkers(img, dict,               ``ArucoDetector(dict, params)
                         parameters=params)``                     .detectMarkers(img)``
a marker's image         ``drawMarker(dict, id, side, borderBits)``  ``generateImageMarker(...)``
=======================  =======================================  =============================

Everything else the project calls (``getPredefinedDictionary``, ``DICT_*``,
``CORNER_REFINE_*``, the parameter fields) is the same in both. Nothing here is chosen by
version number: each call uses the API that the installed cv2 has.
"""
from __future__ import annotations

import cv2
import numpy as np

ARUCO_MISSING = ('this OpenCV has no ArUco module (cv2.aruco): install python3-opencv (Ubuntu, '
                 'contrib modules included) or opencv-python(-headless) >= 4.7, or '
                 'opencv-contrib-python(-headless) 4.6')


def _aruco():
    aruco = getattr(cv2, 'aruco', None)
    if aruco is None:
        raise ImportError(ARUCO_MISSING)
    return aruco


def has_aruco_detector() -> bool:
    """Return whether cv2 has the >= 4.7 object API (``cv2.aruco.ArucoDetector``)."""
    return hasattr(_aruco(), 'ArucoDetector')


def aruco_parameters() -> cv2.aruco.DetectorParameters:
    """Return default ArUco detector parameters (a ``cv2.aruco.DetectorParameters``)."""
    aruco = _aruco()
    if has_aruco_detector():
        return aruco.DetectorParameters()
    return aruco.DetectorParameters_create()


class ArucoMarkerDetector:
    """``detectMarkers`` of one dictionary with parameters that can be changed between calls."""

    def __init__(self, dictionary, parameters) -> None:
        self._aruco = _aruco()
        self._dictionary = dictionary
        self._parameters = parameters
        self._detector = (self._aruco.ArucoDetector(dictionary, parameters)
                          if has_aruco_detector() else None)

    def set_parameters(self, parameters: cv2.aruco.DetectorParameters) -> None:
        """Use ``parameters`` from the next :meth:`detect` on."""
        self._parameters = parameters
        if self._detector is not None:
            self._detector.setDetectorParameters(parameters)

    def detect(self, image: np.ndarray) -> tuple:
        """Return (corners, ids) of the markers in a mono8 image, as ``detectMarkers`` does.

        ``corners``: a sequence of (1, 4, 2) float32 arrays, ``ids``: (n, 1) int32 or None.
        """
        if self._detector is not None:
            corners, ids, _ = self._detector.detectMarkers(image)
        else:
            corners, ids, _ = self._aruco.detectMarkers(image, self._dictionary,
                                                        parameters=self._parameters)
        return corners, ids


def aruco_marker_image(dictionary: cv2.aruco.Dictionary, marker_id: int, side_px: int,
                       border_bits: int = 1) -> np.ndarray:
    """Return the mono8 image (side_px, side_px) of one marker, black border included."""
    aruco = _aruco()
    if hasattr(aruco, 'generateImageMarker'):
        return aruco.generateImageMarker(dictionary, int(marker_id), int(side_px),
                                         borderBits=int(border_bits))
    return aruco.drawMarker(dictionary, int(marker_id), int(side_px), borderBits=int(border_bits))
