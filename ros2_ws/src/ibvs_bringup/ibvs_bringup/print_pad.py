"""Print the landing pad of ``pad_layout.yaml`` at true scale: a PNG or a one-page PDF.

``ros2 run ibvs_bringup print_pad OUTPUT.png|OUTPUT.pdf [--dpi N] [--pad-layout FILE]``

The page shows the pad as the sim renders it and the pad detector reads it
(docs/onboard.md, section 5): every marker of every group, drawn by the detector's own ArUco
dictionary (``ibvs_perception.core.pad.aruco_dictionary``), at its layout size, its white
quiet zone around it, in the sim's orientation (marker columns along +y_I, rows along -x_I:
the page's top edge towards +x_I, away from the window). Around the markers: each marker's
id where it fits outside every quiet zone, a cross at the pad centre, a light outline of the
pad, a 100 mm scale bar and a legend of the groups.

True scale: a PNG carries its resolution in a ``pHYs`` chunk (pixels per metre), a PDF page
is the image at ``dpi`` (MediaBox = pixels x 72 / dpi points). Print at 100 % ("actual
size", no fit to page) and check the scale bar with a ruler.

:func:`render_pad` is ROS-free (OpenCV and numpy); :func:`png_bytes` and :func:`pdf_bytes`
use only the standard library on top of it; :func:`main` is the command line.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
import math
import os
import struct
import sys
import zlib

import cv2
import numpy as np

from ibvs_common.core.config import ConfigError, load_pad_layout, PadLayout
from ibvs_common.core.cv_compat import aruco_marker_image
from ibvs_perception.core.pad import aruco_dictionary, PadConfigError

METRES_PER_INCH = 0.0254
POINTS_PER_INCH = 72.0
DEFAULT_DPI = 150.0
MIN_DPI = 50.0                 # the smallest marker of the reference layout: 8 px per cell
MAX_DPI = 600.0
MAX_PIXELS = 250_000_000       # a 1 m pad at 600 dpi would be 550 M pixels of mono8
MARGIN_M = 0.02                # white border of the page
OUTLINE_M = 0.005              # the pad's outline, outside the outermost quiet zone
HEADER_M = 0.03                # the orientation line above the pad
SCALE_BAR_M = 0.10             # scale bar length, 10 mm ticks
TEXT_M = 0.007                 # height of the header and legend text
LINE_M = 0.012                 # legend line pitch
LABEL_FRACTION = 0.12          # id label height / marker side
OUTLINE_GRAY = 200
CROSS_GRAY = 120
LABEL_GRAY = 90
CROSS_HALF_M = 0.005
FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_PX = 22.0                # cap height of FONT at scale 1 (cv2.getTextSize)


class PrintPadError(ValueError):
    """A request that cannot be printed: bad resolution, layout or output name."""


@dataclass(frozen=True)
class PlacedMarker:
    """One marker on the page: its id, group, and its black square in pixels."""

    marker_id: int
    group: str
    x0: int                    # left column of the black square
    y0: int                    # top row
    side_px: int


@dataclass(frozen=True)
class PadPage:
    """The rendered page: mono8 image, its resolution, and where the pad and markers are."""

    image: np.ndarray
    dpi: float
    centre_px: tuple[float, float]      # the pad centre (column, row), continuous pixels
    markers: tuple[PlacedMarker, ...]
    labelled: tuple[int, ...]           # ids written beside their marker

    @property
    def pixels_per_metre(self) -> float:
        """Return the page's resolution in pixels per metre."""
        return self.dpi / METRES_PER_INCH

    @property
    def size_m(self) -> tuple[float, float]:
        """Return the page's (width, height) in metres."""
        h, w = self.image.shape
        return w / self.pixels_per_metre, h / self.pixels_per_metre


def check_dpi(dpi: float) -> float:
    """Return ``dpi`` as a float if it is a usable print resolution, else raise."""
    if not (isinstance(dpi, (int, float)) and math.isfinite(dpi)) \
            or not MIN_DPI <= dpi <= MAX_DPI:
        raise PrintPadError(f'--dpi must be a number from {MIN_DPI:g} to {MAX_DPI:g}, '
                            f'got {dpi!r}')
    return float(dpi)


def pad_half_extent(layout: PadLayout) -> float:
    """Return the half side (m) of the square holding every marker's quiet zone."""
    return max(g.c + g.side * (0.5 + layout.quiet_zone) for g in layout.groups)


