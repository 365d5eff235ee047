"""Renderer of the planar reference world (docs/spec.md section 2) for one calibrated camera.

:class:`SceneRenderer` draws the floor, the wall with its aperture and frame band, the back
wall and the pad's ArUco markers, each a textured plane warped by a homography into an
undistorted virtual pinhole image, anti-aliased along its edges, then distorted with the
camera's own model by one ``cv2.remap``. Output: mono8, noise-free (the read noise is
``sensor_noise.py``'s). World, marker orientation and method: docs/sim.md "Cameras".
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ibvs_common.core.config import CameraConfig, PadLayout
from ibvs_sim.core.world import WorldConfig
from ibvs_common.core.cv_compat import aruco_marker_image

# Virtual undistorted camera: focal length relative to the real one and margin (px).
VIRTUAL_FOCAL_SCALE = 1.0
VIRTUAL_MARGIN_PX = 3
NEAR_PLANE_M = 0.02               # clipping distance in front of the optical centre
BACKGROUND_GRAY = 70              # what is outside the modelled world (ceiling, side walls)
FLOOR_TEXEL_M = 9.0 / 2880.0      # ~3.1 mm, floor texture resolution (level 0)
WALL_TEXEL_M = 0.004              # brick wall texture resolution
BACK_WALL_TEXEL_M = 0.006
MARKER_CELL_PX = 16               # texels per ArUco cell in the marker textures (level 0)
FLOOR_STRIP_M = 1.5               # floor strips along x_I (one pyramid level each)
PYRAMID_LEVELS = 6
SUBPIXEL_SHIFT = 8                # fractional bits of polygon vertices (cv2.fillConvexPoly)
SUBPIXEL_SCALE = float(1 << SUBPIXEL_SHIFT)
# Anti-aliased edges: pixels within EDGE_BAND_HALF_PX (along the edge's minor image axis, so at
# least EDGE_BAND_HALF_PX / sqrt(2) across it) of a visible edge, and up to EDGE_BAND_EXTEND_PX
# past its ends, get their exact coverage. cv2.fillConvexPoly's mask errs by at most ~1 px.
EDGE_BAND_HALF_PX = 2
EDGE_BAND_EXTEND_PX = 2
TEXTURE_EDGE_MARGIN_PX = 1        # mask widening of surfaces whose texture draws their edge
APERTURE_CLIP_MARGIN_PX = 6       # widening of the aperture's view cone (px at its far corner)
MIN_WALL_DISTANCE_M = 0.01        # nearer to the wall plane: no aperture clip
ON_LINE_TOLERANCE_PX = 1e-3       # a clipped polygon's vertex this near an edge line is on it
FRAME_BAND_GRAY = 18
MORTAR_GRAY = 185
BRICK_SIZE_M = (0.24, 0.07)       # length along y_I, height along z_I
MORTAR_M = 0.012
ARUCO_DICTIONARIES = {'DICT_4X4_50': cv2.aruco.DICT_4X4_50,
                      'DICT_4X4_100': cv2.aruco.DICT_4X4_100,
                      'DICT_5X5_50': cv2.aruco.DICT_5X5_50,
                      'DICT_6X6_50': cv2.aruco.DICT_6X6_50}
QUIET_ZONE_GRAY = 255
_QUIET_ZONES = object()           # placeholder in the drawing order


class RenderError(ValueError):
    """Unusable pose or world description."""


# --- Textures ----------------------------------------------------------------------------

def _value_noise(rng: np.random.Generator, shape: tuple[int, int],
                 octaves: list[tuple[int, float]]) -> np.ndarray:
    """Sum of bicubically upsampled white noise, one term per (cell size px, amplitude)."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    for cell, amp in octaves:
        small = rng.random((max(2, h // cell + 2), max(2, w // cell + 2))).astype(np.float32)
        big = cv2.resize(small, ((w // cell + 2) * cell, (h // cell + 2) * cell),
                         interpolation=cv2.INTER_CUBIC)
        out += amp * big[:h, :w]
    return out


def _normalise(img: np.ndarray, lo: float = 25.0, hi: float = 230.0) -> np.ndarray:
    a, b = np.percentile(img, [1, 99])
    out = (img - a) / max(b - a, 1e-6) * (hi - lo) + lo
    return np.clip(out, 0, 255).astype(np.uint8)


def make_floor_texture(seed: int, shape: tuple[int, int], texel_m: float) -> np.ndarray:
    """Non-repeating floor texture (mono8): value noise + random patches, band-limited.

    Patches of 1.5 to 12 cm with random grey levels give corners for LK tracking; the finest
    content is about 3 texels so that minified views alias little.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    cm = 0.01 / texel_m  # texels per centimetre
    img = _value_noise(rng, shape, [(int(60 * cm), 0.8), (int(15 * cm), 0.5),
                                    (max(3, int(3 * cm)), 0.25)])
    img = _normalise(img, 60, 190).astype(np.float32)
    n_patches = int(h * w * texel_m ** 2 * 120)   # ~120 patches per square metre
    for _ in range(n_patches):
        x, y = rng.integers(0, w), rng.integers(0, h)
        a, b = rng.uniform(1.5, 12.0, 2) * cm
        grey = float(rng.choice([rng.uniform(5, 60), rng.uniform(190, 250)]))
        if rng.random() < 0.6:
            cv2.rectangle(img, (int(x), int(y)), (int(x + a), int(y + b)), grey, -1)
        else:
            cv2.ellipse(img, (int(x), int(y)), (int(a / 2), int(b / 2)),
                        float(rng.uniform(0, 180)), 0, 360, grey, -1)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_brick_texture(seed: int, shape: tuple[int, int], texel_m: float) -> np.ndarray:
    """Brick-like wall texture (mono8): staggered bricks of random grey, light mortar."""
    rng = np.random.default_rng(seed)
    h, w = shape
    img = np.full(shape, MORTAR_GRAY, np.float32)
    bw, bh = BRICK_SIZE_M[0] / texel_m, BRICK_SIZE_M[1] / texel_m
    gap = MORTAR_M / texel_m
    row = 0
    y = 0.0
    while y < h:
        x = -bw / 2.0 if row % 2 else 0.0
        while x < w:
            grey = float(rng.uniform(70, 150))
            cv2.rectangle(img, (int(round(x + gap / 2)), int(round(y + gap / 2))),
                          (int(round(x + bw - gap / 2)), int(round(y + bh - gap / 2))),
                          grey, -1)
            x += bw
        y += bh
        row += 1
    img += (_value_noise(rng, shape, [(8, 30.0), (3, 15.0)]) - 22.0)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_marker_texture(dictionary: str, marker_id: int, quiet_zone: float) -> np.ndarray:
    """Draw an ArUco marker (black border included) with a white quiet zone, cell: 16 texels."""
    if dictionary not in ARUCO_DICTIONARIES:
        raise RenderError(f'unsupported ArUco dictionary {dictionary!r}')
    d = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARIES[dictionary])
    cells = d.markerSize + 2
    side_px = cells * MARKER_CELL_PX
    marker = aruco_marker_image(d, marker_id, side_px, border_bits=1)
    q = int(round(quiet_zone * side_px))
    return cv2.copyMakeBorder(marker, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


def _pyramid(texture: np.ndarray, levels: int = PYRAMID_LEVELS) -> list[np.ndarray]:
    """Area-averaged pyramid; each level covers exactly the same rectangle as level 0."""
    out = [texture]
    for _ in range(levels - 1):
        h, w = out[-1].shape
        if h < 8 or w < 8:
            break
        out.append(cv2.resize(out[-1], ((w + 1) // 2, (h + 1) // 2),
                              interpolation=cv2.INTER_AREA))
    return out


# --- Geometry ----------------------------------------------------------------------------

@dataclass
class TexturedPlane:
    """A textured rectangle of a plane of the world, paper frame {I}.

    ``corner_I`` is the corner of texel (0, 0); ``edge_u_I`` (texture columns) and
    ``edge_v_I`` (texture rows) are the full edge vectors, metres.

    ``holes_I``: convex polygons (K, 3) in the same plane that are cut out (the aperture).
    ``polygons_I``: sub-rectangles (4, 3) drawn separately (floor strips); default the whole.
    Edges shared by two of them are inner edges: drawn without anti-aliasing (no seam).
    ``texture_edges``: the texture itself draws the polygons' edges (it continues beyond them
    with content that may be drawn there, e.g. a marker's white quiet zone): the mask is widened
    by TEXTURE_EDGE_MARGIN_PX instead of being anti-aliased.
    """

    name: str
    texture: np.ndarray
    corner_I: np.ndarray
    edge_u_I: np.ndarray
    edge_v_I: np.ndarray
    holes_I: tuple = ()
    polygons_I: tuple = ()
    texture_edges: bool = False

    def __post_init__(self) -> None:
        self.pyramid = _pyramid(self.texture)
        self.corner_I = np.asarray(self.corner_I, float)
        self.edge_u_I = np.asarray(self.edge_u_I, float)
        self.edge_v_I = np.asarray(self.edge_v_I, float)
        if not self.polygons_I:
            self.polygons_I = (self.outline_I(),)
        self.polygons_I = tuple(np.asarray(p, float) for p in self.polygons_I)
        self.holes_I = tuple(np.asarray(p, float) for p in self.holes_I)
        self.outer_edges = _outer_edges(self.polygons_I)
        self.texel_m = [max(np.linalg.norm(self.edge_u_I) / lvl.shape[1],
                            np.linalg.norm(self.edge_v_I) / lvl.shape[0])
                        for lvl in self.pyramid]

    def outline_I(self) -> np.ndarray:
        """Return the rectangle's 4 corners (4, 3) in {I}."""
        c, u, v = self.corner_I, self.edge_u_I, self.edge_v_I
        return np.array([c, c + u, c + u + v, c + v])

    def texel_frame_I(self, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(O, du, dv) with texel (s, t) centre at O + s du + t dv, for a pyramid level.

        OpenCV's convention: integer coordinates are pixel centres, so texel (0, 0) covers
        [0, du] x [0, dv] of the rectangle and its centre is corner + du/2 + dv/2.
        """
        h, w = self.pyramid[level].shape
        du, dv = self.edge_u_I / w, self.edge_v_I / h
        return self.corner_I + 0.5 * du + 0.5 * dv, du, dv


def _outer_edges(polygons: tuple) -> list[np.ndarray]:
    """Per polygon, a bool per edge (i, i+1): True unless another polygon has the same edge."""
    def key(a: np.ndarray, b: np.ndarray) -> frozenset:
        return frozenset((tuple(np.round(a, 9)), tuple(np.round(b, 9))))
    keys = [[key(p[i], p[(i + 1) % len(p)]) for i in range(len(p))] for p in polygons]
    out = []
    for k, own in enumerate(keys):
        others = {e for j, ks in enumerate(keys) if j != k for e in ks}
        out.append(np.array([e not in others for e in own]))
    return out


def clip_polygon(P: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (K, 3) to {P : n . P >= d} for all (n, d)."""
    S = P @ normals.T - offsets              # (K, planes) signed distances
    inside = S >= 0
    if inside.all():
        return P
    if not inside.any(axis=0).all():         # wholly outside one plane
        return P[:0]
    poly = P
    for n, d in zip(normals[~inside.all(axis=0)], offsets[~inside.all(axis=0)]):
        if len(poly) == 0:
            break
        s = poly @ n - d
        if np.all(s >= 0):
            continue
        if np.all(s < 0):
            return poly[:0]
        out = []
        k = len(poly)
        for i in range(k):
            j = (i + 1) % k
            if s[i] >= 0:
                out.append(poly[i])
            if (s[i] >= 0) != (s[j] >= 0):
                a = s[i] / (s[i] - s[j])
                out.append(poly[i] + a * (poly[j] - poly[i]))
        poly = np.array(out) if out else poly[:0]
    return poly


def edge_band(uv0: np.ndarray, uv1: np.ndarray, regions: list, size: tuple[int, int]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels along the image segments uv0[k] -> uv1[k] (K, 2) and their coverage.

    Band: along each segment's major axis, every integer coordinate from EDGE_BAND_EXTEND_PX
    before its start to as far past its end; across, the 2 EDGE_BAND_HALF_PX + 1 pixels around
    it; only pixels inside the image ``size`` (W, H). Pixels near two segments appear twice.

    Coverage: the product over ``regions``, (lines, hole) pairs, of a pixel's area inside the
    convex region {l . (u, v, 1) >= 0 for all lines} (1 minus it for a hole), that area being
    the product over the lines of ``clip(0.5 + l . (u, v, 1), 0, 1)`` (lines scaled to give
    signed distances in pixels). ``lines``: (L, 3), or (K, L, 3) with one set per segment.

    Returns x, y (int32), the segment index and the coverage (float32) of each pixel.
    """
    d = uv1 - uv0
    steep = np.abs(d[:, 1]) > np.abs(d[:, 0])            # major axis: y
    major = steep.astype(np.intp)
    k = np.arange(len(d))
    a0, a1, b0 = uv0[k, major], uv1[k, major], uv0[k, 1 - major]
    da = d[k, major]
    slope = d[k, 1 - major] / np.where(da == 0.0, 1.0, da)
    lo = np.floor(np.minimum(a0, a1)).astype(np.int32) - EDGE_BAND_EXTEND_PX
    counts = np.ceil(np.maximum(a0, a1)).astype(np.int32) + EDGE_BAND_EXTEND_PX - lo + 1
    # Samples: one per integer major coordinate a, at the minor coordinate b of the segment.
    seg = np.repeat(k.astype(np.int32), counts)
    a = (np.arange(counts.sum(), dtype=np.int32)
         - np.repeat((np.cumsum(counts) - counts - lo).astype(np.int32), counts))
    b = np.rint(b0[seg] + (a - a0[seg]) * slope[seg]).astype(np.int32)
    st = steep[seg]
    xs, ys = np.where(st, b, a), np.where(st, a, b)
    # Pixels: the samples moved by `offsets` across (along x for steep segments, else y).
    offsets = np.arange(-EDGE_BAND_HALF_PX, EDGE_BAND_HALF_PX + 1, dtype=np.float32)
    xf, yf = xs.astype(np.float32), ys.astype(np.float32)
    cov = np.ones((len(seg), len(offsets)), np.float32)
    for lines, hole in regions:
        L = (lines if lines.ndim == 2 else lines[seg]).astype(np.float32)
        area = np.ones_like(cov)
        for j in range(L.shape[-2]):
            la, lb = L[..., j, 0], L[..., j, 1]
            at_sample = xf * la + yf * lb + (L[..., j, 2] + np.float32(0.5))
            across = np.where(st, la, lb) * np.ones_like(xf)
            dist = at_sample[:, None] + across[:, None] * offsets
            area *= np.clip(dist, 0.0, 1.0, out=dist)
        cov *= (1.0 - area) if hole else area
    stx = st[:, None]
    off = offsets.astype(np.int32)
    x = (xs[:, None] + np.where(stx, off, 0)).ravel()
    y = (ys[:, None] + np.where(stx, 0, off)).ravel()
    inside = (x >= 0) & (x < size[0]) & (y >= 0) & (y < size[1])
    return (x[inside], y[inside], np.repeat(seg, len(offsets))[inside],
            cov.ravel()[inside])


def edges_on_lines(uv: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges (uv0, uv1) of the image polygon uv (n, 2) that lie on one of the lines (K, 3)."""
    nxt = np.arange(1, len(uv) + 1) % len(uv)
    on = np.abs(uv @ lines[:, :2].T + lines[:, 2]) < ON_LINE_TOLERANCE_PX
    keep = np.any(on & on[nxt], axis=1)
    return uv[keep], uv[nxt[keep]]


# --- Renderer ----------------------------------------------------------------------------

class SceneRenderer:
    """Render the reference world as one camera sees it (mono8, distorted as CameraInfo says)."""

    def __init__(self, world: WorldConfig, pad: PadLayout, camera: CameraConfig) -> None:
        self.world = world
        self.camera = camera
        self.R_BC = np.asarray(camera.R_BC, float)
        self.t_BC = np.asarray(camera.t_BC, float).reshape(3)    # optical centre, body FRD
        self._lever_arm = bool(np.any(self.t_BC != 0.0))
        model = camera.model
        self.width, self.height = model.width, model.height
        self._build_virtual_camera()
        self._build_planes(world, pad)
        self.overlay_planes: list[TexturedPlane] = []

    # -- set-up --
    def _build_virtual_camera(self) -> None:
        """Choose K_v covering the undistorted image and precompute the distortion map."""
        model = self.camera.model
        w, h = self.width, self.height
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        xy = model.pixels_to_normalized(np.column_stack([uu.ravel(), vv.ravel()]))
        if not np.all(np.isfinite(xy)):
            raise RenderError(f'camera {self.camera.name}: distortion not invertible')
        f = VIRTUAL_FOCAL_SCALE * float(model.K[0, 0])
        x_lo, y_lo = xy.min(axis=0)
        x_hi, y_hi = xy.max(axis=0)
        m = VIRTUAL_MARGIN_PX
        cx, cy = -x_lo * f + m, -y_lo * f + m
        self.virtual_size = (int(np.ceil(x_hi * f + cx + m)) + 1,
                             int(np.ceil(y_hi * f + cy + m)) + 1)
        self.K_v = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        self._K_v_inv = np.linalg.inv(self.K_v)
        map_x = (xy[:, 0] * f + cx).reshape(h, w).astype(np.float32)
        map_y = (xy[:, 1] * f + cy).reshape(h, w).astype(np.float32)
        self._map1, self._map2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        # View frustum of the virtual image in the optical frame: n . P >= d.
        W, H = self.virtual_size
        xl, xr = (-0.5 - cx) / f, (W - 0.5 - cx) / f
        yt, yb = (-0.5 - cy) / f, (H - 0.5 - cy) / f
        self._frustum_n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, -xl], [-1.0, 0.0, xr],
                                    [0.0, 1.0, -yt], [0.0, -1.0, yb]])
        self._frustum_d = np.array([NEAR_PLANE_M, 0.0, 0.0, 0.0, 0.0])

    def _build_planes(self, world: WorldConfig, pad: PadLayout) -> None:
        seeds = world.texture_seeds
        fz = world.floor_z
        (x0, x1), (y0, y1) = world.floor_extent_x, world.floor_extent_y
        nx = int(round((x1 - x0) / FLOOR_TEXEL_M))
        ny = int(round((y1 - y0) / FLOOR_TEXEL_M))
        floor_tex = make_floor_texture(seeds['floor'], (nx, ny), FLOOR_TEXEL_M)
        # Floor: columns along +y_I, rows along -x_I (upright for the level down camera).
        corner = np.array([x1, y0, fz])
        eu, ev = np.array([0.0, y1 - y0, 0.0]), np.array([x0 - x1, 0.0, 0.0])
        wx = world.wall_x

        def strips(xa: float, xb: float) -> tuple:
            edges = np.arange(xa, xb, FLOOR_STRIP_M).tolist() + [xb]
            return tuple(np.array([[a, y0, fz], [a, y1, fz], [b, y1, fz], [b, y0, fz]])
                         for a, b in zip(edges[:-1], edges[1:]) if b - a > 1e-9)
        self.floor_near = TexturedPlane('floor', floor_tex, corner, eu, ev,
                                        polygons_I=strips(x0, min(wx, x1)))
        self.floor_far = TexturedPlane('floor', floor_tex, corner, eu, ev,
                                       polygons_I=strips(max(wx, x0), x1))
        self.floor_far.pyramid = self.floor_near.pyramid   # share the texture memory

        # Wall x = wall_x: columns along +y_I, rows along +z_I, with the aperture as a hole.
        (wy0, wy1), (wz0, wz1) = world.wall_y_range, world.wall_z_range
        ww = int(round((wy1 - wy0) / WALL_TEXEL_M))
        wh = int(round((wz1 - wz0) / WALL_TEXEL_M))
        wall_tex = make_brick_texture(seeds['wall'], (wh, ww), WALL_TEXEL_M)
        win = world.window
        band = win.frame_band
        cy_, cz_ = win.center_I[1], win.center_I[2]
        ty = (wy1 - wy0) / ww
        tz = (wz1 - wz0) / wh
        a = (int(round((cy_ - win.width / 2 - band - wy0) / ty)),
             int(round((cz_ - win.height / 2 - band - wz0) / tz)))
        b = (int(round((cy_ + win.width / 2 + band - wy0) / ty)) - 1,
             int(round((cz_ + win.height / 2 + band - wz0) / tz)) - 1)
        cv2.rectangle(wall_tex, a, b, FRAME_BAND_GRAY, -1)
        self.wall = TexturedPlane('wall', wall_tex, np.array([wx, wy0, wz0]),
                                  np.array([0.0, wy1 - wy0, 0.0]),
                                  np.array([0.0, 0.0, wz1 - wz0]),
                                  holes_I=(win.corners_I(),))
        bw = int(round((wy1 - wy0) / BACK_WALL_TEXEL_M))
        bh = int(round((wz1 - wz0) / BACK_WALL_TEXEL_M))
        back_tex = make_floor_texture(seeds['back_wall'], (bh, bw), BACK_WALL_TEXEL_M)
        self.back_wall = TexturedPlane('back_wall', back_tex,
                                       np.array([world.back_wall_x, wy0, wz0]),
                                       np.array([0.0, wy1 - wy0, 0.0]),
                                       np.array([0.0, 0.0, wz1 - wz0]))
        # Markers: lying on the floor, columns along +y_I, rows along -x_I.
        # Quiet zones are filled white first, then all marker bodies are drawn: where the
        # quiet zone of one group overlaps the black border of another, the border wins.
        self.markers: list[TexturedPlane] = []
        self.quiet_zones_I: list[np.ndarray] = []
        for g in pad.groups:
            full = g.side * (1.0 + 2.0 * pad.quiet_zone)
            h = g.side / 2.0
            for mid, c in zip(g.ids, g.marker_centres_I()):
                tex = make_marker_texture(pad.dictionary, mid, pad.quiet_zone)
                corner = np.array([c[0] + full / 2, c[1] - full / 2, fz])
                body = np.array([[c[0] + h, c[1] - h, fz], [c[0] + h, c[1] + h, fz],
                                 [c[0] - h, c[1] + h, fz], [c[0] - h, c[1] - h, fz]])
                plane = TexturedPlane(f'marker_{mid}', tex, corner,
                                      np.array([0.0, full, 0.0]),
                                      np.array([-full, 0.0, 0.0]), polygons_I=(body,),
                                      texture_edges=True)
                self.markers.append(plane)
                self.quiet_zones_I.append(plane.outline_I())
        # Aperture clip (render): valid when what lies across the wall is within its extent.
        far = [self.floor_near, self.floor_far, self.back_wall, *self.markers]
        pts = np.concatenate([p for plane in far for p in plane.polygons_I]
                             + self.quiet_zones_I)
        self._far_within_wall = bool(np.all((pts[:, 1] >= wy0) & (pts[:, 1] <= wy1)
                                            & (pts[:, 2] >= wz0) & (pts[:, 2] <= wz1)))
        # Rectangle of the floor holding every quiet zone: the pad is skipped when it is unseen.
        (px0, py0, _), (px1, py1, _) = np.min(pts[-4 * len(self.markers):], axis=0), \
            np.max(pts[-4 * len(self.markers):], axis=0)
        self._pad_outline_I = np.array([[px0, py0, fz], [px0, py1, fz], [px1, py1, fz],
                                        [px1, py0, fz]])

    # -- rendering --
    def render(self, R_IB: np.ndarray, xi_I: np.ndarray) -> np.ndarray:
        """Image (H, W) mono8 of the camera on a body at ``xi_I`` with attitude ``R_IB``.

        The optical centre is at ``xi_I + R_IB t_BC`` (the camera's lever arm ``t_BC``, body
        FRD); the camera attitude is ``R_IB @ R_BC``. Raises RenderError on a non-finite pose.
        """
        R_IB = np.asarray(R_IB, float)
        xi_I = np.asarray(xi_I, float).reshape(3)
        if R_IB.shape != (3, 3) or not (np.all(np.isfinite(R_IB))
                                        and np.all(np.isfinite(xi_I))):
            raise RenderError('pose must be a finite 3x3 rotation and a finite 3-vector')
        if self._lever_arm:                    # from here on xi_I is the optical centre
            xi_I = xi_I + R_IB @ self.t_BC
        R_CI = (R_IB @ self.R_BC).T
        W, H = self.virtual_size
        canvas = np.full((H, W), BACKGROUND_GRAY, np.uint8)
        cone = self._aperture_cone(R_CI, xi_I)
        # Quiet zones first, then every marker body: a black border wins over a quiet zone.
        pad = [_QUIET_ZONES, *self.markers]
        if xi_I[0] < self.world.wall_x:
            far = [self.back_wall, self.floor_far, *pad]
            order = far + [self.wall, self.floor_near]
        else:
            order = [self.floor_near, self.wall, self.floor_far, *pad, self.back_wall]
            far = [self.floor_near]
        pad_planes = cone if any(p is self.floor_far for p in far) else None
        if len(self._visible(self._pad_outline_I, R_CI, xi_I, pad_planes)) < 3:
            order = [item for item in order if not any(item is p for p in pad)]
        for item in order + self.overlay_planes:
            planes = cone if any(item is f for f in far) else None
            if item is _QUIET_ZONES:
                if self.quiet_zones_I:
                    self._fill_polygons(canvas, np.array(self.quiet_zones_I), QUIET_ZONE_GRAY,
                                        R_CI, xi_I, planes)
            else:
                self._draw_plane(canvas, item, R_CI, xi_I, planes)
        return cv2.remap(canvas, self._map1, self._map2, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND_GRAY)

    def _aperture_cone(self, R_CI: np.ndarray, xi_I: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray] | None:
        """Clip planes (normals, offsets) of everything seen across the wall, or None.

        With the optical centre within the wall's y-z extent, a point across the wall plane and
        within that extent too is seen only through the aperture: the cone from the optical
        centre through the aperture, widened by APERTURE_CLIP_MARGIN_PX.
        """
        world = self.world
        (y0, y1), (z0, z1) = world.wall_y_range, world.wall_z_range
        if not (self._far_within_wall and y0 <= xi_I[1] <= y1 and z0 <= xi_I[2] <= z1
                and abs(xi_I[0] - world.wall_x) > MIN_WALL_DISTANCE_M):
            return None
        win = world.window
        corners = win.corners_I()
        centre = np.asarray(win.center_I, float)
        reach = float(np.max(np.linalg.norm(corners - xi_I, axis=1)))
        margin = APERTURE_CLIP_MARGIN_PX * reach / self.K_v[0, 0]
        grow = np.sign(corners - centre)
        grow[:, 0] = 0.0
        P_C = self._to_camera(corners + margin * grow, R_CI, xi_I)
        n = np.cross(P_C, np.roll(P_C, -1, axis=0))
        n *= np.sign(n @ self._to_camera(centre, R_CI, xi_I))[:, None]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return (np.vstack([self._frustum_n, n]),
                np.concatenate([self._frustum_d, np.zeros(len(n))]))

    def _to_camera(self, P_I: np.ndarray, R_CI: np.ndarray, xi_I: np.ndarray) -> np.ndarray:
        return (P_I - xi_I) @ R_CI.T

    def _visible(self, poly_I: np.ndarray, R_CI: np.ndarray, xi_I: np.ndarray,
                 planes: tuple | None = None) -> np.ndarray:
        normals, offsets = planes if planes is not None else (self._frustum_n, self._frustum_d)
        return clip_polygon(self._to_camera(poly_I, R_CI, xi_I), normals, offsets)

    def _project(self, P_C: np.ndarray) -> np.ndarray:
        p = P_C @ self.K_v.T
        return p[:, :2] / p[:, 2:3]

    def _edge_lines(self, P_C: np.ndarray, inside_C: np.ndarray,
                    edges: np.ndarray | None = None) -> np.ndarray:
        """Image lines (K, 3) of the polygon P_C's edges (camera frame), all or the selected.

        Line l of edge (P_i, P_i+1): the plane through the optical centre and the edge,
        ``l = K_v^-T (P_i x P_i+1)``, scaled so that ``l . (u, v, 1)`` is the signed distance
        in virtual pixels, positive on the side of ``inside_C`` (a point of the polygon).
        """
        Q = P_C[np.arange(1, len(P_C) + 1) % len(P_C)]
        n = np.column_stack([P_C[:, 1] * Q[:, 2] - P_C[:, 2] * Q[:, 1],
                             P_C[:, 2] * Q[:, 0] - P_C[:, 0] * Q[:, 2],
                             P_C[:, 0] * Q[:, 1] - P_C[:, 1] * Q[:, 0]])
        if edges is not None:
            n = n[edges]
        lines = n @ self._K_v_inv
        norm = np.hypot(lines[:, 0], lines[:, 1]) * np.sign(n @ inside_C)
        ok = np.abs(norm) > 1e-12
        return lines[ok] / norm[ok, None]

    def _coverage_band(self, uv: np.ndarray, lines: np.ndarray, holes: list
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels (x, y) along the anti-aliased edges and their coverage (float32).

        ``uv``: the visible polygon (virtual pixels), ``lines``: its anti-aliased edges'
        lines; ``holes``: (uv, lines) of each visible hole.
        """
        seg0, seg1 = [], []
        for poly, ls in [(uv, lines)] + holes:
            a, b = edges_on_lines(poly, ls)
            seg0.append(a)
            seg1.append(b)
        regions = [(lines, False)] + [(hole_lines, True) for _, hole_lines in holes]
        x, y, _, cov = edge_band(np.concatenate(seg0), np.concatenate(seg1), regions,
                                 self.virtual_size)
        return x, y, cov

    def _fill_polygons(self, canvas: np.ndarray, polys_I: np.ndarray, value: int,
                       R_CI: np.ndarray, xi_I: np.ndarray, planes: tuple | None = None) -> None:
        """Fill convex polygons (M, K, 3) of {I}, in order, with a grey; anti-aliased edges.

        The geometry of all polygons is computed at once; only the fills are done one by one.
        """
        P_C = self._to_camera(polys_I.reshape(-1, 3), R_CI, xi_I).reshape(polys_I.shape)
        Q_C = np.roll(P_C, -1, axis=1)
        n = np.cross(P_C, Q_C)                                       # (M, K, 3)
        lines = n @ self._K_v_inv
        norm = (np.hypot(lines[..., 0], lines[..., 1])
                * np.sign(np.einsum('mkj,mj->mk', n, P_C.mean(axis=1))))
        degenerate = norm == 0.0                                     # edge seen end-on
        lines /= np.where(degenerate, 1.0, norm)[..., None]
        lines[degenerate] = (0.0, 0.0, 1e6)                          # no constraint
        normals, offsets = planes if planes is not None else (self._frustum_n, self._frustum_d)
        uvs, seg0, seg1, owner = [], [], [], []
        for m in range(len(P_C)):
            poly_C = P_C[m]
            vis_C = clip_polygon(poly_C, normals, offsets)
            if len(vis_C) < 3:
                continue
            uv = self._project(vis_C)
            a, b = (uv, np.roll(uv, -1, axis=0)) if vis_C is poly_C else \
                edges_on_lines(uv, lines[m])
            uvs.append((m, uv))
            seg0.append(a)
            seg1.append(b)
            owner.append(np.full(len(a), m))
        if not uvs:
            return
        owner = np.concatenate(owner)
        x, y, seg, cov = edge_band(np.concatenate(seg0), np.concatenate(seg1),
                                   [(lines[owner], False)], self.virtual_size)
        poly = owner[seg]
        ends = np.searchsorted(poly, [m for m, _ in uvs], side='right')
        start = 0
        for (m, uv), end in zip(uvs, ends):
            xm, ym = x[start:end], y[start:end]
            below = canvas[ym, xm].astype(np.float32)
            cv2.fillConvexPoly(canvas, np.round(uv * SUBPIXEL_SCALE).astype(np.int32),
                               int(value), lineType=cv2.LINE_8, shift=SUBPIXEL_SHIFT)
            canvas[ym, xm] = np.rint(below + cov[start:end] * (float(value) - below)
                                     ).astype(np.uint8)
            start = end

    def _draw_plane(self, canvas: np.ndarray, plane: TexturedPlane, R_CI: np.ndarray,
                    xi_I: np.ndarray, planes: tuple | None = None) -> None:
        W, H = self.virtual_size
        f = self.K_v[0, 0]
        for poly_I, outer in zip(plane.polygons_I, plane.outer_edges):
            vis_C = self._visible(poly_I, R_CI, xi_I, planes)
            if len(vis_C) < 3:
                continue
            uv = self._project(vis_C)
            m = EDGE_BAND_HALF_PX + EDGE_BAND_EXTEND_PX + 1     # room for the edge band
            u0 = max(int(np.floor(uv[:, 0].min())) - m, 0)
            v0 = max(int(np.floor(uv[:, 1].min())) - m, 0)
            u1 = min(int(np.ceil(uv[:, 0].max())) + 1 + m, W)
            v1 = min(int(np.ceil(uv[:, 1].max())) + 1 + m, H)
            if u1 <= u0 or v1 <= v0:
                continue
            # Finest pixel footprint on this polygon: at its nearest visible point.
            footprint = float(np.min(np.linalg.norm(vis_C, axis=1))) / f
            level = 0
            while level + 1 < len(plane.pyramid) and plane.texel_m[level + 1] <= footprint:
                level += 1
            O, du, dv = plane.texel_frame_I(level)
            Hmat = self.K_v @ np.column_stack([R_CI @ du, R_CI @ dv, R_CI @ (O - xi_I)])
            Hroi = np.array([[1.0, 0.0, -u0], [0.0, 1.0, -v0], [0.0, 0.0, 1.0]]) @ Hmat
            size = (u1 - u0, v1 - v0)
            warped = cv2.warpPerspective(plane.pyramid[level], Hroi, size,
                                         flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_REPLICATE)
            mask = np.zeros((size[1], size[0]), np.uint8)
            pts = np.round((uv - (u0, v0)) * SUBPIXEL_SCALE).astype(np.int32)
            cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=SUBPIXEL_SHIFT)
            roi = canvas[v0:v1, u0:u1]
            if plane.texture_edges:
                cv2.polylines(mask, [pts], True, 1, thickness=2 * TEXTURE_EDGE_MARGIN_PX + 1,
                              lineType=cv2.LINE_8, shift=SUBPIXEL_SHIFT)
                np.copyto(roi, warped, where=mask.view(bool))
                continue
            holes = []
            for hole_I in plane.holes_I:
                hole_C = self._visible(hole_I, R_CI, xi_I)
                if len(hole_C) >= 3:
                    huv = self._project(hole_C)
                    holes.append((huv, self._edge_lines(self._to_camera(hole_I, R_CI, xi_I),
                                                        hole_C.mean(axis=0))))
                    cv2.fillConvexPoly(mask, np.round((huv - (u0, v0)) * SUBPIXEL_SCALE)
                                       .astype(np.int32), 0, lineType=cv2.LINE_8,
                                       shift=SUBPIXEL_SHIFT)
            lines = self._edge_lines(self._to_camera(poly_I, R_CI, xi_I), vis_C.mean(axis=0),
                                     outer)
            x, y, cov = self._coverage_band(uv, lines, holes)
            x -= u0
            y -= v0
            below = roi[y, x].astype(np.float32)
            np.copyto(roi, warped, where=mask.view(bool))
            roi[y, x] = np.rint(below + cov * (warped[y, x] - below)).astype(np.uint8)
