"""targets.py: vertex cells, distance transform and vertex graph from hand-made polylines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt
from shapely.geometry import LineString

from instagram_hdmap.data.local_map import resample_line
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.targets import (
    NO_VERTEX,
    build_targets,
    cells_to_vertices_px,
    distance_transform,
    graph_to_polylines,
    vertex_graph,
)

GRID = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)  # paper: 400 x 200, 50 x 25 cells
GRID_LONG = BEVGrid(-50.0, 50.0, -50.0, 50.0, 0.25, 8)  # long range: 400 x 400


def _line(pts, label=0, sample_dist=1.5) -> dict:
    return {"pts": resample_line(LineString(pts), sample_dist), "label": label, "closed": False}


def _ring(pts, label=1, sample_dist=1.5) -> dict:
    pts = np.asarray(pts, dtype=float)
    return {"pts": resample_line(LineString(np.r_[pts, pts[:1]]), sample_dist, closed=True), "label": label,
            "closed": True}


def scene(rng: np.random.Generator, extent: float = 1.0, sample_dist: float = 1.5) -> list[dict]:
    """~25 map elements laid out on a 60 m x 30 m grid (scaled by ``extent``) so that different
    elements never come within a cell of each other: wavy dividers / boundaries at y = -12, 0, 12,
    rotated ped crossings at y = 6, round islands at y = -6, short dividers at y = -3."""
    elements = []  # (points, label, closed) before scaling
    x = np.linspace(-28, 28, 80)
    for y in (-12.0, 0.0, 12.0):
        elements.append((np.c_[x, y + np.sin(x / 7 + rng.uniform(0, 2 * np.pi))], int(rng.choice([0, 2])), False))
    for cx in np.arange(-24.0, 25.0, 8.0):
        a = rng.uniform(0, np.pi)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        box = np.array([[-1.2, -0.8], [1.2, -0.8], [1.2, 0.8], [-1.2, 0.8]]) @ R.T + [cx, 6.0]
        elements.append((box, 1, True))
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    for cx in np.arange(-20.0, 21.0, 10.0):
        elements.append((np.c_[cx + 1.2 * np.cos(t), -6.0 + 1.2 * np.sin(t)], 2, True))
    for cx in np.arange(-26.0, 27.0, 13.0):  # some shorter than a cell
        elements.append((np.array([[cx, -3.0], [cx + rng.uniform(0.1, 4.0), -3.0]]), 0, False))
    polys = []
    for pts, label, closed in elements:
        pts = pts * extent
        if closed:
            polys.append(_ring(pts, label, sample_dist))
        else:
            polys.append(_line(pts, label, sample_dist))
    return polys


def point_to_polyline(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance of each point [N, 2] to the polyline (segments) [P, 2], [N]."""
    if len(poly) == 1:
        return np.linalg.norm(points - poly[0], axis=-1)
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = ((points[:, None] - a) * ab).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12)
    proj = a + np.clip(t, 0, 1)[..., None] * ab
    return np.linalg.norm(points[:, None] - proj, axis=-1).min(1)


def round_trip_error(p: np.ndarray, q: np.ndarray) -> float:
    """Symmetric vertex-to-curve Hausdorff distance between two polylines (metres):
    max( max over P's vertices of the distance to Q's curve, max over Q's vertices of the distance to
    P's curve ). Vertex positions are compared to the other *curve*, not to its vertices, because the
    graph keeps one vertex per cell: a dropped vertex is bridged by the edge from its kept
    predecessor to its kept successor, and what matters is how far the curve moved."""
    return float(max(point_to_polyline(p, q).max(), point_to_polyline(q, p).max()))


# --- shapes, cells, distance transform ----------------------------------------------------------------


