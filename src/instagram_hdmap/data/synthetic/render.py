"""Camera images and LIDAR_TOP sweeps of the synthetic world.

Ground: a world-aligned texture of the ground around the ego (asphalt, painted markings, kerbs,
sidewalks, grass) is painted with OpenCV from the map geometry, twice (0.025 m/px within 20 m,
0.1 m/px within 80 m), and warped into each camera with the exact ground-plane homography
``K [r1 r2 t]`` of the stored calibration and ego pose: each pixel shows where its ray meets
z = 0. Above the horizon: sky. Then raised boxes (vehicles, buildings, trees, poles) are drawn
far to near with per-face sun shading; distance haze, per-camera exposure and sensor noise
finish the image. Per scene (see :func:`scene_look`): exposure, sun, asphalt tone, marking
colour and wear, vegetation, sky and haze vary, so that no fixed colour threshold finds the
markings.

Colours are BGR (OpenCV) throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..rig import Sensor
from .network import Box, RoadNetwork, as_polygons

JPEG_QUALITY = 90
FINE_RES, FINE_HALF = 0.025, 20.0  # m/px, half extent (m) of the near ground texture
COARSE_RES, COARSE_HALF = 0.1, 80.0
TILE = 512  # texture noise tile (px), repeats in world coordinates
NEAR = 0.2  # camera near plane (m)
PROP_RANGE = 120.0  # boxes farther than this from the ego are not drawn
LIDAR_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)  # a 32-beam spinning lidar
LIDAR_AZIMUTHS = 360
LIDAR_RANGE = 70.0


@dataclass
class SceneLook:
    """Per-scene appearance. Colours BGR floats before exposure."""

    gain: float  # global exposure
    cam_gain: dict[str, float]  # per-camera exposure jitter
    asphalt: np.ndarray
    white: np.ndarray  # marking paint after wear (blended towards the asphalt)
    yellow: np.ndarray
    kerb: np.ndarray
    sidewalk: np.ndarray
    ground: dict[str, np.ndarray]  # grass | dirt | paved
    sky_zenith: np.ndarray
    sky_horizon: np.ndarray
    haze: np.ndarray
    haze_dist: float  # m: ground contrast halves at ~0.7 of this
    sun: np.ndarray  # unit vector towards the sun, world frame
    ambient: float
    noise_sigma: float


def scene_look(rng: np.random.Generator, sensors: dict[str, Sensor]) -> SceneLook:
    """A scene's appearance, drawn from ``rng``; one exposure jitter per camera of ``sensors``, in its order."""
    cameras = [ch for ch, s in sensors.items() if s.modality == "camera"]
    overcast = rng.random() < 0.4
    asphalt_grey = rng.uniform(55.0, 115.0)
    asphalt = asphalt_grey + rng.uniform(-6.0, 6.0, 3)
    wear = rng.uniform(0.5, 1.0)  # 1: fresh paint
    white = asphalt + wear * (rng.uniform(200.0, 245.0, 1) + rng.uniform(-5, 5, 3) - asphalt)
    yellow_paint = np.array([rng.uniform(20, 70), rng.uniform(150, 200), rng.uniform(200, 240)])
    yellow = asphalt + wear * (yellow_paint - asphalt)
    elevation = math.radians(rng.uniform(15.0, 70.0))
    azimuth = rng.uniform(0.0, 2 * math.pi)
    sun = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                    math.sin(elevation)])
    horizon = np.array([200.0, 190.0, 185.0]) if overcast else np.array([235.0, 205.0, 175.0])
    return SceneLook(
        gain=float(rng.uniform(0.75, 1.2)),
        cam_gain={ch: float(rng.uniform(0.92, 1.08)) for ch in cameras},
        asphalt=asphalt,
        white=white,
        yellow=yellow,
        kerb=np.full(3, rng.uniform(150.0, 200.0)),
        sidewalk=np.full(3, rng.uniform(130.0, 185.0)) + rng.uniform(-8, 8, 3),
        ground={"grass": np.array([rng.uniform(40, 70), rng.uniform(95, 140), rng.uniform(60, 100)]),
                "dirt": np.array([rng.uniform(70, 100), rng.uniform(110, 140), rng.uniform(140, 170)]),
                "paved": np.full(3, rng.uniform(100.0, 150.0))},
        sky_zenith=np.array([190.0, 180.0, 175.0]) if overcast else np.array([210.0, 140.0, 80.0]),
        sky_horizon=horizon,
        haze=horizon * rng.uniform(0.85, 1.0),
        haze_dist=float(rng.uniform(120.0, 400.0)),
        sun=sun,
        ambient=float(rng.uniform(0.65, 0.8) if overcast else rng.uniform(0.35, 0.55)),
        noise_sigma=float(rng.uniform(2.0, 6.0)),
    )


