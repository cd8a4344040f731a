"""Local vectorized HD map around an ego pose, in HDMapNet's protocol (which MapTR and InstaGraM follow).

For a pose (global x, y, yaw) and a BEV grid, the patch is the grid's box in the ego frame, i.e. the
devkit's ``patch_box = (x, y, patch_h = y extent, patch_w = x extent)`` rotated by
``patch_angle = yaw`` (degrees) about the patch centre (for a grid centred on the ego). The map
expansion records are turned into polyline dicts (docs/conventions.md), in metres in the ego frame
(x forward, y left), clipped to the grid:

* class 0 **divider**: ``road_divider`` and ``lane_divider`` lines, clipped; a line cut into pieces
  gives one polyline per piece.
* class 1 **ped_crossing**: the union of the ``ped_crossing`` polygons, clipped to the patch; each
  part's exterior ring is one closed polyline (a crossing cut by the patch edge stays closed along
  the edge, as in MapTR).
* class 2 **boundary**: the union of the ``road_segment`` and ``lane`` polygons, clipped to the patch;
  every exterior *and* interior ring (islands) is a boundary. A ring that stays 0.2 m inside the
  patch is one closed polyline; a ring that reaches the patch edge is cut by the patch shrunk by
  0.2 m (HDMapNet's margin, so the artificial edge along the patch border is dropped) and the pieces
  (line-merged) are open polylines.

Rings are oriented as in MapTR (exterior clockwise, interiors counter-clockwise). Invalid polygons
are skipped, as the devkit's ``_get_layer_polygon`` does. Every line is resampled every
``sample_dist`` metres along its length, plus its end point (InstaGraM's ``np.arange(0, L, d)`` +
end point); a closed ring is resampled the same way and repeats its first point at the end (a ring
shorter than ``3 * sample_dist`` is resampled at ``L / 3`` so that it keeps 3 distinct points).
All points are strictly inside the grid (``grid.inside_m``).

Unlike the devkit (which intersects every record of a layer with the patch, per sample), the map's
geometries are built once per location and queried with an STR-tree, so one sample costs a few ms.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LinearRing, LineString, MultiLineString, Polygon, box
from shapely.geometry.polygon import orient

from ..config import UserError
from ..geometry import BEVGrid

DIVIDER, PED_CROSSING, BOUNDARY = 0, 1, 2
DIVIDER_LAYERS = ("road_divider", "lane_divider")
PED_LAYER = "ped_crossing"
AREA_LAYERS = ("road_segment", "lane")
EDGE_MARGIN_M = 0.2  # HDMapNet: boundary rings are cut this far inside the patch
INSIDE_EPS_M = 1e-3  # clip box shrink so that no point lies on the grid's upper edges
MIN_LENGTH_M = 1e-3  # clipped pieces shorter than this are dropped


class MapError(UserError):
    """A map expansion file is missing or unreadable."""


@dataclass
class _LocationMap:
    """Shapely geometries of one map location (global frame) with an STR-tree per group."""

    dividers: np.ndarray
    divider_tree: shapely.STRtree
    peds: np.ndarray
    ped_tree: shapely.STRtree
    areas: np.ndarray
    area_tree: shapely.STRtree


def map_expansion_path(dataroot: str | Path, location: str) -> Path:
    return Path(dataroot) / "maps" / "expansion" / f"{location}.json"


def load_location_map(dataroot: str | Path, location: str) -> _LocationMap:
    """Read ``maps/expansion/<location>.json`` with the devkit and build the geometry index."""
    from nuscenes.map_expansion.map_api import NuScenesMap, locations

    path = map_expansion_path(dataroot, location)
    if not path.is_file():
        raise MapError(
            f"map expansion file not found: {path} (location '{location}'); download the nuScenes map "
            f"expansion (v1.3) and unpack it into {Path(dataroot) / 'maps'}"
        )
    if location not in locations:
        raise MapError(f"unknown map location '{location}' in {path}; the devkit knows {', '.join(locations)}")
    try:
        nmap = NuScenesMap(dataroot=str(dataroot), map_name=location)
    except Exception as e:  # the devkit raises bare Exceptions / KeyErrors on bad files
        raise MapError(f"cannot read map expansion file {path}: {type(e).__name__}: {e}") from None
    ex = nmap.explorer

    dividers = [ex.extract_line(r["line_token"]) for layer in DIVIDER_LAYERS for r in getattr(nmap, layer)]
    dividers = np.array([g for g in dividers if not g.is_empty], dtype=object)
    peds = [ex.extract_polygon(r["polygon_token"]) for r in getattr(nmap, PED_LAYER)]
    peds = np.array([p for p in peds if p.is_valid and not p.is_empty], dtype=object)
    areas = [ex.extract_polygon(r["polygon_token"]) for layer in AREA_LAYERS for r in getattr(nmap, layer)]
    areas = np.array([p for p in areas if p.is_valid and not p.is_empty], dtype=object)
    return _LocationMap(
        dividers, shapely.STRtree(dividers), peds, shapely.STRtree(peds), areas, shapely.STRtree(areas)
    )


def resample_line(line: LineString, sample_dist: float, closed: bool = False) -> np.ndarray:
    """Points every ``sample_dist`` metres along ``line`` plus its end point, [P, 2] float64.

    A closed ring (``closed``) repeats its first point at the end and keeps >= 3 distinct points.
    """
    length = line.length
    step = min(sample_dist, length / 3) if closed else sample_dist
    dists = np.arange(0.0, length, step)
    if len(dists) > 1 and length - dists[-1] < 1e-6 * step:  # float rounding: drop a duplicate end
        dists = dists[:-1]
    pts = shapely.get_coordinates(shapely.line_interpolate_point(line, dists))
    end = pts[:1] if closed else np.asarray(line.coords[-1:], dtype=np.float64)[:, :2]
    return np.concatenate([pts, end])


def _lines(geom) -> list[LineString]:
    """The non-degenerate LineStrings in a clipping result (LineString, Multi*, collection)."""
    return [g for g in shapely.get_parts(geom) if g.geom_type == "LineString" and g.length > MIN_LENGTH_M]


def _polygons(geom) -> list[Polygon]:
    return [g for g in shapely.get_parts(geom) if g.geom_type == "Polygon" and g.area > 0]


class LocalMapBuilder:
    """``builder(location, x, y, yaw) -> list of polyline dicts`` (see the module docstring).

    Map files are read lazily, once per location (or eagerly with ``preload``).
    """

    def __init__(self, dataroot: str | Path, grid: BEVGrid, sample_dist: float = 1.5):
        if sample_dist <= 0:
            raise UserError(f"config key 'data.sample_dist' must be > 0, got {sample_dist}")
        self.dataroot = Path(dataroot)
        self.grid = grid
        self.sample_dist = sample_dist
        self._maps: dict[str, _LocationMap] = {}
        e = INSIDE_EPS_M
        self._clip_box = box(grid.xmin + e, grid.ymin + e, grid.xmax - e, grid.ymax - e)
        m = EDGE_MARGIN_M
        self._edge_box = box(grid.xmin + m, grid.ymin + m, grid.xmax - m, grid.ymax - m)

    def preload(self, locations) -> None:
        for loc in locations:
            self.location_map(loc)

    def location_map(self, location: str) -> _LocationMap:
        if location not in self._maps:
            self._maps[location] = load_location_map(self.dataroot, location)
        return self._maps[location]

    def patch_global(self, x: float, y: float, yaw: float) -> Polygon:
        """The grid's box in the global frame (the devkit's rotated ``patch_box``)."""
        g = self.grid
        corners = np.array([[g.xmin, g.ymin], [g.xmax, g.ymin], [g.xmax, g.ymax], [g.xmin, g.ymax]])
        c, s = np.cos(yaw), np.sin(yaw)
        return Polygon(corners @ np.array([[c, s], [-s, c]]) + [x, y])

    def __call__(self, location: str, x: float, y: float, yaw: float) -> list[dict]:
        """Polylines around the global pose (x, y, yaw radians), metres in the ego frame."""
        lmap = self.location_map(location)
        patch = self.patch_global(x, y, yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s], [s, c]])  # ego -> global; global -> ego is (p - t) @ rot

        def to_ego(geoms: np.ndarray) -> np.ndarray:
            return shapely.transform(geoms, lambda p: (p - [x, y]) @ rot)

        out: list[dict] = []
        # dividers
        cand = lmap.dividers[lmap.divider_tree.query(patch, predicate="intersects")]
        for geom in shapely.intersection(to_ego(cand), self._clip_box):
            out += [self._poly(line, DIVIDER, closed=False) for line in _lines(geom)]
        # ped crossings: union, clip, exterior rings (closed)
        cand = lmap.peds[lmap.ped_tree.query(patch, predicate="intersects")]
        if len(cand):
            union = shapely.union_all(shapely.intersection(to_ego(cand), self._clip_box))
            for poly in _polygons(union):
                ring = orient(poly, sign=-1.0).exterior
                out.append(self._poly(LineString(ring.coords), PED_CROSSING, closed=True))
        # boundaries: union of road segments and lanes, exterior and interior rings
        cand = lmap.areas[lmap.area_tree.query(patch, predicate="intersects")]
        if len(cand):
            union = shapely.union_all(shapely.intersection(to_ego(cand), self._clip_box))
            for poly in _polygons(union):
                poly = orient(poly, sign=-1.0)
                for ring in [poly.exterior, *poly.interiors]:
                    out += self._ring_pieces(ring)
        return out

    def _ring_pieces(self, ring: LinearRing) -> list[dict]:
        if ring.within(self._edge_box):
            return [self._poly(LineString(ring.coords), BOUNDARY, closed=True)]
        cut = shapely.intersection(LineString(ring.coords), self._edge_box)
        if isinstance(cut, MultiLineString):
            cut = shapely.line_merge(cut)
        return [self._poly(line, BOUNDARY, closed=False) for line in _lines(cut)]

    def _poly(self, line: LineString, label: int, closed: bool) -> dict:
        return {"pts": resample_line(line, self.sample_dist, closed), "label": label, "closed": closed}