def _text_scale(height_px: float) -> tuple[float, int]:
    return height_px / _FONT_PX, max(1, int(round(height_px / 12.0)))


def _put_text(img: np.ndarray, text: str, left: float, baseline: float, height_px: float,
              gray: int) -> None:
    scale, thickness = _text_scale(height_px)
    cv2.putText(img, text, (int(round(left)), int(round(baseline))), FONT, scale, int(gray),
                thickness, cv2.LINE_AA)


def _text_size(text: str, height_px: float) -> tuple[int, int]:
    scale, thickness = _text_scale(height_px)
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    return w, h


def _boxes_overlap(a: tuple, b: tuple) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def render_pad(layout: PadLayout, dpi: float = DEFAULT_DPI) -> PadPage:
    """Draw ``layout`` at ``dpi`` on a white page; return the page and where things are."""
    dpi = check_dpi(dpi)
    ppm = dpi / METRES_PER_INCH
    try:
        dictionary = aruco_dictionary(layout.dictionary)
    except PadConfigError as exc:
        raise PrintPadError(f'pad layout: {exc}') from exc
    n_ids = int(dictionary.bytesList.shape[0])
    for g in layout.groups:
        bad = [i for i in g.ids if not 0 <= i < n_ids]
        if bad:
            raise PrintPadError(f'pad layout: group {g.name} has ids {bad} outside '
                                f'{layout.dictionary} (0-{n_ids - 1})')
    e = pad_half_extent(layout)
    legend = [f'{g.name}: ids {" ".join(str(i) for i in g.ids)}, side '
              f'{g.side * 1000:g} mm, centres at +-{g.c * 1000:g} mm' for g in layout.groups]
    legend.append(f'{layout.dictionary}, quiet zone {layout.quiet_zone:g} x side, '
                  f'{dpi:g} dpi: print at 100 % (actual size)')
    width_m = 2 * (MARGIN_M + OUTLINE_M + e)
    pad_top_m = MARGIN_M + HEADER_M
    scale_top_m = pad_top_m + 2 * (OUTLINE_M + e) + 0.015
    legend_top_m = scale_top_m + 0.03
    height_m = legend_top_m + LINE_M * len(legend) + MARGIN_M
    w_px, h_px = int(round(width_m * ppm)), int(round(height_m * ppm))
    if w_px * h_px > MAX_PIXELS:
        raise PrintPadError(f'{width_m:.2f} x {height_m:.2f} m at {dpi:g} dpi is '
                            f'{w_px} x {h_px} pixels, more than {MAX_PIXELS / 1e6:g} M: '
                            'choose a lower --dpi')
    img = np.full((h_px, w_px), 255, np.uint8)
    cu, cv = width_m / 2 * ppm, (pad_top_m + OUTLINE_M + e) * ppm   # pad centre, px

    def page_px(x_i: float, y_i: float) -> tuple[float, float]:
        """Return (column, row) of a point of the pad plane: columns +y_I, rows -x_I."""
        return cu + y_i * ppm, cv - x_i * ppm

    # outline (cut line) and header
    r = (e + OUTLINE_M) * ppm
    cv2.rectangle(img, (int(round(cu - r)), int(round(cv - r))),
                  (int(round(cu + r)) - 1, int(round(cv + r)) - 1), OUTLINE_GRAY, 1)
    text_px = TEXT_M * ppm
    _put_text(img, 'TOP EDGE: +x_I, away from the window (the direction of flight)',
              MARGIN_M * ppm, (MARGIN_M + TEXT_M) * ppm, text_px, 0)
    # quiet zones (pixel boxes), markers and labels
    quiet_boxes, placed = [], []
    for g in layout.groups:
        side_px = int(round(g.side * ppm))
        q_px = layout.quiet_zone * g.side * ppm
        for mid, centre in zip(g.ids, g.marker_centres_I()):
            u, v = page_px(centre[0], centre[1])
            x0, y0 = int(round(u - side_px / 2)), int(round(v - side_px / 2))
            placed.append(PlacedMarker(int(mid), g.name, x0, y0, side_px))
            quiet_boxes.append((u - side_px / 2 - q_px, v - side_px / 2 - q_px,
                                u + side_px / 2 + q_px, v + side_px / 2 + q_px))
    # ids: beside each marker, half way between it and the pad's axis x_I (same row), where
    # the label clears every quiet zone and every other label
    labelled, label_boxes = [], []
    for g in layout.groups:
        for mid, centre in zip(g.ids, g.marker_centres_I()):
            gap = abs(centre[1]) - g.side * (0.5 + layout.quiet_zone)
            height_px = LABEL_FRACTION * g.side * ppm
            text = str(mid)
            tw, th = _text_size(text, height_px)
            u, v = page_px(centre[0], math.copysign(gap / 2, centre[1]))
            box = (u - tw / 2 - 2, v - th / 2 - 2, u + tw / 2 + 2, v + th / 2 + 2)
            if gap <= 0 or box[2] - box[0] > gap * ppm or any(
                    _boxes_overlap(box, b) for b in quiet_boxes + label_boxes):
                continue
            _put_text(img, text, u - tw / 2, v + th / 2, height_px, LABEL_GRAY)
            labelled.append(int(mid))
            label_boxes.append(box)
    # pad centre cross, if it clears the quiet zones
    a = CROSS_HALF_M * ppm
    if not any(_boxes_overlap((cu - a, cv - a, cu + a, cv + a), b) for b in quiet_boxes):
        cv2.line(img, (int(round(cu - a)), int(round(cv))), (int(round(cu + a)), int(round(cv))),
                 CROSS_GRAY, 1)
        cv2.line(img, (int(round(cu)), int(round(cv - a))), (int(round(cu)), int(round(cv + a))),
                 CROSS_GRAY, 1)
    # quiet zones white, then every marker body (a black border wins over a quiet zone, as in
    # the sim's renderer)
    for x0, y0, x1, y1 in quiet_boxes:
        img[max(0, int(round(y0))):int(round(y1)), max(0, int(round(x0))):int(round(x1))] = 255
    for m in placed:
        img[m.y0:m.y0 + m.side_px, m.x0:m.x0 + m.side_px] = aruco_marker_image(
            dictionary, m.marker_id, m.side_px, border_bits=1)
    # scale bar: a black bar of SCALE_BAR_M with 10 mm ticks below it
    bar_x0, bar_y0 = MARGIN_M * ppm, scale_top_m * ppm
    bar_len, bar_h = SCALE_BAR_M * ppm, 0.004 * ppm
    img[int(round(bar_y0)):int(round(bar_y0 + bar_h)),
        int(round(bar_x0)):int(round(bar_x0 + bar_len))] = 0
    for k in range(int(round(SCALE_BAR_M / 0.01)) + 1):
        x = int(round(bar_x0 + k * 0.01 * ppm))
        x = min(x, int(round(bar_x0 + bar_len)) - 1)
        cv2.line(img, (x, int(round(bar_y0 + bar_h))), (x, int(round(bar_y0 + 2.5 * bar_h))),
                 0, 1)
    _put_text(img, f'{SCALE_BAR_M * 1000:g} mm', bar_x0 + bar_len + 0.01 * ppm,
              bar_y0 + bar_h + text_px / 2, text_px, 0)
    for k, line in enumerate(legend):
        _put_text(img, line, MARGIN_M * ppm, (legend_top_m + TEXT_M + k * LINE_M) * ppm,
                  text_px, 0)
    return PadPage(img, dpi, (cu, cv), tuple(placed), tuple(labelled))