def _bgr(c: np.ndarray, gain: float) -> tuple[float, float, float]:
    v = np.clip(np.asarray(c, dtype=np.float64) * gain, 0, 255)
    return float(v[0]), float(v[1]), float(v[2])


def _rings(shape) -> list[np.ndarray]:
    out = []
    for p in as_polygons(shape):
        out.append(np.asarray(p.exterior.coords)[:-1])
        out.extend(np.asarray(r.coords)[:-1] for r in p.interiors)
    return out


class _PolySet:
    """Many world polygons with bounding boxes, selected by overlap with a canvas."""

    def __init__(self, polys: list[np.ndarray], values: list | None = None):
        self.polys = polys
        self.values = values if values is not None else [None] * len(polys)
        if polys:
            self.lo = np.array([p.min(axis=0) for p in polys])
            self.hi = np.array([p.max(axis=0) for p in polys])
        else:
            self.lo = self.hi = np.zeros((0, 2))

    def select(self, lo: np.ndarray, hi: np.ndarray) -> list[int]:
        m = np.all(self.hi >= lo, axis=1) & np.all(self.lo <= hi, axis=1)
        return [int(i) for i in np.nonzero(m)[0]]


class MapPainter:
    """World-frame paint lists of one road network (built once per map)."""

    def __init__(self, net: RoadNetwork, seed: int):
        self.net = net
        self.ground = [(_rings(shape), kind) for shape, kind in net.ground]
        self.walkway = _rings(net.walkway)
        self.islands = [r for p in net.islands for r in _rings(p)]
        self.road = _PolySet([np.asarray(st.shape.exterior.coords)[:-1] for st in net.stretches]
                             + [np.asarray(jn.shape.exterior.coords)[:-1] for jn in net.junctions.values()],
                             [st.tone for st in net.stretches] + [jn.tone for jn in net.junctions.values()])
        self.white = _PolySet(net.markings.white)
        self.yellow = _PolySet(net.markings.yellow)
        self.patches = _PolySet([p for p, _ in net.markings.patches], [t for _, t in net.markings.patches])
        self.kerb = _rings(net.kerb)
        self.props = net.props
        rng = np.random.default_rng([seed, 77])
        # periodic noise: fine grain plus low-frequency blotches (white noise low-passed by FFT)
        grain = rng.normal(0.0, 5.0, (TILE, TILE))
        f = np.fft.fftfreq(TILE)
        low = np.exp(-(f[:, None] ** 2 + f[None, :] ** 2) * (2 * math.pi * 12.0) ** 2 / 2)
        blotch = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(0.0, 1.0, (TILE, TILE))) * low))
        blotch *= 7.0 / max(float(blotch.std()), 1e-9)
        self.tile = np.clip(grain + blotch, -40, 40).astype(np.int16)
        self._padded: dict[int, np.ndarray] = {}

    def texture(self, ox: int, oy: int, size: int) -> np.ndarray:
        """World-fixed noise [size, size, 3] int16 (a view) for a canvas whose pixel (0, 0) is the
        world pixel (ox, oy)."""
        if size not in self._padded:
            reps = size // TILE + 2
            big = np.tile(self.tile, (reps, reps))[: TILE + size, : TILE + size]
            self._padded[size] = np.ascontiguousarray(np.repeat(big[:, :, None], 3, axis=2))
        oy, ox = oy % TILE, ox % TILE
        return self._padded[size][oy:oy + size, ox:ox + size]


