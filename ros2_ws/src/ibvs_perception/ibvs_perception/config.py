"""The typed configurations of the perception nodes (ROS-free).

Each field is a ROS parameter (:func:`~ibvs_common.core.params.param`) or a group of them;
the nodes declare them with ``declare_config``.
"""
from __future__ import annotations

from dataclasses import dataclass

from ibvs_common.core.attitude_buffer import AttitudeBufferConfig
from ibvs_common.core.params import group, param
from ibvs_perception.core.flow import FlowConfig
from ibvs_perception.core.latest_only import LatestOnlyConfig
from ibvs_perception.core.pad import PadDetectorConfig
from ibvs_perception.core.window import WindowDetectorConfig

VEHICLE_FILE = ("vehicle YAML (the camera's calibration: mount, frame, rate, time offset); '' "
                '= the installed vehicle.yaml')


@dataclass(frozen=True)
class ImageInputConfig:
    """How every perception node takes its camera's images (gating, latest only, frozen)."""

    mode_gating: bool = param(
        True, 'compute this product only for the images of a mode that uses it '
        '(ibvs/supervisor_status; before the first one the latched ibvs/mode, or every image '
        'without it); false: every image')
    mode_gate_depth: int = param(
        4, 'images kept unprocessed while the mode does not use the product, processed at once '
        'if the mode switches to one that does within them (the status of a frame arrives '
        'after its image); >= 2', 2, 50)
    image_transport: str = param(
        'raw', "'raw' (sensor_msgs/Image on <camera>_camera/image_raw) | 'compressed' "
        '(sensor_msgs/CompressedImage on <camera>_camera/image_raw/compressed, decoded to '
        'mono8)')
    frozen_after_frames: int = param(
        3, 'frames: a camera whose consecutive images are bit-identical to their predecessor '
        "this many times in a row is frozen (a hung driver re-stamping its last buffer: a live "
        "sensor's read noise never repeats); its images are then dropped, nothing is published "
        'for them; integer >= 1', 1)
    latest: LatestOnlyConfig = group(LatestOnlyConfig)


@dataclass(frozen=True)
class WindowDetectorNodeConfig:
    """Parameters of the ``window_detector`` node."""

    publish_debug_image: bool = param(False,
                                      'publish window/debug_image (bgr8, the detection drawn)')
    vehicle_file: str = param('', VEHICLE_FILE + ' (the front mount, for the gyro prediction)')
    window_layout_file: str = param(
        '', "window layout YAML (aperture size and frame band: the band's proportions); '' = "
        'the installed window_layout.yaml')
    detector: WindowDetectorConfig = group(WindowDetectorConfig)
    imu: AttitudeBufferConfig = group(AttitudeBufferConfig, 'imu_')
    images: ImageInputConfig = group(ImageInputConfig)


@dataclass(frozen=True)
class PadDetectorNodeConfig:
    """Parameters of the ``pad_detector`` node."""

    pad_layout_file: str = param('', "pad layout YAML (ArUco dictionary, groups, marker "
                                 "sizes); '' = the installed pad_layout.yaml")
    vehicle_file: str = param('', VEHICLE_FILE + ' (the down camera: frame, rate, time offset)')
    detector: PadDetectorConfig = group(PadDetectorConfig)
    images: ImageInputConfig = group(ImageInputConfig)


@dataclass(frozen=True)
class OpticalFlowNodeConfig:
    """Parameters of an ``optical_flow`` node (one per camera)."""

    camera: str = param('down', "'front' (the wall plane, needs window/corners) | 'down' (the "
                        'floor): the camera, its topics and its mount R_BC')
    vehicle_file: str = param('', VEHICLE_FILE)
    max_window_age_frames: float = param(
        10.0, 'computed frames (the camera period times the frame stride), front: the wall '
        'plane comes from the newest window corners older than the image, at most this older, '
        '>= 1', 1.0)
    floor_second_plane: bool = param(
        True, 'front: the floor (eta = e3) as a second plane that may be in view below the '
        'wall, at an unknown distance (two-plane flow model, docs/perception.md); down: unused')
    flow: FlowConfig = group(FlowConfig)
    imu: AttitudeBufferConfig = group(AttitudeBufferConfig, 'imu_')
    images: ImageInputConfig = group(ImageInputConfig)

    def __post_init__(self) -> None:
        """Raise ValueError for a camera that is neither 'front' nor 'down'."""
        if self.camera not in ('front', 'down'):
            raise ValueError(f"parameter camera must be 'front' or 'down', got {self.camera!r}")
