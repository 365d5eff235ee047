"""print_pad: the printed pad is pad_layout.yaml at true scale, and the pad detector reads it.

The expected values come from the YAML file itself (read here with yaml.safe_load) and from
the definitions of the units (25.4 mm to the inch, 72 points to the inch); the sizes are
measured in the output with OpenCV contours, the PNG and PDF structures parsed here.
"""
from pathlib import Path
import re
import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
import yaml

from ibvs_bringup import print_pad
from ibvs_common.core.camera import CameraModel
from ibvs_common.core.config import load_pad_layout
from ibvs_perception.core.pad import PadDetector, PadDetectorConfig

LAYOUT_FILE = Path(__file__).resolve().parents[1] / 'config' / 'pad_layout.yaml'
RAW = yaml.safe_load(LAYOUT_FILE.read_text())
GROUPS = {g['name']: g for g in RAW['groups']}
ALL_IDS = sorted(i for g in RAW['groups'] for i in g['ids'])


def px_per_m(dpi: float) -> float:
    return dpi / 0.0254


@pytest.fixture(scope='module')
def layout():
    return load_pad_layout(LAYOUT_FILE)


def black_squares(image: np.ndarray, min_side: int = 10) -> list[tuple[int, int, int, int]]:
    """Return (x, y, w, h) of every filled-looking black square blob (the markers)."""
    mask = (image < 128).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        x, y, w, h = cv2.boundingRect(c)
        if w >= min_side and abs(w - h) <= 1 and cv2.contourArea(c) > 0.9 * w * h:
            out.append((x, y, w, h))
    return out


def expected_marker_sides_px(dpi: float) -> list[float]:
    return sorted(g['side'] * px_per_m(dpi) for g in RAW['groups'] for _ in g['ids'])


@pytest.mark.parametrize('dpi', [72.0, 150.0])
def test_marker_squares_measure_the_layout_sizes_and_places(layout, dpi):
    page = print_pad.render_pad(layout, dpi)
    squares = black_squares(page.image)
    assert len(squares) == len(ALL_IDS), squares
    measured = sorted(w for _, _, w, _ in squares)
    assert np.allclose(measured, expected_marker_sides_px(dpi), atol=1.0), \
        (measured, expected_marker_sides_px(dpi))
    # the centres: every group's 4 squares sit at (+-c, +-c) around the pad centre, which
    # is the mean of all centres (the layout is symmetric)
    centres = np.array([(x + w / 2, y + h / 2) for x, y, w, h in squares])
    pad_centre = centres.mean(axis=0)
    for (x, y, w, h), centre in zip(squares, centres):
        group = min(RAW['groups'], key=lambda g: abs(g['side'] * px_per_m(dpi) - w))
        offset = np.abs(centre - pad_centre)
        assert np.allclose(offset, group['c'] * px_per_m(dpi), atol=1.0), (group, offset)


def test_scale_bar_is_100_mm(layout):
    dpi = 100.0
    page = print_pad.render_pad(layout, dpi)
    mask = (page.image < 128).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    rects = [cv2.boundingRect(c) for c in contours]
    pad_bottom = max(y + h for x, y, w, h in black_squares(page.image))
    below = [r for r in rects if r[1] > pad_bottom]
    bar = max(below, key=lambda r: r[2])     # the widest blob under the pad
    # measured between the bar's first and last pixel column
    assert abs(bar[2] - 0.100 * px_per_m(dpi)) <= 1.0, bar


def test_detector_reads_every_id_in_the_sims_orientation(layout):
    """All 16 ids; each marker's first corner (its image's top left) at +x_I, -y_I.

    The sim draws marker image columns along +y_I and rows along -x_I (docs/sim.md
    "Cameras"); the page puts +x_I at its top edge, so a marker's first ArUco corner is its
    top left on the page, and the id sits at its layout place.
    """
    dpi = 72.0
    page = print_pad.render_pad(layout, dpi)
    found = PadDetector(layout, PadDetectorConfig()).detect_markers(page.image)
    assert sorted(found) == ALL_IDS
    # the reference layout leaves room for every id's label outside all quiet zones
    assert sorted(page.labelled) == ALL_IDS
    ppm = px_per_m(dpi)
    centres = {i: c.mean(axis=0) for i, c in found.items()}
    pad_centre = np.mean(list(centres.values()), axis=0)
    signs = [(1, 1), (1, -1), (-1, -1), (-1, 1)]      # pad_layout.yaml: the ids' order
    for g in RAW['groups']:
        for marker_id, (sx, sy) in zip(g['ids'], signs):
            col, row = centres[marker_id] - pad_centre
            x_i, y_i = -row / ppm, col / ppm
            assert np.allclose([x_i, y_i], [sx * g['c'], sy * g['c']], atol=1.5 / ppm), \
                (marker_id, x_i, y_i)
            corners = found[marker_id]
            first = corners[0] - centres[marker_id]
            assert first[0] < 0 and first[1] < 0, (marker_id, corners)