class GroundCanvas:
    """A square world-aligned ground texture around a point: pixel (i, j) shows world
    (x0 + j * res, y0 + i * res); rows grow with y."""

    def __init__(self, res: float, half: float):
        self.res = res
        self.size = int(round(2 * half / res))

    def paint(self, painter: MapPainter, look: SceneLook, centre: np.ndarray, shadows: list[np.ndarray]):
        """Returns (image [S, S, 3] uint8, A [3, 3] canvas pixel -> world)."""
        res, size = self.res, self.size
        ox = int(math.floor(centre[0] / res)) - size // 2
        oy = int(math.floor(centre[1] / res)) - size // 2
        x0, y0 = ox * res, oy * res
        lo, hi = np.array([x0, y0]) - 1.0, np.array([x0, y0]) + size * res + 1.0
        img = np.full((size, size, 3), _bgr(look.ground["grass"], look.gain), np.uint8)

        def fill(rings, color, aa=False):
            """Fills the world rings with ``color`` (before exposure)."""
            if not rings:
                return
            pts = [np.round((r - (x0, y0)) / res * 16.0).astype(np.int32) for r in rings]
            cv2.fillPoly(img, pts, _bgr(color, look.gain), lineType=cv2.LINE_AA if aa else cv2.LINE_8, shift=4)

        for rings, kind in painter.ground:
            if kind != "grass":
                fill(rings, look.ground[kind])
        fill(painter.walkway, look.sidewalk)
        island = look.ground["grass"] if painter.net.style.island_ground == "grass" else look.sidewalk * 0.9
        fill(painter.islands, island)
        for i in painter.road.select(lo, hi):
            fill([painter.road.polys[i]], look.asphalt + painter.road.values[i])
        patches = painter.patches.select(lo, hi)
        for i in patches:
            if painter.patches.values[i] >= -10.0:
                fill([painter.patches.polys[i]], look.asphalt + painter.patches.values[i])
        for paint_set, color in ((painter.white, look.white), (painter.yellow, look.yellow)):
            # each polygon separately: fillPoly's even-odd rule must not cancel touching pieces
            for i in paint_set.select(lo, hi):
                fill([paint_set.polys[i]], color, aa=True)
        for i in patches:  # the darkest patches over the paint: they wear it away
            if painter.patches.values[i] < -10.0:
                fill([painter.patches.polys[i]], look.asphalt + painter.patches.values[i], aa=True)
        fill(painter.kerb, look.kerb, aa=True)
        for sh in shadows:
            if np.all(sh.max(axis=0) >= lo) and np.all(sh.min(axis=0) <= hi):
                fill([sh], look.asphalt * 0.35, aa=True)
        img = cv2.add(img, painter.texture(ox, oy, size), dtype=cv2.CV_8U)
        A = np.array([[res, 0.0, x0], [0.0, res, y0], [0.0, 0.0, 1.0]])
        return img, A


