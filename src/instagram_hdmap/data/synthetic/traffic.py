"""The ego vehicle's drive through a road network, and the other vehicles of a scene.

The ego follows lane centre lines and lane connectors at a constant speed, through junctions
(straight on or turning). Other vehicles are parked at the kerb, queue at a stop line or drive
along lanes the ego does not use, so they never collide with it; they are the scene's
annotations (sample_annotation) and occlude the road in the camera images. ``place_occluders`` adds,
at a chosen density, rows of parked vehicles along kerbs and a truck ahead in the ego's lane: a world
where a map model's memory matters (``synth --occluders``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .network import Box, RoadNetwork
from .paths import Path

KEYFRAME_INTERVAL_S = 0.5  # nuScenes key frames at 2 Hz
ANNOTATION_RANGE_M = 60.0

VEHICLE_TYPES = (  # category, probability, (width, length, height) ranges
    ("vehicle.car", 0.8, ((1.7, 2.0), (4.2, 4.9), (1.4, 1.7))),
    ("vehicle.truck", 0.12, ((2.3, 2.6), (6.0, 9.0), (2.8, 3.5))),
    ("vehicle.bus.rigid", 0.08, ((2.5, 2.6), (10.0, 12.0), (3.0, 3.3))),
)
PAINT = [(30, 30, 30), (200, 200, 205), (40, 40, 150), (150, 80, 30), (90, 90, 95), (225, 225, 225),
         (30, 90, 160), (60, 120, 60), (20, 20, 60)]


@dataclass
class EgoDrive:
    route: Path
    s: np.ndarray  # [K] arc length of each key frame along route
    lanes: set[int]  # lanes the route uses
    speed: float

    def poses(self) -> np.ndarray:
        """[K, 3] (x, y, yaw) of the ego at each key frame."""
        return self.route.pose_at(self.s)


@dataclass
class Vehicle:
    category: str
    size: tuple[float, float, float]  # nuScenes order: width, length, height
    color: tuple[int, int, int]
    path: Path
    s0: float  # arc length at t = 0
    speed: float  # m/s along path (0: static)
    s_max: float  # stops here (stop line)
    lateral: float  # offset to the left of the path (parked at the kerb)
    parked: bool

    def state(self, t: float) -> tuple[np.ndarray, float, str]:
        """Centre (x, y, z), yaw, attribute name at time t (s)."""
        s = min(self.s0 + self.speed * t, self.s_max)
        x, y, yaw = self.path.pose_at(s)[0]
        c = np.array([x - self.lateral * math.sin(yaw), y + self.lateral * math.cos(yaw), self.size[2] / 2])
        if self.parked:
            attr = "vehicle.parked"
        elif self.speed > 0 and self.s0 + self.speed * t < self.s_max:
            attr = "vehicle.moving"
        else:
            attr = "vehicle.stopped"
        return c, float(yaw), attr

    def box(self, t: float) -> Box:
        c, yaw, _ = self.state(t)
        w, l, h = self.size
        return Box(float(c[0]), float(c[1]), yaw, l, w, 0.0, h, self.color, "vehicle")


def plan_drive(net: RoadNetwork, num_samples: int, rng: np.random.Generator) -> EgoDrive:
    """A drive of `num_samples` key frames along lanes and connectors, usually through a junction."""
    speed = float(rng.uniform(4.0, 11.0))
    needed = speed * KEYFRAME_INTERVAL_S * max(num_samples - 1, 0) + 1.0
    outgoing: dict[int, list] = {}
    for con in net.connectors:
        outgoing.setdefault(con.src, []).append(con)
    # the map must reach 30 m beyond the last key frame (the BEV window): no route into a dead end
    lookahead = 30.0
    candidates = [ln for ln in net.lanes if ln.path.length >= 15.0 and ln.index in outgoing]
    for _ in range(200):
        lane = candidates[int(rng.integers(len(candidates)))]
        # half of the drives start shortly before the lane's end, so that they cross a junction
        if rng.random() < 0.5:
            back = float(rng.uniform(5.0, max(6.0, 0.6 * needed + 20.0)))
        else:
            back = float(rng.uniform(0.0, lane.path.length))
        s0 = max(0.0 if lane.start is not None else min(lookahead, lane.path.length - 5.0), lane.path.length - back)
        paths, used, total = [lane.path], {lane.index}, lane.path.length - s0
        while total < needed + lookahead:
            options = outgoing.get(lane.index, [])
            if not options:
                break
            weights = np.array([2.0 if c.turn == "straight" else 1.0 for c in options])
            con = options[int(rng.choice(len(options), p=weights / weights.sum()))]
            lane = net.lanes[con.dst]
            paths += [con.path, lane.path]
            used.add(lane.index)
            total += con.path.length + lane.path.length
        if total >= needed + lookahead:
            s = s0 + speed * KEYFRAME_INTERVAL_S * np.arange(num_samples)
            return EgoDrive(route=Path.concat(paths), s=s, lanes=used, speed=speed)
    raise RuntimeError(f"no drivable route of {needed:.0f} m in {net.location}")


def place_vehicles(net: RoadNetwork, drive: EgoDrive, rng: np.random.Generator) -> list[Vehicle]:
    """Parked, queued and moving vehicles on lanes near the drive that the ego does not use."""
    ego_xy = drive.poses()[:, :2]
    out: list[Vehicle] = []
    for lane in net.lanes:
        if lane.index in drive.lanes:
            continue
        pts = lane.path.pose_at(np.arange(0.0, lane.path.length, 5.0))[:, :2]
        if np.min(np.linalg.norm(pts[:, None] - ego_xy[None], axis=-1)) > ANNOTATION_RANGE_M:
            continue
        role = rng.random()
        length = lane.path.length
        if role < 0.35 and lane.kerb_rank == 0:
            s = float(rng.uniform(1.0, 8.0))
            for _ in range(int(rng.integers(1, 4))):
                v = _vehicle(rng)
                s += v.size[1] / 2
                if s + v.size[1] / 2 > length - 1.0:
                    break
                kerb = lane.width / 2 - v.size[0] / 2 - 0.2
                v.path, v.s0, v.s_max, v.parked = lane.path, s, s, True
                v.lateral = -kerb if net.drive_right else kerb
                out.append(v)
                s += v.size[1] / 2 + float(rng.uniform(1.5, 12.0))
        elif role < 0.6:
            v = _vehicle(rng)
            v.path, v.speed = lane.path, float(rng.uniform(2.0, 9.0))
            v.s_max = length - v.size[1] / 2 - 1.0
            v.s0 = float(rng.uniform(v.size[1] / 2, max(v.size[1] / 2, 0.5 * v.s_max)))
            if v.s0 <= v.s_max:
                out.append(v)
        elif role < 0.75:
            s = length - 1.0
            for _ in range(int(rng.integers(1, 3))):
                v = _vehicle(rng)
                s -= v.size[1] / 2
                if s - v.size[1] / 2 < 0.0:
                    break
                v.path, v.s0, v.s_max = lane.path, s, s
                out.append(v)
                s -= v.size[1] / 2 + float(rng.uniform(1.5, 3.0))
    return out


def place_occluders(net: RoadNetwork, drive: EgoDrive, rng: np.random.Generator, density: float,
                    others: list[Vehicle] = ()) -> list[Vehicle]:
    """Vehicles that hide the map from the ego, ``density`` in [0, 1] (0: none, and no draw at all):

    * **parked rows along kerbs**: each kerb lane near the drive that neither the ego nor a moving vehicle
      of ``others`` uses gets, with probability ``density``, a row of parked cars, vans and trucks at its
      kerb, from end to end, gaps of 0.8 m to ``0.8 + 8 (1 - density)`` m, around the standing vehicles
      of ``others`` there;
    * **a truck ahead in the lane**: with probability ``density``, a truck or bus drives the ego's route
      8-15 m ahead of it at its speed (it hides the road ahead at every frame).

    The caller draws from a generator of its own (jobs.plan_scene: seeded by ``(seed, 2000 + scene)``), so the
    scene's other draws, and a world at density 0, do not change."""
    if density <= 0:
        return []
    ego_xy = drive.poses()[:, :2]
    moving = {id(v.path) for v in others if v.speed > 0}
    standing: dict[int, list[tuple[float, float]]] = {}
    for v in others:
        if v.speed == 0:
            standing.setdefault(id(v.path), []).append((v.s0 - v.size[1] / 2 - 1.0, v.s0 + v.size[1] / 2 + 1.0))
    out: list[Vehicle] = []
    for lane in net.lanes:
        if lane.index in drive.lanes or lane.kerb_rank != 0 or id(lane.path) in moving:
            continue
        pts = lane.path.pose_at(np.arange(0.0, lane.path.length, 5.0))[:, :2]
        if np.min(np.linalg.norm(pts[:, None] - ego_xy[None], axis=-1)) > ANNOTATION_RANGE_M:
            continue
        if rng.random() >= density:
            continue
        busy = standing.get(id(lane.path), [])
        s = float(rng.uniform(0.5, 3.0))
        while True:
            v = _vehicle(rng, weights=(0.6, 0.3, 0.1))
            if s + v.size[1] > lane.path.length - 0.5:
                break
            clash = [hi for lo, hi in busy if lo < s + v.size[1] and s < hi]
            if clash:
                s = max(clash)
                continue
            s += v.size[1] / 2
            kerb = lane.width / 2 - v.size[0] / 2 - 0.2
            v.path, v.s0, v.s_max, v.parked = lane.path, s, s, True
            v.lateral = -kerb if net.drive_right else kerb
            out.append(v)
            s += v.size[1] / 2 + float(rng.uniform(0.8, 0.8 + 8.0 * (1.0 - density)))
    if rng.random() < density:
        v = _vehicle(rng, weights=(0.0, 0.7, 0.3))
        gap = float(rng.uniform(8.0, 15.0))
        v.path, v.speed = drive.route, drive.speed
        v.s0 = float(drive.s[0]) + gap + v.size[1] / 2
        v.s_max = drive.route.length - v.size[1] / 2
        out.append(v)
    return out


def _vehicle(rng: np.random.Generator, weights: tuple[float, ...] | None = None) -> Vehicle:
    """A random vehicle of VEHICLE_TYPES (``weights``: other odds of its three types than theirs)."""
    probs = np.array(weights if weights is not None else [p for _, p, _ in VEHICLE_TYPES])
    cat, _, ranges = VEHICLE_TYPES[int(rng.choice(len(VEHICLE_TYPES), p=probs / probs.sum()))]
    size = tuple(float(rng.uniform(lo, hi)) for lo, hi in ranges)
    color = PAINT[int(rng.integers(len(PAINT)))]
    return Vehicle(category=cat, size=size, color=color, path=None, s0=0.0, speed=0.0, s_max=0.0,  # type: ignore[arg-type]
                   lateral=0.0, parked=False)