def test_keys_shapes_dtypes():
    t = build_targets(scene(np.random.default_rng(0)), GRID)
    M = len(t["gt_vertices_px"])
    assert M > 100
    assert t["gt_vertex_cells"].shape == (25, 50) and t["gt_vertex_cells"].dtype == torch.int64
    assert t["gt_distance"].shape == (3, 200, 400) and t["gt_distance"].dtype == torch.float32
    assert t["gt_vertices_px"].shape == (M, 2) and t["gt_vertices_px"].dtype == torch.float32
    assert t["gt_vertex_mask"].shape == (M,) and t["gt_vertex_mask"].all()
    for k in ("labels", "instance", "order", "next", "prev"):
        assert t[f"gt_vertex_{k}"].shape == (M,) and t[f"gt_vertex_{k}"].dtype == torch.int64


@pytest.mark.parametrize("grid", [GRID, GRID_LONG])
def test_cells_one_label_each_and_match_graph(grid):
    t = build_targets(scene(np.random.default_rng(1), extent=grid.W * grid.resolution / 60), grid)
    cells = t["gt_vertex_cells"]
    S = grid.cell_size
    assert cells.shape == (grid.Hc, grid.Wc)
    assert ((cells >= 0) & (cells <= S * S)).all()
    # the non-dustbin cells are exactly the graph vertices (one per cell, no vertex lost)
    decoded = cells_to_vertices_px(cells, S)
    assert len(decoded) == len(t["gt_vertices_px"]) == int((cells < S * S).sum())
    as_set = lambda x: set(map(tuple, x.long().tolist()))  # noqa: E731
    assert as_set(decoded) == as_set(t["gt_vertices_px"])
    # and the depth-to-space order of docs/conventions.md puts a one-hot back at the vertex pixel
    onehot = torch.nn.functional.one_hot(cells, S * S + 1)[..., : S * S].permute(2, 0, 1)[None].float()
    heat = onehot.reshape(1, S, S, grid.Hc, grid.Wc).permute(0, 3, 1, 4, 2).reshape(grid.H, grid.W)
    v, u = torch.nonzero(heat, as_tuple=True)
    assert as_set(torch.stack([u, v], -1)) == as_set(t["gt_vertices_px"])


def test_vertex_pixels_are_polyline_pixels():
    polys = scene(np.random.default_rng(2))
    t = build_targets(polys, GRID)
    allpix = {tuple(p) for poly in polys for p in GRID.px_index(GRID.m_to_px(poly["pts"])).tolist()}
    assert {tuple(p) for p in t["gt_vertices_px"].long().tolist()} <= allpix


def test_distance_transform_exact_and_zero_on_lines():
    polys = scene(np.random.default_rng(3))
    dt = distance_transform(polys, GRID, num_classes=3, dt_clip=10.0)
    assert dt.min() >= 0 and dt.max() <= 10.0
    for k in range(3):
        lines = dt[k].numpy() == 0
        assert lines.sum() > 100
        # an independent exact Euclidean distance transform of the same zero set, clipped
        ref = np.minimum(distance_transform_edt(~lines), 10.0)
        assert np.abs(dt[k].numpy() - ref).max() < 1e-3
        # every polyline point's pixel is on the rasterised line, and every line pixel lies on a
        # polyline of that class (within the 8-connected rasterisation's half-diagonal)
        mine = [GRID.m_to_px(p["pts"]) for p in polys if p["label"] == k]
        uv = np.concatenate([GRID.px_index(m) for m in mine])
        assert lines[uv[:, 1], uv[:, 0]].all()
        vv, uu = np.nonzero(lines)
        pix = np.stack([uu, vv], -1).astype(float)
        near = np.min([point_to_polyline(pix, m) for m in mine], axis=0)
        assert near.max() <= math.sqrt(2) / 2 + 0.5 + 1e-6


def test_empty_map_gives_valid_empty_targets():
    t = build_targets([], GRID, num_classes=3, dt_clip=10.0)
    assert (t["gt_vertex_cells"] == GRID.cell_size**2).all()
    assert (t["gt_distance"] == 10.0).all()
    assert t["gt_vertices_px"].shape == (0, 2) and t["gt_vertex_next"].shape == (0,)
    assert graph_to_polylines(t["gt_vertices_px"], t["gt_vertex_labels"], t["gt_vertex_next"]) == []


