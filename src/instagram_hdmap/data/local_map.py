"""Local vectorized HD map around an ego pose, in HDMapNet's protocol (which MapTR and InstaGraM follow).

For a pose (global x, y, yaw) and a BEV grid, the patch is the grid's box in the ego frame, i.e. the
devkit's ``patch_box = (x, y, patch_h = y extent, patch_w = x extent)`` rotated by
``patch_angle = yaw`` (degrees) about the patch centre (for a grid centred on the ego). The map
expansion records are turned into polyline dicts (docs/conventions.md), in metres in the ego frame
(x forward, y left), clipped to the grid:

* class 0 **divider**: ``road_divider`` and ``lane_divider`` lines, clipped; a line cut into pieces
  gives one polyline per piece.
* class 1 **ped_crossing**, in one of three conventions (``data.ped_crossing``, ``PED_CROSSING_CONVENTIONS``;
  none of them loses a crossing edge, docs/conventions.md):

  - ``edges`` (HDMapNet's, the official InstaGraM code's, the paper's; the default): each crossing's
    **two longest edges as two open polylines**. Official ``data/vector_map.py``,
    ``VectorizedLocalMap.get_ped_crossing_line``: per crossing record, the squared lengths of the
    exterior ring's edges, ``np.argsort(dist)[-2:]`` (the second longest, then the longest), each a
    2-point line in the ring's stored direction, intersected with the (unshrunk) patch; then
    ``connect_lines`` joins two such lines whose first segments point within 5 deg of each other and
    whose ends lie within 2 m, into the line between their far ends (``join_collinear_edges``). On AV2
    a crossing is stored as its two principal edges (``PedestrianCrossing.edge1 / edge2``, the lines a
    pedestrian walks along); those are its two edges here (StreamMapNet's ``polygon_ped=False``), in the
    direction of the crossing's ring (edge2 reversed), as on nuScenes.
  - ``union`` (MapTR's ``ped_poly_geoms_to_instances``): the union of the crossing polygons, clipped to
    the patch; every ring of every part, the exterior (clockwise) **and the interiors**
    (counter-clockwise: where four overlapping crossings enclose a junction, its inner outline), each
    one closed polyline.
  - ``each`` (StreamMapNet's ``get_ped_crossing_contour``, its AV2 and nuScenes setting): each crossing's
    polygon clipped to the patch, its ring (counter-clockwise) one closed polyline; crossings that
    overlap stay apart.

  A closed crossing cut by the patch edge stays closed along the edge (as in MapTR and StreamMapNet).
* class 2 **boundary**: the union of the ``road_segment`` and ``lane`` polygons, clipped to the patch;
  every exterior *and* interior ring (islands) is a boundary. A ring that stays 0.2 m inside the
  patch is one closed polyline; a ring that reaches the patch edge is cut by the patch shrunk by
  0.2 m (HDMapNet's margin, so the artificial edge along the patch border is dropped) and the pieces
  (line-merged) are open polylines.

Boundary rings are oriented as in MapTR (exterior clockwise, interiors counter-clockwise). Invalid
area polygons are skipped, as the devkit's ``_get_layer_polygon`` does, counted in one ``UserWarning``
per map naming the file and the records. A crossing polygon that is
invalid (self-intersecting) is repaired with ``shapely.make_valid`` (its polygonal parts kept), one
with fewer than 3 distinct points is skipped; both are counted and reported once per map (a
``UserWarning`` naming the file; ``_LocationMap.crossing_report``), never silently and never at the
cost of a valid neighbour (``collect_crossings``). Every line is resampled every ``sample_dist`` metres
along its length, plus its end point (InstaGraM's ``np.arange(0, L, d)`` + end point); a closed ring
is resampled the same way and repeats its first point at the end (a ring shorter than
``3 * sample_dist`` is resampled at ``L / 3`` so that it keeps 3 distinct points). All points are
strictly inside the grid (``grid.inside_m``).

Unlike the devkit (which intersects every record of a layer with the patch, per sample), the map's
geometries are built once per location and queried with an STR-tree, so one sample costs a few ms.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LineString, MultiLineString, Polygon, box

from ..config import UserError
from ..geometry import BEVGrid

DIVIDER, PED_CROSSING, BOUNDARY = 0, 1, 2
DIVIDER_LAYERS = ("road_divider", "lane_divider")
PED_LAYER = "ped_crossing"
AREA_LAYERS = ("road_segment", "lane")
PED_CROSSING_CONVENTIONS = ("edges", "union", "each")  # data.ped_crossing (module docstring)
EDGE_MARGIN_M = 0.2  # HDMapNet: boundary rings are cut this far inside the patch
INSIDE_EPS_M = 1e-3  # clip box shrink so that no point lies on the grid's upper edges
MIN_LENGTH_M = 1e-3  # clipped pieces shorter than this are dropped
JOIN_EDGE_M = 2.0  # official connect_lines: crossing edges whose ends are this close are joined ...
JOIN_EDGE_DEG = 5.0  # ... when their first segments point within this angle of each other
DISTINCT_DECIMALS = 6  # crossing ring points equal to 1 um are one point (degenerate-polygon check)
# divider-on-kerb rule (maps that set _LocationMap.divider_exclusion, i.e. AV2): a clipped divider piece
# with more than this fraction of its length inside the exclusion zone is dropped
EXCLUDED_FRACTION = 0.5
EXCLUDED_STEP_M = 0.5  # ... the fraction measured at points this far apart along the piece


# an ego pose this far outside its location's map is not in that city: poses in millimetres (nuScenes' and AV2's
# city frames span a few km; closer, a pose off the mapped streets just has an empty local map)
OFF_MAP_M = 10_000.0


class MapError(UserError):
    """A map expansion file is missing or unreadable."""


@dataclass
class _LocationMap:
    """Shapely geometries of one map location (global frame) with an STR-tree per group.

    ``peds``: the crossing polygons (valid; a repaired crossing may give several); ``ped_edges``: two
    lines per crossing (its two longest ring edges; AV2: its principal edges), for ``edges``.
    ``divider_exclusion``: where a divider piece is taken for a road edge (AV2's painted lane boundaries
    along the drivable-area edge), None: no rule; ``merge_dividers``: line-merge the kept pieces of a
    sample (AV2's lane boundaries come one lane segment at a time). ``crossing_report``: the bad crossing
    polygons of the map ('' when none), as warned once when the map was read."""

    dividers: np.ndarray
    peds: np.ndarray
    ped_edges: np.ndarray
    areas: np.ndarray
    divider_exclusion: Polygon | None = None
    merge_dividers: bool = False
    crossing_report: str = ""

    def __post_init__(self) -> None:
        self.divider_tree = shapely.STRtree(self.dividers)
        self.ped_tree = shapely.STRtree(self.peds)
        self.ped_edge_tree = shapely.STRtree(self.ped_edges)
        self.area_tree = shapely.STRtree(self.areas)
        geoms = [g for g in (self.dividers, self.peds, self.areas) if len(g)]
        # the map's extent (xmin, ymin, xmax, ymax); NaN for a map without geometry
        self.bounds = shapely.total_bounds(np.concatenate(geoms)) if geoms else np.full(4, np.nan)
        if self.divider_exclusion is not None:
            shapely.prepare(self.divider_exclusion)  # point-in-zone tests per sample (_divider_pieces)


def some_of(names: Sequence[str], shown: int = 5) -> str:
    """The first ``shown`` of ``names``, comma-separated, and how many more there are."""
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def heading(rotation) -> float:
    """The yaw (radians) of an ego -> global rotation [3, 3], as ``LocalMapBuilder`` takes it: the heading of the
    ego's x axis in the global xy plane."""
    return math.atan2(rotation[1][0], rotation[0][0])


def map_expansion_path(dataroot: str | Path, location: str) -> Path:
    return Path(dataroot) / "maps" / "expansion" / f"{location}.json"


# --- crossings: the map's polygons, repaired or skipped, and their two edges ---------------------------


def longest_edges(ring_xy: np.ndarray) -> list[LineString]:
    """The two longest edges of a closed ring [P, 2] (first point repeated), as 2-point lines in the
    ring's direction: the second longest, then the longest (official ``np.argsort(dist)[-2:]``)."""
    dist = np.square(np.diff(ring_xy, axis=0)).sum(1)
    return [LineString(ring_xy[i:i + 2]) for i in np.argsort(dist, kind="stable")[-2:]]


def crossing_geometry(ring_xy: np.ndarray, edges: Sequence[np.ndarray] | None = None
                      ) -> tuple[list[Polygon], list[LineString], str]:
    """One crossing of a map: its ring [P, 2] (closed or not) and, where the map stores them (AV2),
    its two edges -> (valid polygons, the two edge lines, status).

    status: ``"ok"``; ``"repaired"``: the polygon was invalid (self-intersecting) and
    ``shapely.make_valid`` gave its polygonal parts; ``"skipped"``: fewer than 3 distinct points (or
    nothing polygonal left), no polygon and no edges."""
    ring_xy = np.asarray(ring_xy, dtype=np.float64).reshape(-1, 2)
    if len(np.unique(np.round(ring_xy, DISTINCT_DECIMALS), axis=0)) < 3 or not np.isfinite(ring_xy).all():
        return [], [], "skipped"
    if not np.array_equal(ring_xy[0], ring_xy[-1]):
        ring_xy = np.concatenate([ring_xy, ring_xy[:1]])
    polys, status = [Polygon(ring_xy)], "ok"
    if not polys[0].is_valid:
        polys, status = _polygons(shapely.make_valid(polys[0])), "repaired"
        if not polys:
            return [], [], "skipped"
    if edges is None:
        lines = longest_edges(ring_xy)
    else:
        lines = [LineString(e) for e in (np.asarray(e, dtype=np.float64)[:, :2] for e in edges) if len(e) >= 2]
        if len(lines) < len(edges) and status == "ok":  # an edge of < 2 points: the crossing lost an edge
            status = "short edge"
    return polys, [ln for ln in lines if ln.length > MIN_LENGTH_M], status


# crossing_geometry's statuses other than "ok", as collect_crossings reports them
CROSSING_PROBLEMS = {
    "repaired": "invalid (self-intersecting) crossing polygon(s) repaired with make_valid",
    "skipped": "degenerate crossing polygon(s) (< 3 distinct points) skipped",
    "short edge": "crossing(s) with an edge of fewer than 2 points, that edge not drawn",
}


def collect_crossings(crossings, source: str) -> tuple[np.ndarray, np.ndarray, str]:
    """``crossings``: iterable of ``(crossing id, ring [P, 2] or None when unreadable, edges or None)``
    -> (polygons, edge lines, report). Bad crossings are repaired or skipped (``crossing_geometry``),
    counted and reported in one ``UserWarning`` naming ``source`` (the map file); good ones are kept
    whatever their neighbours are."""
    polys, lines = [], []
    bad: dict[str, list[str]] = {status: [] for status in CROSSING_PROBLEMS}
    for cid, ring, edges in crossings:
        p, e, status = crossing_geometry(ring, edges) if ring is not None else ([], [], "skipped")
        polys += p
        lines += e
        if status != "ok":
            bad[status].append(str(cid))
    parts = [f"{len(ids)} {CROSSING_PROBLEMS[status]} ({some_of(ids)})" for status, ids in bad.items() if ids]
    report = f"{source}: " + "; ".join(parts) if parts else ""
    if report:
        warnings.warn(report, stacklevel=3)
    return np.array(polys, dtype=object), np.array(lines, dtype=object), report


def load_location_map(dataroot: str | Path, location: str) -> _LocationMap:
    """Read ``maps/expansion/<location>.json`` with the devkit and build the geometry index."""
    from nuscenes.map_expansion.map_api import NuScenesMap, locations

    path = map_expansion_path(dataroot, location)
    if not path.is_file():
        root = Path(dataroot)  # the expansion's zip unpacked one level off: "download it" did not say where it was
        near = [p for p in (root / "expansion" / path.name, root / "maps" / path.name,
                            root / "maps" / "expansion" / "expansion" / path.name) if p.is_file()]
        where = (f"; {near[0]} is there: move its folder's map files to {path.parent}, where the devkit reads them"
                 if near else f"; download the nuScenes map expansion (v1.3) and unpack it into {root / 'maps'}")
        raise MapError(f"map expansion file not found: {path} (location '{location}'){where}")
    if location not in locations:
        raise MapError(f"unknown map location '{location}' in {path}; the devkit knows {', '.join(locations)}")
    try:
        nmap = NuScenesMap(dataroot=str(dataroot), map_name=location)
    except Exception as e:  # the devkit raises bare Exceptions / KeyErrors on bad files
        raise MapError(f"cannot read map expansion file {path}: {_map_file_problem(path) or f'{type(e).__name__}: {e}'}"
                       ) from None

    def record(table: str, token, layer: str, rtoken) -> dict:
        try:
            return nmap.get(table, token)
        except (KeyError, TypeError):
            raise MapError(f"map expansion file {path}: {layer} record {rtoken} names {table} {token}, which the "
                           f"file's {table} table does not hold; the file is corrupt (re-download the map expansion)"
                           ) from None

    def nodes(tokens, layer: str, rtoken, finite: bool = True) -> np.ndarray:
        """[P, 2] of the nodes ``tokens`` (the devkit's extract_line / extract_polygon read them the same way), a
        MapError naming the record for a missing node, a coordinate that is no number or (``finite``) NaN."""
        try:
            xy = np.array([[float(record("node", t, layer, rtoken)[k]) for k in ("x", "y")] for t in tokens],
                          dtype=np.float64).reshape(-1, 2)
        except (KeyError, TypeError, ValueError) as e:  # a GEOS / NumPy error named nothing of the file's
            raise MapError(f"map expansion file {path}: {layer} record {rtoken}: a node has no number x / y "
                           f"({type(e).__name__}: {e}); the file is corrupt") from None
        if finite and not np.isfinite(xy).all():
            raise MapError(f"map expansion file {path}: {layer} record {rtoken}: its nodes hold NaN or infinite "
                           "coordinates; the file is corrupt (re-download the map expansion)")
        return xy

    dividers, short = [], []
    for layer in DIVIDER_LAYERS:
        for r in getattr(nmap, layer):
            line = record("line", r.get("line_token"), layer, r.get("token"))
            xy = nodes(line.get("node_tokens", ()), layer, r.get("token"))
            if len(xy) == 1:  # GEOS refused a one-point line with an error naming nothing of the map's
                short.append(str(r.get("token")))
            elif len(xy):
                dividers.append(LineString(xy))
    if short:
        warnings.warn(f"{path}: {len(short)} divider line(s) of one point skipped ({some_of(short)})", stacklevel=2)
    dividers = np.array([g for g in dividers if not g.is_empty], dtype=object)

    def crossing_rings():
        for r in getattr(nmap, PED_LAYER):
            # the exterior nodes as stored (the devkit's extract_polygon would raise on < 4 coordinates); a NaN
            # node makes the crossing degenerate (skipped and reported by collect_crossings)
            poly = record("polygon", r.get("polygon_token"), PED_LAYER, r.get("token"))
            yield r["token"], nodes(poly.get("exterior_node_tokens", ()), PED_LAYER, r["token"], finite=False), None

    peds, ped_edges, report = collect_crossings(crossing_rings(), str(path))
    areas = []
    for layer in AREA_LAYERS:
        for r in getattr(nmap, layer):
            poly = record("polygon", r.get("polygon_token"), layer, r.get("token"))
            ring = nodes(poly.get("exterior_node_tokens", ()), layer, r.get("token"))
            holes = [h for h in (nodes(h.get("node_tokens", ()), layer, r.get("token")) for h in poly.get("holes", ()))
                     if len(h)]
            if len(ring) >= 3 and all(len(h) >= 3 for h in holes):  # fewer: no area (GEOS would raise)
                areas.append((str(r.get("token")), Polygon(ring, holes)))
    invalid = [token for token, a in areas if not a.is_valid]
    if invalid:  # skipped as the devkit's _get_layer_polygon does, but no longer with no word (a boundary lost)
        warnings.warn(f"{path}: {len(invalid)} invalid (self-intersecting) road_segment / lane polygon(s) skipped, "
                      f"their boundaries not drawn ({some_of(invalid)})", stacklevel=2)
    areas = np.array([a for _, a in areas if a.is_valid and not a.is_empty], dtype=object)
    return _LocationMap(dividers, peds, ped_edges, areas, crossing_report=report)


def _map_file_problem(path: Path) -> str | None:
    """Why a map expansion file the devkit refused is not one, in words (an empty object or a list was "an outdated
    map version (%s)", a missing layer a bare KeyError); None when it looks like one."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        return f"not valid JSON ({type(e).__name__}: {e})"
    if not isinstance(data, dict):
        return (f"it holds a JSON {type(data).__name__}, not a map expansion (an object of layers: node, line, "
                "polygon, ...)")
    version = data.get("version")
    if isinstance(version, str) and version < "1.3":  # the devkit's own words: "an outdated map version (%s)!"
        return (f"its version is {version}, an earlier map expansion; the devkit reads version 1.3: download the map "
                "expansion v1.3 (nuScenes-map-expansion-v1.3.zip) and unpack it into the dataroot's maps/ folder")
    missing = [k for k in ("version", "node", "line", "polygon", *DIVIDER_LAYERS, PED_LAYER, *AREA_LAYERS)
               if k not in data]
    if missing:
        return (f"it has no {', '.join(repr(k) for k in missing[:6])} (a map expansion v1.3 file has them): the file "
                "is incomplete or not a map expansion (re-download the map expansion)")
    return None


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


def join_collinear_edges(lines: list[LineString]) -> list[LineString]:
    """The official ``connect_lines`` (data/vector_map.py) on 2-point crossing edges: repeatedly, the first
    line is joined with the first later line whose first segment points within ``JOIN_EDGE_DEG`` of its
    own and one of whose ends lies within ``JOIN_EDGE_M`` of one of its ends (tested in the order
    begin-begin, begin-end, end-begin, end-end); the joined line runs between the two other ends and
    takes the first line's place. A line that joins nothing is final."""
    todo = [np.asarray(ln.coords, dtype=np.float64) for ln in lines]
    out: list[LineString] = []
    while todo:
        a = todo[0]
        da = a[1] - a[0]
        for i in range(1, len(todo)):
            b = todo[i]
            db = b[1] - b[0]
            angle = np.degrees(np.arctan2(da[0] * db[1] - da[1] * db[0], da @ db))
            if abs(angle) > JOIN_EDGE_DEG:
                continue
            ends = ((a[0], b[0], a[-1], b[-1]), (a[0], b[-1], a[-1], b[0]), (a[-1], b[0], a[0], b[-1]),
                    (a[-1], b[-1], a[0], b[0]))
            join = next(((p, q) for e1, e2, p, q in ends if np.hypot(*(e1 - e2)) < JOIN_EDGE_M), None)
            if join is None:
                continue
            todo[0] = np.array(join)
            del todo[i]
            break
        else:
            out.append(LineString(todo.pop(0)))
    return [ln for ln in out if ln.length > MIN_LENGTH_M]


def _lines(geom) -> list[LineString]:
    """The non-degenerate LineStrings in a clipping result (LineString, Multi*, collection)."""
    return [g for g in shapely.get_parts(geom) if g.geom_type == "LineString" and g.length > MIN_LENGTH_M]


def _polygons(geom) -> list[Polygon]:
    """The polygons of positive area in a clipping result (or of ``make_valid``'s)."""
    return [g for g in shapely.get_parts(geom) if g.geom_type == "Polygon" and g.area > 0]


def _rings(poly: Polygon, exterior_ccw: bool) -> list[LineString]:
    """The polygon's rings as lines, the exterior counter-clockwise if ``exterior_ccw`` (else clockwise)
    and the interiors the other way (shapely's ``orient``, with GEOS's orientation test)."""
    rings = [poly.exterior, *poly.interiors]
    want = np.array([exterior_ccw] + [not exterior_ccw] * (len(rings) - 1))
    flip = shapely.is_ccw(np.array(rings, dtype=object)) != want
    return [LineString(np.asarray(r.coords)[::-1] if f else r.coords) for r, f in zip(rings, flip)]


class LocalMapBuilder:
    """``builder(location, x, y, yaw) -> list of polyline dicts`` (see the module docstring).

    ``ped_crossing``: the crossing convention, one of ``PED_CROSSING_CONVENTIONS`` (config
    ``data.ped_crossing``). Map files are read once per location, when first asked for (``location_map``).
    """

    def __init__(self, dataroot: str | Path, grid: BEVGrid, sample_dist: float = 1.5, ped_crossing: str = "edges"):
        if sample_dist <= 0:
            raise UserError(f"config key 'data.sample_dist' must be > 0, got {sample_dist}")
        if ped_crossing not in PED_CROSSING_CONVENTIONS:
            raise UserError(f"config key 'data.ped_crossing' must be one of {', '.join(PED_CROSSING_CONVENTIONS)}, "
                            f"got {ped_crossing!r}")
        self.dataroot = Path(dataroot)
        self.grid = grid
        self.sample_dist = sample_dist
        self.ped_crossing = ped_crossing
        self._maps: dict[str, _LocationMap] = {}
        self._clip_box, self._edge_box = (box(grid.xmin + m, grid.ymin + m, grid.xmax - m, grid.ymax - m)
                                          for m in (INSIDE_EPS_M, EDGE_MARGIN_M))

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
        x0, y0, x1, y1 = lmap.bounds
        if np.isfinite(lmap.bounds).all() and patch.distance(box(x0, y0, x1, y1)) > OFF_MAP_M:
            raise MapError(f"the ego position ({x:.1f}, {y:.1f}) lies {patch.distance(box(x0, y0, x1, y1)) / 1000:.0f} "
                           f"km outside the map of location '{location}' (x "
                           f"{x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f} m): ego poses in millimetres, or a log of "
                           "another location (nuScenes: the log table's 'location'; AV2: the log's map/ folder)?")
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s], [s, c]])  # ego -> global; global -> ego is (p - t) @ rot

        def to_ego(geoms: np.ndarray) -> np.ndarray:
            return shapely.transform(geoms, lambda p: (p - [x, y]) @ rot)

        def to_global(pts: np.ndarray) -> np.ndarray:
            return pts @ rot.T + [x, y]

        def query(tree: shapely.STRtree) -> np.ndarray:  # map order, so that the output does not depend on the tree
            return np.sort(tree.query(patch, predicate="intersects"))

        out: list[dict] = []
        out += [self._poly(line, DIVIDER, closed=False)
                for line in self._divider_pieces(lmap, query(lmap.divider_tree), to_ego, to_global)]
        out += self._crossings(lmap, query, to_ego)
        # boundaries: union of road segments and lanes, exterior and interior rings
        cand = lmap.areas[query(lmap.area_tree)]
        if len(cand):
            union = shapely.union_all(shapely.intersection(to_ego(cand), self._clip_box))
            for poly in _polygons(union):
                for ring in _rings(poly, exterior_ccw=False):
                    out += self._ring_pieces(ring)
        return out

    def _divider_pieces(self, lmap: _LocationMap, idx: np.ndarray, to_ego, to_global) -> list[LineString]:
        """The divider lines clipped to the grid; with a divider exclusion zone (AV2), each clipped piece
        with more than ``EXCLUDED_FRACTION`` of its length in the zone (measured at points every
        ``EXCLUDED_STEP_M``) is dropped (the rule on the clipped pieces, as StreamMapNet's
        ``remove_boundary_dividers``), and the kept ones are line-merged (``merge_dividers``)."""
        pieces = [ln for g in shapely.intersection(to_ego(lmap.dividers[idx]), self._clip_box) for ln in _lines(g)]
        if lmap.divider_exclusion is not None and pieces:
            geoms = np.array(pieces, dtype=object)
            counts = np.maximum(np.ceil(shapely.length(geoms) / EXCLUDED_STEP_M).astype(np.int64), 1)
            starts = np.cumsum(counts) - counts
            dists = (np.arange(counts.sum()) - np.repeat(starts, counts) + 0.5) * EXCLUDED_STEP_M
            pts = to_global(shapely.get_coordinates(shapely.line_interpolate_point(np.repeat(geoms, counts), dists)))
            inside = shapely.contains_xy(lmap.divider_exclusion, pts[:, 0], pts[:, 1])
            keep = np.add.reduceat(inside.astype(np.float64), starts) / counts <= EXCLUDED_FRACTION
            pieces = [p for p, k in zip(pieces, keep) if k]
        if lmap.merge_dividers and len(pieces) > 1:
            pieces = _lines(shapely.line_merge(MultiLineString(pieces)))
        return pieces

    def _crossings(self, lmap: _LocationMap, query, to_ego) -> list[dict]:
        """Class 1 in the builder's convention (module docstring)."""
        if self.ped_crossing == "edges":
            cand = lmap.ped_edges[query(lmap.ped_edge_tree)]
            lines = [ln for g in shapely.intersection(to_ego(cand), self._clip_box) for ln in _lines(g)]
            return [self._poly(ln, PED_CROSSING, closed=False) for ln in join_collinear_edges(lines)]
        cand = lmap.peds[query(lmap.ped_tree)]
        if not len(cand):
            return []
        clipped = shapely.intersection(to_ego(cand), self._clip_box)
        if self.ped_crossing == "union":  # MapTR: exterior clockwise, interiors counter-clockwise
            parts, ccw = _polygons(shapely.union_all(clipped)), False
        else:  # each, StreamMapNet: counter-clockwise
            parts, ccw = [p for g in clipped for p in _polygons(g)], True
        return [self._poly(ring, PED_CROSSING, closed=True) for poly in parts for ring in _rings(poly, ccw)]

    def _ring_pieces(self, ring: LineString) -> list[dict]:
        if ring.within(self._edge_box):
            return [self._poly(ring, BOUNDARY, closed=True)]
        cut = shapely.intersection(ring, self._edge_box)
        if isinstance(cut, MultiLineString):
            cut = shapely.line_merge(cut)
        return [self._poly(line, BOUNDARY, closed=False) for line in _lines(cut)]

    def _poly(self, line: LineString, label: int, closed: bool) -> dict:
        return {"pts": resample_line(line, self.sample_dist, closed), "label": label, "closed": closed}
