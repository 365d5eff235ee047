"""Raw image buffers (as sensor_msgs/Image carries them) to 8-bit grey images, by hand.

No cv_bridge: the 8-bit encodings of common camera drivers are converted with numpy and
OpenCV (names as in sensor_msgs/image_encodings.hpp):

- ``mono8``: as is;
- ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``: ITU-R BT.601 luma (cv2.cvtColor);
- ``yuv422_yuy2`` / ``yuyv`` (Y0 U Y1 V) and ``yuv422`` / ``uyvy`` (U Y0 V Y1): the Y bytes as
  they are, the luma the camera computed (video range 16-235 for most drivers; the detectors
  threshold adaptively);
- ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` (the first two rows'
  colours): demosaiced to BT.601 luma. OpenCV names a pattern by the second row's second and
  third pixels, so ``bayer_rggb8`` is OpenCV's ``BayerBG`` (as cv_bridge maps it).

Any buffer whose size, step or encoding does not describe a valid image raises
:class:`ImageFormatError` with a readable reason, so that the nodes can log it and drop the
frame.
"""
from __future__ import annotations

import cv2
import numpy as np

MONO8 = 'mono8'
BGR8 = 'bgr8'
RGB8 = 'rgb8'
#: bytes per pixel of each supported encoding
BYTES_PER_PIXEL = {
    MONO8: 1, BGR8: 3, RGB8: 3, 'bgra8': 4, 'rgba8': 4,
    'yuv422_yuy2': 2, 'yuyv': 2, 'yuv422': 2, 'uyvy': 2,
    'bayer_rggb8': 1, 'bayer_bggr8': 1, 'bayer_gbrg8': 1, 'bayer_grbg8': 1,
}
SUPPORTED_ENCODINGS = tuple(BYTES_PER_PIXEL)
#: cv2.cvtColor code to grey of the colour and Bayer encodings
_TO_GREY = {
    BGR8: cv2.COLOR_BGR2GRAY, RGB8: cv2.COLOR_RGB2GRAY,
    'bgra8': cv2.COLOR_BGRA2GRAY, 'rgba8': cv2.COLOR_RGBA2GRAY,
    'bayer_rggb8': cv2.COLOR_BayerBG2GRAY, 'bayer_bggr8': cv2.COLOR_BayerRG2GRAY,
    'bayer_gbrg8': cv2.COLOR_BayerGR2GRAY, 'bayer_grbg8': cv2.COLOR_BayerGB2GRAY,
}
#: offset of the Y byte in each 2-byte pixel of the YUV 4:2:2 encodings
_LUMA_OFFSET = {'yuv422_yuy2': 0, 'yuyv': 0, 'yuv422': 1, 'uyvy': 1}


class ImageFormatError(ValueError):
    """An image buffer that cannot be decoded (encoding, size, step or data length)."""


def image_to_mono8(data: 'bytes | bytearray | memoryview | np.ndarray', width: int,
                   height: int, encoding: str, step: int) -> np.ndarray:
    """Decode a raw row-major image buffer to a (height, width) uint8 grey image.

    ``step`` is the row length in bytes (it may include padding); ``data`` must hold exactly
    ``step * height`` bytes, as sensor_msgs/Image requires. Encodings and their conversion:
    module docstring. Raises ImageFormatError.
    """
    if encoding not in BYTES_PER_PIXEL:
        raise ImageFormatError(f'encoding {encoding!r} not supported {SUPPORTED_ENCODINGS}')
    if width <= 0 or height <= 0:
        raise ImageFormatError(f'image size {width}x{height} is not positive')
    size = BYTES_PER_PIXEL[encoding]
    if step < width * size:
        raise ImageFormatError(f'step {step} < width {width} x {size} byte(s)')
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else data.reshape(-1).view(np.uint8)
    if buf.size != step * height:
        raise ImageFormatError(f'data holds {buf.size} bytes, step x height = {step * height}')
    rows = buf.reshape(height, step)[:, :width * size]
    if encoding in _LUMA_OFFSET:
        return np.ascontiguousarray(rows[:, _LUMA_OFFSET[encoding]::2])
    if encoding not in _TO_GREY:
        return np.ascontiguousarray(rows)
    if encoding.startswith('bayer_') and (width < 2 or height < 2):
        raise ImageFormatError(f'a Bayer image needs 2x2 pixels at least, got {width}x{height}')
    pixels = np.ascontiguousarray(rows.reshape(height, width, size) if size > 1 else rows)
    return cv2.cvtColor(pixels, _TO_GREY[encoding])