# --- Files ---------------------------------------------------------------------------------

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack('>I', len(data)) + kind + data + \
        struct.pack('>I', zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_chunks(png: bytes) -> list[tuple[bytes, bytes]]:
    """Return the (type, data) chunks of a PNG file's bytes (CRCs checked)."""
    if not png.startswith(PNG_SIGNATURE):
        raise ValueError('not a PNG file')
    chunks, pos = [], len(PNG_SIGNATURE)
    while pos < len(png):
        (length,) = struct.unpack('>I', png[pos:pos + 4])
        kind, data = png[pos + 4:pos + 8], png[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack('>I', png[pos + 8 + length:pos + 12 + length])
        if crc != zlib.crc32(kind + data) & 0xFFFFFFFF:
            raise ValueError(f'PNG chunk {kind!r} at byte {pos}: bad CRC')
        chunks.append((kind, data))
        pos += 12 + length
    return chunks


def png_bytes(image: np.ndarray, dpi: float) -> bytes:
    """Encode a mono8 image as PNG with a pHYs chunk of ``dpi`` (pixels per metre, rounded)."""
    ok, encoded = cv2.imencode('.png', image)
    if not ok:
        raise PrintPadError('OpenCV could not encode the PNG')
    ppm = int(round(dpi / METRES_PER_INCH))
    phys = _png_chunk(b'pHYs', struct.pack('>IIB', ppm, ppm, 1))     # unit 1: the metre
    out = [PNG_SIGNATURE]
    for kind, data in png_chunks(encoded.tobytes()):
        if kind == b'pHYs':
            continue
        out.append(_png_chunk(kind, data))
        if kind == b'IHDR':
            out.append(phys)
    return b''.join(out)


def pdf_bytes(image: np.ndarray, dpi: float) -> bytes:
    """Return a one-page PDF holding a mono8 image at ``dpi`` (the page is the image)."""
    h, w = image.shape
    width_pt, height_pt = w * POINTS_PER_INCH / dpi, h * POINTS_PER_INCH / dpi
    pixels = zlib.compress(np.ascontiguousarray(image, np.uint8).tobytes(), 6)
    content = f'q {width_pt:.4f} 0 0 {height_pt:.4f} 0 0 cm /Im0 Do Q\n'.encode('ascii')
    objects = [
        b'<< /Type /Catalog /Pages 2 0 R >>',
        b'<< /Type /Pages /Kids [3 0 R] /Count 1 >>',
        (f'<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {width_pt:.4f} {height_pt:.4f}] '
         '/Resources << /XObject << /Im0 5 0 R >> >> /Contents 4 0 R >>').encode('ascii'),
        f'<< /Length {len(content)} >>\nstream\n'.encode('ascii') + content
        + b'\nendstream',
        (f'<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray '
         f'/BitsPerComponent 8 /Filter /FlateDecode /Length {len(pixels)} >>\nstream\n'
         ).encode('ascii') + pixels + b'\nendstream',
    ]
    out = bytearray(b'%PDF-1.4\n%\xe2\xe3\xcf\xd3\n')
    offsets = []
    for number, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f'{number} 0 obj\n'.encode('ascii') + body + b'\nendobj\n'
    xref = len(out)
    out += f'xref\n0 {len(objects) + 1}\n0000000000 65535 f \n'.encode('ascii')
    for offset in offsets:
        out += f'{offset:010d} 00000 n \n'.encode('ascii')
    out += (f'trailer\n<< /Size {len(objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n'
            '%%EOF\n').encode('ascii')
    return bytes(out)


def write_pad(path: str, layout: PadLayout, dpi: float = DEFAULT_DPI) -> PadPage:
    """Render ``layout`` and write it to ``path`` (.png or .pdf); return the page."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in ('.png', '.pdf'):
        raise PrintPadError(f'{path}: the output must end in .png or .pdf')
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise PrintPadError(f'{path}: folder {folder} does not exist')
    page = render_pad(layout, dpi)
    data = png_bytes(page.image, page.dpi) if ext == '.png' else pdf_bytes(page.image, page.dpi)
    try:
        with open(path, 'wb') as f:
            f.write(data)
    except OSError as exc:
        raise PrintPadError(f'cannot write {path}: {exc}') from exc
    return page


def main(argv: list[str] | None = None) -> int:
    """Command line: write the pad; 0 on success, 2 with a one-line reason otherwise."""
    parser = argparse.ArgumentParser(
        prog='print_pad', description=__doc__.splitlines()[0],
        epilog='Print at 100 %% (actual size) and check the scale bar with a ruler.')
    parser.add_argument('output', help='OUTPUT.png or OUTPUT.pdf')
    parser.add_argument('--dpi', type=float, default=DEFAULT_DPI,
                        help=f'print resolution, {MIN_DPI:g}-{MAX_DPI:g} '
                             f'(default {DEFAULT_DPI:g})')
    parser.add_argument('--pad-layout', default=None,
                        help='pad layout YAML (default: the installed pad_layout.yaml)')
    args = parser.parse_args(argv)
    try:
        check_dpi(args.dpi)
        layout = load_pad_layout(args.pad_layout)
        page = write_pad(args.output, layout, args.dpi)
    except (ConfigError, PrintPadError) as exc:
        print(f'print_pad: {exc}', file=sys.stderr)
        return 2
    w, h = page.size_m
    print(f'print_pad: wrote {args.output}: {w * 1000:.0f} x {h * 1000:.0f} mm at '
          f'{page.dpi:g} dpi ({page.image.shape[1]} x {page.image.shape[0]} px), '
          f'{len(page.markers)} markers; print at 100 % and check the '
          f'{SCALE_BAR_M * 1000:g} mm scale bar')
    return 0


if __name__ == '__main__':
    sys.exit(main())
