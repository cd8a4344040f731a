"""nuScenes map expansion v1.3 records, built with integer ids and written as the official JSON.

The road network (roads.py) adds nodes, polygons, lines and layer records through
:class:`MapRecords`; :meth:`MapRecords.to_json` turns the integer references into 32-hex tokens and
produces exactly the layers that ``nuscenes.map_expansion.map_api.NuScenesMap`` reads:
``polygon, line, node, drivable_area, road_segment, road_block, lane, ped_crossing, walkway,
stop_line, carpark_area, road_divider, lane_divider, traffic_light, lane_connector,
arcline_path_3, connectivity, canvas_edge, version``.

Every polygon is checked with shapely when it is added: the devkit silently drops invalid ones.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path as FsPath

import cv2
import numpy as np
from shapely.geometry import MultiPolygon, Polygon
from shapely.validation import explain_validity

MAP_VERSION = "1.3"

POLYGON_LAYERS = ("drivable_area", "road_segment", "road_block", "lane", "ped_crossing", "walkway", "stop_line",
                  "carpark_area", "lane_connector")
LINE_LAYERS = ("road_divider", "lane_divider", "traffic_light")
RECORD_LAYERS = POLYGON_LAYERS + LINE_LAYERS
SEMANTIC_PRIOR_RESOLUTION = 0.1  # m / px of maps/<token>.png, the devkit's MapMask default


def make_token(*parts: object) -> str:
    """A deterministic nuScenes-style token (32 hex characters) from the given parts."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


@dataclass(frozen=True)
class Ref:
    """A reference to the `index`-th record of `layer` ('node', 'polygon', 'line' or a record layer)."""

    layer: str
    index: int


class MapRecords:
    """Integer-indexed map records of one location, serialised by :meth:`to_json`."""

    def __init__(self, namespace: str):
        self.namespace = namespace
        self.nodes: list[tuple[float, float]] = []
        self.polygons: list[tuple[list[int], list[list[int]]]] = []
        self.lines: list[list[int]] = []
        self.layers: dict[str, list[dict]] = {name: [] for name in RECORD_LAYERS}
        self.arclines: dict[Ref, list[dict]] = {}
        self.connectivity: dict[Ref, dict[str, list[Ref]]] = {}

    # --- geometry -----------------------------------------------------------------------------
    def add_nodes(self, xy: np.ndarray) -> np.ndarray:
        """Add points [n, 2] (metres); returns their node ids [n]."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        start = len(self.nodes)
        self.nodes.extend((float(x), float(y)) for x, y in xy)
        return np.arange(start, start + len(xy))

    def node_xy(self, ids) -> np.ndarray:
        return np.array([self.nodes[i] for i in ids], dtype=np.float64).reshape(-1, 2)

    def shape_of(self, polygon_index: int) -> Polygon:
        ext, holes = self.polygons[polygon_index]
        return Polygon(self.node_xy(ext), [self.node_xy(h) for h in holes])

    def add_polygon(self, exterior, holes=(), what: str = "polygon") -> Ref:
        """Add a polygon from node ids (rings not closed); raises if shapely finds it invalid."""
        ext = [int(i) for i in exterior]
        hs = [[int(i) for i in h] for h in holes]
        self.polygons.append((ext, hs))
        shape = self.shape_of(len(self.polygons) - 1)
        if not shape.is_valid or shape.area <= 0:
            raise RuntimeError(f"synthetic map {self.namespace}: invalid {what} polygon: {explain_validity(shape)}")
        return Ref("polygon", len(self.polygons) - 1)

    def add_shapely(self, shape: Polygon, what: str) -> Ref:
        """Add a shapely polygon (new nodes, closing points dropped)."""
        ext = self.add_nodes(np.asarray(shape.exterior.coords)[:-1])
        holes = [self.add_nodes(np.asarray(r.coords)[:-1]) for r in shape.interiors]
        return self.add_polygon(ext, holes, what)

    def add_line(self, ids) -> Ref:
        ids = [int(i) for i in ids]
        if len(ids) < 2:
            raise RuntimeError(f"synthetic map {self.namespace}: a line needs >= 2 nodes")
        self.lines.append(ids)
        return Ref("line", len(self.lines) - 1)

    def add(self, layer: str, **fields) -> Ref:
        self.layers[layer].append(fields)
        return Ref(layer, len(self.layers[layer]) - 1)

    def get(self, ref: Ref) -> dict:
        return self.layers[ref.layer][ref.index]

    # --- serialisation ------------------------------------------------------------------------
    def token(self, ref: Ref) -> str:
        return make_token(self.namespace, ref.layer, ref.index)

    def _resolve(self, value):
        if isinstance(value, Ref):
            return self.token(value)
        if isinstance(value, list):
            return [self._resolve(v) for v in value]
        if isinstance(value, dict):
            return {k: self._resolve(v) for k, v in value.items()}
        return value

    def to_json(self, canvas_edge: tuple[float, float]) -> dict:
        tok = self.token
        node = [tok(Ref("node", i)) for i in range(len(self.nodes))]
        out: dict = {"version": MAP_VERSION}
        out["polygon"] = [{"token": tok(Ref("polygon", i)), "exterior_node_tokens": [node[n] for n in ext],
                           "holes": [{"node_tokens": [node[n] for n in h]} for h in holes]}
                          for i, (ext, holes) in enumerate(self.polygons)]
        out["line"] = [{"token": tok(Ref("line", i)), "node_tokens": [node[n] for n in ids]}
                       for i, ids in enumerate(self.lines)]
        out["node"] = [{"token": node[i], "x": x, "y": y} for i, (x, y) in enumerate(self.nodes)]
        for layer in RECORD_LAYERS:
            out[layer] = [{"token": tok(Ref(layer, i)), **self._resolve(r)} for i, r in enumerate(self.layers[layer])]
        out["canvas_edge"] = [float(canvas_edge[0]), float(canvas_edge[1])]
        out["arcline_path_3"] = {tok(ref): paths for ref, paths in self.arclines.items()}
        out["connectivity"] = {tok(ref): self._resolve(c) for ref, c in self.connectivity.items()}
        return out


def write_map_json(records: MapRecords, canvas_edge: tuple[float, float], path: FsPath) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        json.dump(records.to_json(canvas_edge), f, separators=(",", ":"))


def write_semantic_prior(shape: Polygon | MultiPolygon, canvas_edge: tuple[float, float], path: FsPath) -> None:
    """The v1.0 ``maps/<token>.png`` semantic prior: 255 on drivable surface and sidewalk, 0 elsewhere,
    0.1 m/px, row 0 at the top (max y), as ``nuscenes.utils.map_mask.MapMask`` reads it."""
    res = SEMANTIC_PRIOR_RESOLUTION
    w, h = int(round(canvas_edge[0] / res)), int(round(canvas_edge[1] / res))
    mask = np.zeros((h, w), np.uint8)
    polys = list(shape.geoms) if isinstance(shape, MultiPolygon) else [shape]
    rings = []
    for p in polys:
        for ring in [p.exterior, *p.interiors]:
            xy = np.asarray(ring.coords)
            px = np.stack([xy[:, 0] / res, h - xy[:, 1] / res], axis=-1)
            rings.append(np.round(px * 16).astype(np.int32))
    cv2.fillPoly(mask, rings, 255, lineType=cv2.LINE_8, shift=4)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), mask):
        raise OSError(f"could not write {path}")
