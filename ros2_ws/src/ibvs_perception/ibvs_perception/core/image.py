"""Raw image buffers (as sensor_msgs/Image carries them) to 8-bit grey images, by hand.

No cv_bridge: the three encodings the cameras use are converted with numpy. Any buffer whose
size, step or encoding does not describe a valid image raises :class:`ImageFormatError` with a
readable reason, so that the nodes can log it and drop the frame.
"""
from __future__ import annotations

import cv2
import numpy as np

MONO8 = 'mono8'
BGR8 = 'bgr8'
RGB8 = 'rgb8'
#: channels per pixel of each supported encoding (all 8 bits per channel)
CHANNELS = {MONO8: 1, BGR8: 3, RGB8: 3}
SUPPORTED_ENCODINGS = tuple(CHANNELS)


class ImageFormatError(ValueError):
    """An image buffer that cannot be decoded (encoding, size, step or data length)."""


def image_to_mono8(data: 'bytes | bytearray | memoryview | np.ndarray', width: int,
                   height: int, encoding: str, step: int) -> np.ndarray:
    """Decode a raw row-major image buffer to a (height, width) uint8 grey image.

    ``step`` is the row length in bytes (it may include padding); ``data`` must hold exactly
    ``step * height`` bytes, as sensor_msgs/Image requires. Colour images are converted with
    the ITU-R BT.601 luma weights (cv2.cvtColor). Raises ImageFormatError.
    """
    if encoding not in CHANNELS:
        raise ImageFormatError(f'encoding {encoding!r} not supported {SUPPORTED_ENCODINGS}')
    if width <= 0 or height <= 0:
        raise ImageFormatError(f'image size {width}x{height} is not positive')
    channels = CHANNELS[encoding]
    if step < width * channels:
        raise ImageFormatError(f'step {step} < width {width} x {channels} byte(s)')
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else data.reshape(-1).view(np.uint8)
    if buf.size != step * height:
        raise ImageFormatError(f'data holds {buf.size} bytes, step x height = {step * height}')
    rows = buf.reshape(height, step)[:, :width * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    pixels = np.ascontiguousarray(rows.reshape(height, width, channels))
    code = cv2.COLOR_BGR2GRAY if encoding == BGR8 else cv2.COLOR_RGB2GRAY
    return cv2.cvtColor(pixels, code)
