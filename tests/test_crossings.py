"""Ped-crossing conventions (data.ped_crossing: edges | union | each, data/local_map.py) on hand-made maps
of both datasets: a junction whose four crossings overlap at the corners (as real crossings do), two
crossings in a row whose edges the official rule joins, and bad crossing polygons (repaired or skipped,
reported once per map, never at the cost of a valid neighbour)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import LinearRing, LineString, Polygon

from instagram_hdmap.data.local_map import (
    PED_CROSSING,
    LocalMapBuilder,
    crossing_geometry,
    join_collinear_edges,
)
from instagram_hdmap.geometry import BEVGrid
from test_dataset import _MapWriter, _rect

GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)
LOCATION = "singapore-onenorth"

# A junction at the origin: four crossings 4 m wide across 18 m of road, overlapping 1 m x 1 m at each
# corner; the union is one ring around the junction with a hole (its inner outline).
JUNCTION = [_rect(8, 12, -9, 9), _rect(-12, -8, -9, 9), _rect(-9, 9, 8, 12), _rect(-9, 9, -12, -8)]
# Two crossings in a row, 1 m apart along the road's edge: their long edges point the same way and end
# within 2 m of each other, so the official connect_lines joins them (two lines of 17 m, not four).
ROW = [_rect(20, 23, -9, -1), _rect(20, 23, 0, 8)]
ALL = JUNCTION + ROW


def _pts(line: LineString, step: float = 0.1) -> np.ndarray:
    return shapely.get_coordinates(shapely.line_interpolate_point(line, np.arange(0.0, line.length, step)))


def coverage(reference, polylines: list[dict], tol: float = 0.3) -> float:
    """Fraction of the points along ``reference`` (lines) within ``tol`` of the polylines."""
    ref = np.concatenate([_pts(line) for line in reference])
    got = shapely.union_all([LineString(p["pts"]) for p in polylines])
    return float((shapely.distance(shapely.points(ref), got) < tol).mean())


def _ring(rect) -> LineString:
    return LineString([*rect, rect[0]])


def _peds(polys):
    return [p for p in polys if p["label"] == PED_CROSSING]


@pytest.fixture(scope="module")
def crossing_map(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("crossings")
    m = _MapWriter()
    m.polygon("road_segment", _rect(-100, 100, -9, 9))
    for rect in ALL:
        m.polygon("ped_crossing", rect)
    m.write(root, LOCATION)
    return root


def test_the_three_conventions_keep_every_crossing_edge(crossing_map):
    build = {c: LocalMapBuilder(crossing_map, GRID, 0.5, c)(LOCATION, 0.0, 0.0, 0.0)
             for c in ("edges", "union", "each")}
    # each (StreamMapNet): one counter-clockwise ring per crossing, every crossing's outline
    each = _peds(build["each"])
    assert len(each) == len(ALL) and all(p["closed"] for p in each)
    assert all(LinearRing(p["pts"]).is_ccw for p in each)
    assert coverage([_ring(r) for r in ALL], each) == 1.0
    # union (MapTR): the junction is one part with an exterior (clockwise) and an interior ring
    # (counter-clockwise, the junction's inner outline that an exterior-only union drops); the row's
    # two crossings do not touch: two more rings
    union = _peds(build["union"])
    assert len(union) == 4 and all(p["closed"] for p in union)
    junction = shapely.union_all([Polygon(r) for r in JUNCTION])
    assert len(junction.interiors) == 1
    inner = [p for p in union if Polygon(p["pts"]).within(Polygon(junction.exterior)) and Polygon(p["pts"]).area < 300]
    assert len(inner) == 1 and LinearRing(inner[0]["pts"]).is_ccw
    outer = max(union, key=lambda p: Polygon(p["pts"]).area)
    assert not LinearRing(outer["pts"]).is_ccw
    assert coverage([junction.exterior, *junction.interiors, *(_ring(r) for r in ROW)], union) == 1.0
    assert coverage([junction.interiors[0]], union) == 1.0
    # edges (HDMapNet / official InstaGraM): two open polylines per junction crossing, along its two
    # longest edges; the row's four edges joined into two lines spanning both crossings
    edges = _peds(build["edges"])
    assert not any(p["closed"] for p in edges) and len(edges) == 2 * len(JUNCTION) + 2
    long_edges = [LineString([(8, -9), (8, 9)]), LineString([(12, -9), (12, 9)]), LineString([(-12, -9), (-12, 9)]),
                  LineString([(-8, -9), (-8, 9)]), LineString([(-9, 8), (9, 8)]), LineString([(-9, 12), (9, 12)]),
                  LineString([(-9, -12), (9, -12)]), LineString([(-9, -8), (9, -8)])]
    assert coverage(long_edges, edges) == 1.0
    joined = sorted((p for p in edges if p["pts"][:, 0].min() > 15), key=lambda p: p["pts"][0, 0])
    assert [round(float(np.ptp(p["pts"][:, 1])), 3) for p in joined] == [17.0, 17.0]
    assert coverage([LineString([(20, -9), (20, 8)]), LineString([(23, -9), (23, 8)])], joined) == 1.0
    for p in edges:  # resampled every 0.5 m along the line, plus its end point
        steps = np.linalg.norm(np.diff(p["pts"], axis=0), axis=1)
        assert steps.max() <= 0.5 + 1e-6 and GRID.inside_m(p["pts"]).all()


def test_edges_take_the_two_longest_edges_in_the_rings_direction():
    ring = np.array([[0, 0], [10, 0], [10, 3], [0, 4], [0, 0]], dtype=float)  # edges 10, 3, 10.05, 4
    polys, lines, status = crossing_geometry(ring)
    assert status == "ok" and len(polys) == 1
    # official: np.argsort(dist)[-2:] -> the second longest, then the longest; each in the ring's direction
    assert [list(ln.coords) for ln in lines] == [[(0, 0), (10, 0)], [(10, 3), (0, 4)]]
    # AV2 stores a crossing's two principal edges: those are its edges, whatever their lengths
    _, lines, _ = crossing_geometry(ring[:4], edges=(ring[[0, 1]], ring[[3, 2]]))
    assert [list(ln.coords) for ln in lines] == [[(0, 0), (10, 0)], [(0, 4), (10, 3)]]


def test_join_collinear_edges_is_the_official_connect_lines():
    a = LineString([(0, 0), (0, 5)])
    b = LineString([(0, 6), (0, 10)])  # same direction, begin of b 1 m after the end of a: joined
    c = LineString([(3, 10), (3, 0)])  # antiparallel to both: kept apart
    d = LineString([(0.1, 13), (0.1, 20)])  # same direction but 3 m away: kept apart
    out = join_collinear_edges([a, b, c, d])
    assert [list(ln.coords) for ln in out] == [[(0, 0), (0, 10)], [(3, 10), (3, 0)], [(0.1, 13), (0.1, 20)]]
    e = LineString([(0, 0), (5, 0.6)])  # 6.8 deg off a line along x: not joined with it
    assert len(join_collinear_edges([LineString([(-5, 0), (0, 0)]), e])) == 2


# --- bad crossing polygons -----------------------------------------------------------------------------

BOWTIE = [[10, -8], [14, 8], [10, 8], [14, -8]]  # self-intersecting: two triangles meeting at (12, 0)
DEGENERATE = [[0, 0], [4, 0], [0, 0], [4, 0]]  # 2 distinct points
VALID = _rect(-24, -20, -8, 8)


def _check_bad_input(build, source: str, bowtie_edges: list[LineString]) -> None:
    """``build(convention)`` -> (builder, location); the map holds BOWTIE, DEGENERATE and VALID;
    ``bowtie_edges``: the bowtie's two edges under ``edges``."""
    for convention in ("edges", "union", "each"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            builder, loc = build(convention)
            polys = _peds(builder(loc, 0.0, 0.0, 0.0))
            again = _peds(builder(loc, 5.0, 0.0, 0.0))  # a second sample of the same map
        reports = [w for w in caught if "crossing polygon" in str(w.message)]
        assert len(reports) == 1, [str(w.message) for w in caught]  # once per map
        msg = str(reports[0].message)
        assert source in msg and "1 invalid (self-intersecting) crossing polygon(s) repaired with make_valid" in msg
        assert "1 degenerate crossing polygon(s) (< 3 distinct points) skipped" in msg
        assert again, "the second sample lost its crossings"
        valid = _ring(VALID) if convention != "edges" else LineString([(-24, -8), (-24, 8)])
        assert coverage([valid], polys) == 1.0, convention  # the valid neighbour is kept
        assert coverage([LineString(DEGENERATE[:2])], polys) == 0.0  # nothing from the degenerate one
        # the bowtie's four sides are all there (make_valid's two triangles), or its two edges
        sides = bowtie_edges if convention == "edges" else [LineString([BOWTIE[i], BOWTIE[(i + 1) % 4]])
                                                            for i in range(4)]
        assert coverage(sides, polys) == 1.0, convention


def test_bad_crossings_of_a_nuscenes_map_are_repaired_or_skipped_and_reported_once(tmp_path):
    m = _MapWriter()
    m.polygon("road_segment", _rect(-100, 100, -9, 9))
    for rect in (BOWTIE, DEGENERATE, VALID):
        m.polygon("ped_crossing", rect)
    m.polygon("ped_crossing", [[50, 0], [52, 0]])  # two nodes: the devkit could not even build it
    m.write(tmp_path, LOCATION)

    def build(convention):
        return LocalMapBuilder(tmp_path, GRID, 0.5, convention), LOCATION

    for convention in ("edges", "union", "each"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            builder, _ = build(convention)
            builder(LOCATION, 0.0, 0.0, 0.0)
        (msg,) = [str(w.message) for w in caught if "crossing polygon" in str(w.message)]
        assert "2 degenerate crossing polygon(s)" in msg and builder.location_map(LOCATION).crossing_report == msg
    # the two-node polygon aside, the same checks as for AV2
    m.obj["ped_crossing"].pop()
    m.write(tmp_path, LOCATION)
    # edges: the ring's two longest edges, its diagonals
    _check_bad_input(build, f"{LOCATION}.json", [LineString(BOWTIE[0:2]), LineString(BOWTIE[2:4])])


def write_av2_map(log_dir: Path, crossings: list[tuple[list, list]], areas: list[list],
                  lanes: list[tuple[list, str, list, str]] = ()) -> None:
    """A minimal AV2 log map archive: crossings as (edge1, edge2), drivable areas as rings, lane segments
    as (left boundary, its mark type, right boundary, its mark type)."""
    def xyz(pts):
        return [{"x": float(x), "y": float(y), "z": 0.0} for x, y in pts]

    segments = {str(200 + i): {"id": 200 + i, "is_intersection": False, "lane_type": "VEHICLE",
                               "left_lane_boundary": xyz(left), "left_lane_mark_type": left_mark,
                               "right_lane_boundary": xyz(right), "right_lane_mark_type": right_mark,
                               "left_neighbor_id": None, "right_neighbor_id": None, "predecessors": [],
                               "successors": []}
                for i, (left, left_mark, right, right_mark) in enumerate(lanes)}
    obj = {"pedestrian_crossings": {str(i): {"id": i, "edge1": xyz(e1), "edge2": xyz(e2)}
                                    for i, (e1, e2) in enumerate(crossings)},
           "lane_segments": segments,
           "drivable_areas": {str(100 + i): {"id": 100 + i, "area_boundary": xyz(r)} for i, r in enumerate(areas)}}
    (log_dir / "map").mkdir(parents=True)
    (log_dir / "map" / f"log_map_archive_{log_dir.name}____PIT_city_1.json").write_text(json.dumps(obj))


def test_bad_crossings_of_an_av2_map_are_repaired_or_skipped_and_reported_once(tmp_path):
    pytest.importorskip("av2", reason='the Argoverse 2 API is the optional extra: pip install -e ".[av2]"')
    from instagram_hdmap.data.av2 import AV2LocalMapBuilder

    # AV2 stores edge1 and edge2 and builds the ring edge1 + reversed edge2: an edge2 given in the
    # opposite direction makes the bowtie
    crossings = [([BOWTIE[0], BOWTIE[3]], [BOWTIE[1], BOWTIE[2]]), ([DEGENERATE[0], DEGENERATE[1]], DEGENERATE[2:]),
                 ([VALID[0], VALID[3]], [VALID[1], VALID[2]])]
    log = tmp_path / "log-a"
    write_av2_map(log, crossings, [_rect(-100, 100, -9, 9)])

    def build(convention):
        return AV2LocalMapBuilder(tmp_path, GRID, 0.5, convention), "log-a"

    # edges: AV2's stored edge1 and edge2, whatever the polygon they make
    _check_bad_input(build, "log_map_archive_log-a____PIT_city_1.json",
                     [LineString([BOWTIE[0], BOWTIE[3]]), LineString([BOWTIE[1], BOWTIE[2]])])


def test_the_divider_on_kerb_rule_judges_the_clipped_pieces(tmp_path):
    """AV2: a painted lane boundary that runs along the kerb for most of its length, but through the middle
    of the road inside the patch, is a divider there (the rule judges each clipped piece, as StreamMapNet's
    remove_boundary_dividers does); paint along the kerb inside the patch is left to the boundary class."""
    pytest.importorskip("av2", reason='the Argoverse 2 API is the optional extra: pip install -e ".[av2]"')
    from instagram_hdmap.data.av2 import AV2LocalMapBuilder
    from instagram_hdmap.data.local_map import BOUNDARY, DIVIDER

    long_way = [[-300, -9], [-40, -9], [-30, 0], [30, 0]]  # 260 m along the kerb y = -9, 60 m mid-road
    along_kerb = [[-30, 9], [30, 9]]  # the kerb y = 9, inside the patch
    unpainted = [[-300, -12], [30, -12]]
    write_av2_map(tmp_path / "log-k", [], [_rect(-400, 100, -9, 9)],
                  lanes=[(long_way, "SOLID_WHITE", unpainted, "NONE"), (along_kerb, "SOLID_YELLOW", unpainted, "NONE")])
    polys = AV2LocalMapBuilder(tmp_path, GRID, 0.5, "each")("log-k", 0.0, 0.0, 0.0)
    dividers = [LineString(p["pts"]) for p in polys if p["label"] == DIVIDER]
    assert coverage([LineString([(-29.99, 0), (29.99, 0)])], [{"pts": np.asarray(d.coords)} for d in dividers]) == 1.0
    assert all(abs(float(np.asarray(d.coords)[:, 1].mean())) < 1 for d in dividers)  # none along y = 9
    assert any(np.allclose(p["pts"][:, 1], 9.0) for p in polys if p["label"] == BOUNDARY)


@pytest.mark.parametrize("convention", ["edges", "union", "each"])
def test_every_part_downstream_takes_each_convention(crossing_map, convention):
    """GT crossings of a convention -> targets -> the outputs of a perfect model (inference.gt_outputs) ->
    the decoders -> the same crossings (cycles for closed ones, paths for open ones), which score AP 1
    under both protocols; the distance transform draws every crossing; the BEV picture draws each one."""
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.evaluation import Evaluator
    from instagram_hdmap.inference import gt_outputs
    from instagram_hdmap.postprocess import postprocess_batch
    from instagram_hdmap.targets import build_targets
    from instagram_hdmap.visualize import bev_polylines_figure

    grid = BEVGrid(-16.0, 16.0, -16.0, 16.0, 0.25, 4)  # the junction whole, and nothing of the row
    polys = LocalMapBuilder(crossing_map, grid, 0.5, convention)(LOCATION, 0.0, 0.0, 0.0)
    peds = _peds(polys)
    assert len(peds) == {"edges": 8, "union": 2, "each": 4}[convention]
    sample = {"gt_polylines": polys, **build_targets(polys, grid)}
    dt = sample["gt_distance"][PED_CROSSING].numpy()
    for p in peds:  # every crossing polyline is drawn into its class's distance transform
        uv = np.clip(grid.px_index(grid.m_to_px(p["pts"])), 0, [grid.W - 1, grid.H - 1])
        assert (dt[uv[:, 1], uv[:, 0]] == 0).all()
    outputs = gt_outputs(collate_fn([sample]), grid, 3)
    for decode in ({"decoder": "greedy"}, {"decoder": "classwise", "match_threshold": 0.02, "min_vertices": 4},
                   {"decoder": "mutual"}):
        got = [p for p in postprocess_batch(outputs, grid, **decode)[0] if p["label"] == PED_CROSSING]
        assert sorted(p["closed"] for p in got) == sorted(p["closed"] for p in peds), decode
        # one vertex per 1 m cell: the decoded crossings follow the GT to within a cell's half diagonal
        assert coverage([LineString(p["pts"]) for p in peds], got, tol=0.75) == 1.0, decode
        for protocol in ("vector", "raster"):
            ev = Evaluator(protocol, grid=grid)
            ev.update([[dict(p, score=1.0) for p in got]], [polys])
            assert ev.compute()["AP_class"]["ped_crossing"] == pytest.approx(1.0), (decode, protocol)
    fig = bev_polylines_figure(polys, grid)
    drawn = [line for ax in fig.axes for line in ax.lines]
    assert len(drawn) >= len(polys)