# --- vertex graph -----------------------------------------------------------------------------------


def test_edges_join_same_instance_in_order():
    polys = scene(np.random.default_rng(4))
    g = vertex_graph(polys, GRID)
    nxt, prv = g["gt_vertex_next"], g["gt_vertex_prev"]
    inst, order = g["gt_vertex_instance"], g["gt_vertex_order"]
    M = len(nxt)
    # next and prev are inverse permutations on their edges
    has = nxt >= 0
    assert (prv[nxt[has]] == torch.arange(M)[has]).all()
    assert int((prv >= 0).sum()) == int(has.sum())
    # an edge never leaves its instance and steps forward by one (or closes a cycle to order 0)
    i = torch.arange(M)[has]
    assert (inst[nxt[i]] == inst[i]).all()
    step = order[nxt[i]] == order[i] + 1
    wrap = (order[nxt[i]] == 0) & torch.tensor([polys[k]["closed"] for k in inst[i].tolist()])
    assert (step | wrap).all()
    # labels are those of the instance; vertices sorted by (instance, order)
    assert (g["gt_vertex_labels"] == torch.tensor([polys[k]["label"] for k in inst.tolist()])).all()
    key = inst * 10_000 + order
    assert (key[1:] > key[:-1]).all()
    # metres and pixels agree
    assert torch.allclose(g["gt_vertices_m"], GRID.px_to_m(g["gt_vertices_px"]), atol=1e-4)


def test_closed_ped_crossing_is_cycle():
    box = [[-3.0, -2.0], [3.0, -2.0], [3.0, 2.0], [-3.0, 2.0]]
    g = vertex_graph([_ring(box)], GRID)
    nxt = g["gt_vertex_next"].tolist()
    M = len(nxt)
    assert M >= 8 and NO_VERTEX not in nxt and NO_VERTEX not in g["gt_vertex_prev"].tolist()
    seen, i = [], 0
    for _ in range(M):
        seen.append(i)
        i = nxt[i]
    assert i == 0 and sorted(seen) == list(range(M))  # one cycle through every vertex
    (poly,) = graph_to_polylines(g["gt_vertices_m"], g["gt_vertex_labels"], g["gt_vertex_next"])
    assert poly["closed"] and (poly["pts"][0] == poly["pts"][-1]).all() and len(poly["pts"]) == M + 1
    # an open divider is a path: first has no prev, last no next
    g = vertex_graph([_line([[-10, 0], [10, 0]])], GRID)
    assert g["gt_vertex_prev"][0] == NO_VERTEX and g["gt_vertex_next"][-1] == NO_VERTEX