def photo_of(page: print_pad.PadPage, camera: CameraModel, position_I: np.ndarray,
             R_IC: np.ndarray, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A camera's view of the printed page lying on the floor, and the page-to-image map.

    Pinhole image of the plane z_I = 0 (z_I down, the camera above it), grey floor around
    the sheet, slight blur and read noise. Returns (mono8 image, 3x3 homography from the
    page's pixels to the image's).
    """
    ppm = page.pixels_per_metre
    cu, cv = page.centre_px
    page_to_plane = np.array([[0.0, -1.0 / ppm, cv / ppm],      # x_I from the row
                              [1.0 / ppm, 0.0, -cu / ppm],      # y_I from the column
                              [0.0, 0.0, 1.0]])
    R_CI = R_IC.T
    plane_to_image = camera.K @ np.column_stack([R_CI[:, 0], R_CI[:, 1], -R_CI @ position_I])
    shrink = 6
    small = cv2.resize(page.image, None, fx=1 / shrink, fy=1 / shrink,
                       interpolation=cv2.INTER_AREA)
    H = plane_to_image @ page_to_plane
    H_small = H @ np.diag([shrink, shrink, 1.0])
    img = cv2.warpPerspective(small, H_small, (camera.width, camera.height),
                              flags=cv2.INTER_LINEAR, borderValue=110)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.6)
    img += np.random.default_rng(seed).normal(0.0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), H


def rotation_xyz(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def test_pad_detector_finds_the_groups_in_a_photo_of_the_print(layout):
    """The project's detector on a down camera's view of the printed sheet, 1.2 m above it.

    The down camera of vehicle.yaml (pinhole part) on a level-ish vehicle: image up = body
    forward = +x_I, as the page. Each complete group's marker centres must lie where the
    true camera sees the layout's centres.
    """
    page = print_pad.render_pad(layout, 100.0)
    camera = CameraModel(752, 480, np.array([[366.667, 0.0, 375.5], [0.0, 366.667, 239.5],
                                             [0.0, 0.0, 1.0]]))
    R_BC = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R_IB = rotation_xyz(np.radians(3.0), np.radians(-4.0), np.radians(15.0))
    position = np.array([0.03, -0.04, -1.2])
    image, H = photo_of(page, camera, position, R_IB @ R_BC)
    detection = PadDetector(layout, PadDetectorConfig()).process(image, camera)
    assert {'A', 'B', 'C'} <= set(detection.group_names), detection.group_names
    assert detection.rejected_groups == ()
    ppm = page.pixels_per_metre
    cu, cv = page.centre_px
    expected = []
    for name in detection.group_names:
        g = GROUPS[name]
        for sx, sy in [(1, 1), (1, -1), (-1, -1), (-1, 1)]:
            page_px = np.array([cu + sy * g['c'] * ppm, cv - sx * g['c'] * ppm, 1.0])
            p = H @ page_px
            expected.append(p[:2] / p[2])
    error = np.linalg.norm(detection.centres_px - np.array(expected), axis=1)
    assert error.max() < 1.0, error


def png_chunks_here(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b'\x89PNG\r\n\x1a\n'
    chunks, pos = [], 8
    while pos < len(data):
        length = struct.unpack('>I', data[pos:pos + 4])[0]
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        crc = struct.unpack('>I', data[pos + 8 + length:pos + 12 + length])[0]
        assert crc == zlib.crc32(kind + body), kind
        chunks.append((kind, body))
        pos += 12 + length
    return chunks


def test_png_carries_its_resolution_in_phys(tmp_path, capsys):
    out = tmp_path / 'pad.png'
    assert print_pad.main([str(out), '--dpi', '127', '--pad-layout', str(LAYOUT_FILE)]) == 0
    assert 'wrote' in capsys.readouterr().out
    chunks = png_chunks_here(out.read_bytes())
    kinds = [k for k, _ in chunks]
    assert kinds[0] == b'IHDR' and kinds.count(b'pHYs') == 1
    assert kinds.index(b'pHYs') < kinds.index(b'IDAT')
    x_ppm, y_ppm, unit = struct.unpack('>IIB', dict(chunks)[b'pHYs'])
    assert (x_ppm, y_ppm, unit) == (5000, 5000, 1)     # 127 dpi = 5000 px/m exactly
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.ndim == 2 and image.dtype == np.uint8
    assert len(black_squares(image)) == len(ALL_IDS)


def pdf_objects(data: bytes) -> dict[int, bytes]:
    """Objects of a PDF by number, found through its xref table (offsets checked)."""
    startxref = int(re.search(rb'startxref\s+(\d+)\s+%%EOF\s*$', data).group(1))
    assert data[startxref:startxref + 4] == b'xref'
    head = re.match(rb'xref\s+0 (\d+)\s+', data[startxref:])
    count, pos = int(head.group(1)), startxref + head.end()
    objects = {}
    for number in range(count):
        entry = data[pos + 20 * number:pos + 20 * (number + 1)]
        offset, _, kind = entry.split()[:3]
        if kind == b'n':
            start = int(offset)
            assert data[start:].startswith(f'{number} 0 obj'.encode()), number
            objects[number] = data[start:data.index(b'endobj', start)]
    return objects


def test_pdf_page_is_the_pad_at_true_size(tmp_path):
    dpi = 90.0
    out = tmp_path / 'pad.pdf'
    assert print_pad.main([str(out), '--dpi', str(dpi), '--pad-layout', str(LAYOUT_FILE)]) == 0
    data = out.read_bytes()
    assert data.startswith(b'%PDF-1.')
    objects = pdf_objects(data)
    box = [float(v) for v in re.search(rb'/MediaBox \[([^\]]+)\]',
                                       b''.join(objects.values())).group(1).split()]
    image_obj = next(o for o in objects.values() if b'/Subtype /Image' in o)
    w = int(re.search(rb'/Width (\d+)', image_obj).group(1))
    h = int(re.search(rb'/Height (\d+)', image_obj).group(1))
    length = int(re.search(rb'/Length (\d+)', image_obj).group(1))
    stream = image_obj[image_obj.index(b'stream\n') + 7:][:length]
    pixels = np.frombuffer(zlib.decompress(stream), np.uint8).reshape(h, w)
    # the page is the image at the dpi: 72 points per inch of dpi pixels
    assert box[:2] == [0.0, 0.0]
    assert box[2] == pytest.approx(w * 72.0 / dpi, abs=1e-3)
    assert box[3] == pytest.approx(h * 72.0 / dpi, abs=1e-3)
    points_per_px = box[2] / w
    # the markers, measured on the page in points, are the layout's sizes in points
    squares = black_squares(pixels)
    sides_pt = sorted(s[2] * points_per_px for s in squares)
    expected_pt = sorted(g['side'] / 0.0254 * 72.0 for g in RAW['groups'] for _ in g['ids'])
    assert np.allclose(sides_pt, expected_pt, atol=points_per_px), (sides_pt, expected_pt)
    # the whole pad (outermost markers' outer edges) spans 2 (c + side / 2) of group A
    span_pt = (max(x + w_ for x, _, w_, _ in squares) - min(x for x, *_ in squares)) \
        * points_per_px
    big = max(RAW['groups'], key=lambda g: g['side'])
    assert span_pt == pytest.approx(2 * (big['c'] + big['side'] / 2) / 0.0254 * 72.0,
                                    abs=points_per_px)
    # and the page holds the pad with its quiet zones
    pad_pt = 2 * (big['c'] + big['side'] * (0.5 + RAW['quiet_zone'])) / 0.0254 * 72.0
    assert pad_pt < box[2] and pad_pt < box[3]


@pytest.mark.parametrize('args, message', [
    (['pad.png', '--dpi', '0'], '--dpi must be a number from 50 to 600'),
    (['pad.png', '--dpi', 'nan'], '--dpi must be a number'),
    (['pad.png', '--dpi', '5000'], '--dpi must be a number'),
    (['pad.jpg'], 'must end in .png or .pdf'),
    (['no/such/folder/pad.png'], 'does not exist'),
    (['pad.png', '--pad-layout', 'missing.yaml'], 'cannot read missing.yaml'),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    assert print_pad.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith('print_pad: ') and message in err and 'Traceback' not in err, err
    assert not (tmp_path / 'pad.png').exists()


def test_a_layout_with_ids_outside_its_dictionary_is_refused(tmp_path, capsys):
    bad = tmp_path / 'pad.yaml'
    bad.write_text('dictionary: DICT_4X4_50\ngroups:\n'
                   '  - {name: A, ids: [48, 49, 50, 51], side: 0.1, c: 0.2}\n')
    assert print_pad.main([str(tmp_path / 'pad.png'), '--pad-layout', str(bad)]) == 2
    assert 'ids [50, 51] outside DICT_4X4_50 (0-49)' in capsys.readouterr().err


def test_command_line_process_exits_nonzero_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, '-m', 'ibvs_bringup.print_pad',
                             str(tmp_path / 'pad.png'), '--dpi', '-3'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert 'print_pad: --dpi must be' in result.stderr and 'Traceback' not in result.stderr
