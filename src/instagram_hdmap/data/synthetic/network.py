"""The data model of a synthetic road network: its chains of grid edges, stretches of road, lanes,
connectors, junctions, props and painted markings, and the network that holds them (roads.py builds
it, render.py and traffic.py read it). Directions are codes 0..3 (E, N, W, S) on the layout grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import LineString, MultiPolygon, Polygon

from .map_writer import MapRecords, Ref
from .paths import Path

LOCATIONS = ("boston-seaport", "singapore-onenorth", "singapore-hollandvillage", "singapore-queenstown")
DIRS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])  # direction codes 0..3 (E, N, W, S)
STOP_LINE_WIDTH = 0.4


def left_of(code: int) -> np.ndarray:
    """Unit normal to the left of direction `code`."""
    return DIRS[(code + 1) % 4]


def yaw_of(code: int) -> float:
    return code * math.pi / 2


def as_polygons(geom) -> list[Polygon]:
    """The non-empty polygons of a shapely geometry (Polygon, MultiPolygon or collection)."""
    return [g for g in shapely.get_parts(geom) if isinstance(g, Polygon) and not g.is_empty]


@dataclass
class MapStyle:
    """Per-map painting and street-furniture parameters (scene-level colours live in render.py)."""

    dash: float  # dashed lane divider: painted length (m)
    gap: float  # dashed lane divider: gap (m)
    line_width: float  # painted line width (m)
    double_gap: float  # gap between the two lines of a double divider (m)
    sidewalk: float  # sidewalk (walkway) width (m)
    kerb: float  # kerb width (m)
    island_ground: str  # 'grass' | 'paved'


@dataclass
class Chain:
    """A road between two junctions (or a junction and the map edge) through corner nodes."""

    nodes: list[tuple[int, int]]  # grid nodes from a junction to a junction (a stub: just its junction)
    dirs: list[int]  # direction code leaving each node but the last (a stub: towards the map edge)
    stub: bool
    n_right: int = 0  # lanes right of the centre path
    n_left: int = 0
    lane_width: float = 3.5
    median: float = 0.0  # median width (m), 0: none
    divider: str = "double_yellow"  # double_yellow | single_yellow | single_white

    @property
    def w_right(self) -> float:
        return self.median / 2 + self.n_right * self.lane_width

    @property
    def w_left(self) -> float:
        return self.median / 2 + self.n_left * self.lane_width


@dataclass
class Stretch:
    chain: Chain
    path: Path  # centre path from the start junction arm (or map edge) to the end one
    s: np.ndarray  # [n] sample arc lengths
    pts: np.ndarray  # [n, 2] centre samples
    nrm: np.ndarray  # [n, 2] left unit normals
    rows: np.ndarray  # [J] lateral offsets, ascending
    kinds: list[str]  # [J] 'edge' | 'lane' | 'median' | 'centre'
    ids: np.ndarray  # [J, n] node ids, -1 where the row is absent (centre row across an island)
    island: tuple[float, float] | None  # (s_a, s_b) nose tips of the island
    start: tuple[tuple[int, int], int] | None  # (junction node, arm code) at s = 0
    end: tuple[tuple[int, int], int] | None  # at s = length; None: map edge
    shape: Polygon | None = None
    segment: Ref | None = None
    tone: float = 0.0  # asphalt tone offset of this stretch (render)


@dataclass
class Lane:
    index: int
    stretch: int
    lo: int  # row index of the lower-offset boundary
    hi: int
    forward: bool  # travels along the stretch path
    path: Path  # centre line in the direction of travel
    kerb_rank: int  # 0 = next to the kerb
    start: tuple[tuple[int, int], int] | None  # (junction, arm) where the lane begins, None: map edge
    end: tuple[tuple[int, int], int] | None
    width: float
    ref: Ref | None = None


@dataclass
class Connector:
    index: int
    path: Path
    src: int  # lane index
    dst: int
    turn: str  # straight | left | right
    ref: Ref | None = None


@dataclass
class Junction:
    node: tuple[int, int]
    centre: np.ndarray
    arms: list[int]
    D: dict[int, float]  # arm end distance from the centre
    wl: dict[int, float]  # half-width left of the outward direction
    wr: dict[int, float]
    crossing: dict[int, bool]
    fillet: dict[int, float]  # kerb radius of the corner between arm a and arm a + 1
    # corner a (between arms a and a + 1) whose two crossings overlap: (depth along arm a, depth along
    # arm a + 1) of the overlap, metres (overlapping_corners)
    overlap: dict[int, tuple[float, float]] = field(default_factory=dict)
    shape: Polygon | None = None
    segment: Ref | None = None
    tone: float = 0.0


@dataclass
class Box:
    """An upright box: centre (x, y), yaw, length along yaw, width, z range, BGR colour, kind."""

    x: float
    y: float
    yaw: float
    length: float
    width: float
    z0: float
    z1: float
    color: tuple[int, int, int]
    kind: str  # building | tree | trunk | pole | vehicle

    def footprint(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hl, hw = self.length / 2, self.width / 2
        local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
        return local @ np.array([[c, s], [-s, c]]) + [self.x, self.y]


@dataclass
class Markings:
    """Painted world-frame polygons (each [P, 2], not closed) by paint colour."""

    white: list[np.ndarray] = field(default_factory=list)
    yellow: list[np.ndarray] = field(default_factory=list)
    patches: list[tuple[np.ndarray, float]] = field(default_factory=list)  # (polygon, tone offset)


@dataclass
class RoadNetwork:
    location: str
    seed: int
    canvas: tuple[float, float]  # map extent (w, h) in metres: nuScenes canvas_edge
    drive_right: bool
    style: MapStyle
    stretches: list[Stretch]
    junctions: dict[tuple[int, int], Junction]
    lanes: list[Lane]
    connectors: list[Connector]
    records: MapRecords
    road: Polygon | MultiPolygon  # drivable road surface (holes: city blocks and median islands)
    road_filled: Polygon | MultiPolygon  # the same without the median islands
    islands: list[Polygon]
    walkway: Polygon | MultiPolygon
    ground: list[tuple[Polygon, str]]  # city blocks outside the sidewalks: (shape, 'grass'|'dirt'|'paved')
    kerb: Polygon | MultiPolygon
    markings: Markings
    props: list[Box]

    def lines(self, layer: str) -> list[LineString]:
        """The generator's own road_divider / lane_divider lines, as written to the map."""
        return [LineString(self.records.node_xy(self.records.lines[r["line_token"].index]))
                for r in self.records.layers[layer]]

    def polygons(self, layer: str) -> list[Polygon]:
        """The generator's own polygons of a polygon layer (drivable_area: every polygon of it)."""
        out = []
        for r in self.records.layers[layer]:
            refs = r["polygon_tokens"] if layer == "drivable_area" else [r["polygon_token"]]
            out.extend(self.records.shape_of(ref.index) for ref in refs)
        return out