def _world_to_ego(pose: np.ndarray) -> np.ndarray:
    """[3, 3] homogeneous 2-D transform world (x, y) -> ego (x, y) for pose (x, y, yaw)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, s, -(c * pose[0] + s * pose[1])], [-s, c, s * pose[0] - c * pose[1]], [0.0, 0.0, 1.0]])


def ground_homography(cam: Sensor, pose: np.ndarray) -> np.ndarray:
    """[3, 3] world ground-plane (x, y, 1) -> image pixel (homogeneous) for ego pose (x, y, yaw)."""
    rt = cam.rot.T
    m = np.stack([rt[:, 0], rt[:, 1], -rt @ cam.trans], axis=1)
    return cam.intrinsic @ m @ _world_to_ego(pose)


_FACES = ((4, 5, 6, 7), (0, 3, 2, 1), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
_FACE_NORMALS_LOCAL = np.array([[0, 0, 1], [0, 0, -1], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0]], float)


def _render_boxes(boxes: list[Box]):
    """Corners [N, 8, 3] and face normals [N, 6, 3] (world) of boxes."""
    n = len(boxes)
    corners = np.zeros((n, 8, 3))
    normals = np.zeros((n, 6, 3))
    for i, b in enumerate(boxes):
        fp = b.footprint()
        corners[i, :4, :2] = fp
        corners[i, 4:, :2] = fp
        corners[i, :4, 2] = b.z0
        corners[i, 4:, 2] = b.z1
        c, s = math.cos(b.yaw), math.sin(b.yaw)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        normals[i] = _FACE_NORMALS_LOCAL @ rot.T
    return corners, normals


def _clip_near(poly: np.ndarray) -> np.ndarray:
    """Clip a camera-frame polygon [P, 3] to z >= NEAR (Sutherland-Hodgman, one plane)."""
    out = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= NEAR, b[2] >= NEAR
        if ina:
            out.append(a)
        if ina != inb:
            t = (NEAR - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


def vehicle_render_boxes(b: Box) -> list[Box]:
    """A vehicle drawn as a body and a darker glass cabin on top."""
    body_h = b.z1 * 0.55
    c = np.asarray(b.color, float)
    glass = tuple(int(v) for v in np.clip(c * 0.35 + 15, 0, 255))
    return [Box(b.x, b.y, b.yaw, b.length, b.width, 0.0, body_h, b.color, "vehicle"),
            Box(b.x, b.y, b.yaw, b.length * 0.62, b.width * 0.9, body_h, b.z1, glass, "vehicle")]


class SceneRenderer:
    """Renders the cameras and the lidar of one scene (fixed map, look and image sizes).

    ``sensors``: the rig, by channel: its cameras in order, and one lidar. ``image_size`` (w, h) is
    the size of every camera without a ``Sensor.size`` of its own, and at least the largest one."""

    def __init__(self, painter: MapPainter, look: SceneLook, sensors: dict[str, Sensor],
                 image_size: tuple[int, int], rng: np.random.Generator):
        self.painter = painter
        self.look = look
        self.sensors = sensors
        self.cameras = [ch for ch, s in sensors.items() if s.modality == "camera"]
        self.lidar = next(s for s in sensors.values() if s.modality == "lidar")
        self.w, self.h = image_size
        self.fine = GroundCanvas(FINE_RES, FINE_HALF)
        self.coarse = GroundCanvas(COARSE_RES, COARSE_HALF)
        self.noise = np.clip(rng.normal(0.0, look.noise_sigma, (self.h + 32, self.w + 32, 3)), -60, 60).astype(np.int16)
        self.noise_rng = rng
        self.sky: dict[str, tuple] = {ch: self._sky(sensors[ch]) for ch in self.cameras}
        props = painter.props
        self.prop_xy = np.array([[b.x, b.y] for b in props]).reshape(-1, 2)
        self.prop_r = np.array([math.hypot(b.length, b.width) / 2 for b in props])

    def size(self, cam: Sensor) -> tuple[int, int]:
        """(w, h) of a camera's images."""
        return cam.size or (self.w, self.h)

    def _sky(self, cam: Sensor):
        """Per camera: sky image, sky mask (ray above the horizon), haze rows and alpha."""
        look, g = self.look, self.look.gain
        m = (cam.rot @ np.linalg.inv(cam.intrinsic)).astype(np.float32)  # pixel (u, v, 1) -> ego ray
        w, h = self.size(cam)
        u = (np.arange(w, dtype=np.float32) + 0.5)[None, :]
        v = (np.arange(h, dtype=np.float32) + 0.5)[:, None]
        rx, ry, rz = (m[i, 0] * u + m[i, 1] * v + m[i, 2] for i in range(3))
        horiz = np.sqrt(rx * rx + ry * ry)
        t = np.clip(np.arctan2(rz, horiz) / 0.6, 0.0, 1.0)[..., None]
        sky = np.clip((look.sky_horizon * (1 - t) + look.sky_zenith * t) * g, 0, 255).astype(np.uint8)
        mask = (rz >= -1e-4).astype(np.uint8)
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = np.where(rz < -1e-4, np.float32(cam.trans[2]) / -rz * horiz, np.float32(np.inf))
        alpha = 1.0 - np.exp(-dist / np.float32(look.haze_dist))
        rows = np.nonzero((alpha > 0.05).any(axis=1))[0]
        r0, r1 = (int(rows.min()), int(rows.max()) + 1) if len(rows) else (0, 0)
        band = alpha[r0:r1, :, None].astype(np.float32)
        return sky, mask, (r0, r1), band

    def render(self, pose: np.ndarray, vehicles: list[Box]):
        """One key frame at ego pose (x, y, yaw) with the given vehicle boxes. Returns
        (JPEG bytes per camera channel, lidar points [N, 5] float32 in the lidar's frame (LIDAR_TOP
        in the nuScenes rig) (x, y, z, intensity, ring), lidar points on each vehicle [len(vehicles)])."""
        look, g = self.look, self.look.gain
        shadows = [np.asarray(_grow(b, 0.25)) for b in vehicles]
        centre = np.asarray(pose[:2])
        fine, a_fine = self.fine.paint(self.painter, look, centre, shadows)
        coarse, a_coarse = self.coarse.paint(self.painter, look, centre, shadows)
        near = np.linalg.norm(self.prop_xy - centre, axis=1) - self.prop_r < PROP_RANGE
        boxes = [b for b, keep in zip(self.painter.props, near) if keep]
        for b in vehicles:
            boxes += vehicle_render_boxes(b)
        corners, normals = _render_boxes(boxes)
        haze = _bgr(look.haze, g)
        out = {}
        for ch in self.cameras:
            cam = self.sensors[ch]
            w, h = self.size(cam)
            H = ground_homography(cam, pose)
            img = cv2.warpPerspective(coarse, H @ a_coarse, (w, h), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=haze)
            cv2.warpPerspective(fine, H @ a_fine, (w, h), dst=img, flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_TRANSPARENT)
            sky, mask, (r0, r1), band = self.sky[ch]
            if r1 > r0:
                part = img[r0:r1].astype(np.float32)
                img[r0:r1] = (part + (np.asarray(haze, np.float32) - part) * band).astype(np.uint8)
            cv2.copyTo(sky, mask, img)
            self._draw_boxes(img, cam, pose, boxes, corners, normals)
            img = cv2.convertScaleAbs(img, alpha=look.cam_gain[ch])
            dy, dx = (int(v) for v in self.noise_rng.integers(0, 32, 2))
            img = cv2.add(img, self.noise[dy:dy + h, dx:dx + w], dtype=cv2.CV_8U)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError(f"JPEG encoding failed for {ch}")
            out[ch] = buf.tobytes()
        points, counts = self._lidar(self.lidar, pose, vehicles, coarse, a_coarse)
        return out, points, counts

    def _draw_boxes(self, img, cam: Sensor, pose, boxes, corners, normals) -> None:
        look, g = self.look, self.look.gain
        c, s = math.cos(pose[2]), math.sin(pose[2])
        r_e = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        t_e = np.array([pose[0], pose[1], 0.0])
        cam_world = r_e @ cam.trans + t_e
        w2c_r = cam.rot.T @ r_e.T  # world -> camera rotation
        w2c_t = -cam.rot.T @ (r_e.T @ t_e + cam.trans)
        pc = corners @ w2c_r.T + w2c_t  # [N, 8, 3]
        in_front = (pc[..., 2] > NEAR).any(axis=1)
        centres = corners.mean(axis=1)
        dist = np.linalg.norm(centres - cam_world, axis=1)
        order = np.argsort(-dist, kind="stable")
        k = cam.intrinsic
        haze = np.asarray(look.haze)
        for i in order:
            if not in_front[i]:
                continue
            proj = pc[i, :, :2] / np.maximum(pc[i, :, 2:3], NEAR) @ k[:2, :2].T + k[:2, 2]
            ok = pc[i, :, 2] > NEAR
            if ok.all() and ((proj[:, 0] < 0).all() or (proj[:, 0] > img.shape[1]).all() or (proj[:, 1] < 0).all()
                             or (proj[:, 1] > img.shape[0]).all()):
                continue
            base = np.asarray(boxes[i].color, float)
            fog = 1.0 - math.exp(-dist[i] / look.haze_dist)
            for f, face in enumerate(_FACES):
                fc = corners[i, list(face)].mean(axis=0)
                if np.dot(normals[i, f], cam_world - fc) <= 0:
                    continue
                shade = look.ambient + (1 - look.ambient) * max(0.0, float(np.dot(normals[i, f], look.sun)))
                color = base * shade * (1 - fog) + haze * fog
                poly = pc[i, list(face)]
                if not (poly[:, 2] > NEAR).all():
                    poly = _clip_near(poly)
                    if len(poly) < 3:
                        continue
                uv = poly[:, :2] / poly[:, 2:3] @ k[:2, :2].T + k[:2, 2]
                cv2.fillConvexPoly(img, np.round(uv * 4).astype(np.int32), _bgr(color, g),
                                   lineType=cv2.LINE_AA, shift=2)

    # --- lidar --------------------------------------------------------------------------------
    def _lidar(self, lidar: Sensor, pose, vehicles: list[Box], canvas: np.ndarray, a_canvas: np.ndarray):
        """A 32-beam sweep cast against the ground plane and all boxes; ground intensity is high on
        paint (read from the ground texture)."""
        c, s = math.cos(pose[2]), math.sin(pose[2])
        r_e = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        t_e = np.array([pose[0], pose[1], 0.0])
        r_wl = r_e @ lidar.rot
        origin = r_e @ lidar.trans + t_e
        el = np.radians(LIDAR_ELEVATIONS_DEG)[:, None]
        az = np.linspace(0.0, 2 * math.pi, LIDAR_AZIMUTHS, endpoint=False)[None, :]
        d_l = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az], axis=-1).reshape(-1, 3)
        ring = np.repeat(np.arange(len(LIDAR_ELEVATIONS_DEG)), LIDAR_AZIMUTHS)
        d_w = d_l @ r_wl.T
        with np.errstate(divide="ignore"):
            t = np.where(d_w[:, 2] < -1e-6, -origin[2] / d_w[:, 2], np.inf)
        hit = np.full(len(d_w), -1)  # -1 ground / none, >= 0 box index
        near = np.linalg.norm(self.prop_xy - origin[:2], axis=1) - self.prop_r < LIDAR_RANGE
        boxes = list(vehicles) + [b for b, keep in zip(self.painter.props, near) if keep]
        for bi, b in enumerate(boxes):
            tb = _ray_box(origin, d_w, b)
            closer = tb < t
            t[closer] = tb[closer]
            hit[closer] = bi
        keep = t < LIDAR_RANGE
        p_w = origin + t[keep, None] * d_w[keep]
        hit = hit[keep]
        intensity = np.full(len(p_w), 20.0)
        ground = hit < 0
        if ground.any():
            px = (p_w[ground, :2] - a_canvas[:2, 2]) / a_canvas[0, 0]
            j = np.clip(np.round(px[:, 0]).astype(int), 0, canvas.shape[1] - 1)
            i = np.clip(np.round(px[:, 1]).astype(int), 0, canvas.shape[0] - 1)
            lum = canvas[i, j].astype(np.float32).mean(axis=1)
            intensity[ground] = np.clip((lum - 60.0) * 0.8, 1.0, 100.0)
        p_l = (p_w - origin) @ r_wl
        pts = np.concatenate([p_l, intensity[:, None], ring[keep, None]], axis=1).astype(np.float32)
        counts = np.bincount(hit[(hit >= 0) & (hit < len(vehicles))], minlength=len(vehicles))[:len(vehicles)]
        return pts, counts


def _ray_box(origin: np.ndarray, d: np.ndarray, b: Box) -> np.ndarray:
    """Entry distance [R] of rays (origin, d [R, 3]) into box b (inf when missed)."""
    c, s = math.cos(b.yaw), math.sin(b.yaw)
    o = origin - np.array([b.x, b.y, 0.0])
    o_l = np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1], o[2]])
    d_l = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=-1)
    lo = np.array([-b.length / 2, -b.width / 2, b.z0])
    hi = np.array([b.length / 2, b.width / 2, b.z1])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o_l) / d_l
        t2 = (hi - o_l) / d_l
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    ok = (tmax >= np.maximum(tmin, 0.0)) & (tmin > 0.0)
    return np.where(ok, tmin, np.inf)


def _grow(b: Box, margin: float) -> np.ndarray:
    return Box(b.x, b.y, b.yaw, b.length + 2 * margin, b.width + 2 * margin, 0, 0, b.color, b.kind).footprint()