def test_one_vertex_per_cell_rules():
    def px(u, v):  # metres of BEV pixel (u, v)
        return GRID.px_to_m(np.array([u, v], dtype=float))

    # consecutive points of one line in one cell merge; the endpoint wins over the interior point
    line = {"pts": np.stack([px(3, 3), px(12, 3), px(18, 3), px(21, 4)]), "label": 0, "closed": False}
    g = vertex_graph([line], GRID)
    assert g["gt_vertices_px"].tolist() == [[3, 3], [12, 3], [21, 4]]
    assert g["gt_vertex_next"].tolist() == [1, 2, -1] and g["gt_vertex_order"].tolist() == [0, 1, 2]
    # two instances in one cell: the lower class wins, the other instance is bridged over it
    a = {"pts": np.stack([px(0, 40), px(10, 40), px(20, 40)]), "label": 2, "closed": False}
    b = {"pts": np.stack([px(10, 30), px(11, 41), px(10, 52)]), "label": 0, "closed": False}
    g = vertex_graph([a, b], GRID)
    assert g["gt_vertices_px"].tolist() == [[0, 40], [20, 40], [10, 30], [11, 41], [10, 52]]
    assert g["gt_vertex_next"].tolist() == [1, -1, 3, 4, -1]
    assert g["gt_vertex_prev"].tolist() == [-1, 0, -1, 2, 3]
    # the rule does not depend on the instance order: swap the list, the same vertex survives
    g2 = vertex_graph([b, a], GRID)
    assert {tuple(p) for p in g2["gt_vertices_px"].long().tolist()} == {
        tuple(p) for p in g["gt_vertices_px"].long().tolist()
    }
    # a closed shape that collapses to 2 cells is one open edge, to 1 cell an isolated vertex
    two = {"pts": np.stack([px(60, 60), px(70, 60), px(66, 63), px(60, 60)]), "label": 1, "closed": True}
    g = vertex_graph([two], GRID)
    assert g["gt_vertices_px"].tolist() == [[60, 60], [70, 60]] and g["gt_vertex_next"].tolist() == [1, -1]
    dot = {"pts": np.stack([px(50, 50), px(51, 50), px(50, 51), px(50, 50)]), "label": 1, "closed": True}
    g = vertex_graph([dot], GRID)
    assert g["gt_vertices_px"].tolist() == [[50, 50]] and g["gt_vertex_next"].tolist() == [-1]
    # points on or beyond the grid edge are clamped into it
    edge = {"pts": np.array([[30.0, 15.0], [40.0, 20.0]]), "label": 0, "closed": False}
    g = vertex_graph([edge], GRID)
    assert g["gt_vertices_px"].tolist() == [[GRID.W - 1, GRID.H - 1]]


@pytest.mark.parametrize("grid,extent", [(GRID, 1.0), (GRID_LONG, 1.6)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_round_trip_within_cell_quantisation(grid, extent, seed):
    """polylines -> vertex graph -> polylines: same instances (order, class, open/closed) and a
    symmetric vertex-to-curve Hausdorff error (round_trip_error) <= S * res * sqrt(2) / 2.

    Pixel snapping moves a kept vertex by <= res * sqrt(2) / 2; a vertex dropped because its cell
    already holds a vertex of its instance lies within one cell of the kept one, and on these
    well-separated, moderately curved elements the bridging edge passes within half a cell diagonal.
    """
    polys = scene(np.random.default_rng(seed), extent=extent)
    g = vertex_graph(polys, grid)
    back = graph_to_polylines(g["gt_vertices_m"], g["gt_vertex_labels"], g["gt_vertex_next"], min_vertices=1)
    assert len(back) == len(polys)
    bound = grid.cell_size * grid.resolution * math.sqrt(2) / 2
    errors = []
    for p, q in zip(polys, back):
        assert q["label"] == p["label"]
        if len(q["pts"]) > 2 or not p["closed"]:
            assert q["closed"] == p["closed"]
        errors.append(round_trip_error(p["pts"], q["pts"]))
    assert max(errors) <= bound, (max(errors), bound)
    # the exact part: kept vertices are the input points snapped to pixel centres
    assert min(errors) <= grid.resolution * math.sqrt(2) / 2 + 1e-5


def test_graph_to_polylines_ignores_padding():
    polys = [_line([[-10, 0], [10, 0]]), _ring([[0, 5], [4, 5], [4, 8], [0, 8]])]
    g = vertex_graph(polys, GRID)
    M = len(g["gt_vertices_m"])
    pad = 5
    verts = torch.cat([g["gt_vertices_m"], torch.zeros(pad, 2)])
    labels = torch.cat([g["gt_vertex_labels"], torch.full((pad,), -1)])
    nxt = torch.cat([g["gt_vertex_next"], torch.tensor([M, M + 1, -1, -1, 0])])  # garbage in padding
    mask = torch.arange(M + pad) < M
    a = graph_to_polylines(verts, labels, nxt, mask)
    b = graph_to_polylines(g["gt_vertices_m"], g["gt_vertex_labels"], g["gt_vertex_next"])
    assert len(a) == len(b) == 2
    for x, y in zip(a, b):
        assert np.array_equal(x["pts"], y["pts"]) and x["label"] == y["label"] and x["closed"] == y["closed"]
