"""Procedural road network of one synthetic map, and its nuScenes map-expansion records.

Layout: a jittered grid of 3-4 x 3-4 nodes 100-150 m apart; some grid edges are removed and some
border nodes get a road running off the map, so nodes become 4-way junctions, T junctions, 90 deg
corners (a circular curve) or straight pass-throughs. The roads between junctions ("stretches")
are straight or curved (corners, gentle S-bends), with 2-6 lanes of 3.0-3.7 m; some wide roads
have a median: a raised island, i.e. a hole in the road polygon whose ring is an island-shaped
road boundary. Junctions have kerb fillets, zebra crossings and stop lines; lanes are joined by
lane connectors. Boston drives on the right, Singapore on the left.

Everything is built from one sampled cross-section grid per stretch (rows = lateral offsets of
the road edges, lane boundaries, median edges and centre line; columns = samples along the
centre path), so road polygons, lane polygons, divider lines and junction polygons share their
nodes exactly, and the union of road_segment and lane polygons is the road surface with clean
exterior and interior (island) rings. Painted markings are drawn from the same paths.
"""

from __future__ import annotations

import math
from itertools import groupby

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from shapely.geometry import LineString, Polygon, box
from shapely.ops import unary_union

from .crossings import OVERLAP_GAP_M, crossing_band, crossing_corners, drop_far_overlaps, overlapping_corners
from .map_writer import MapRecords, Ref, make_token
from .network import (
    DIRS,
    LOCATIONS,
    STOP_LINE_WIDTH,
    Chain,
    Connector,
    Junction,
    Lane,
    MapStyle,
    Markings,
    RoadNetwork,
    Stretch,
    as_polygons,
    left_of,
    yaw_of,
)
from .paint import add_patches, paint_stretch, place_props, zebra
from .paths import Path, Turtle, connect, principal_angle

SEGMENT_TYPE = {"double_yellow": "DOUBLE_SOLID_YELLOW", "single_yellow": "SINGLE_SOLID_YELLOW",
                "single_white": "SINGLE_SOLID_WHITE"}  # of the centre line, by Chain.divider

# ---------------------------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------------------------


def _connected(arms: dict, edges: set) -> bool:
    """Whether the grid edges join every node of ``arms`` into one network."""
    index = {n: i for i, n in enumerate(arms)}
    rows, cols = zip(*((index[a], index[b]) for a, b in edges))
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(index), len(index)))
    return connected_components(graph, directed=False)[0] == 1


def _code(a: tuple[int, int], b: tuple[int, int]) -> int:
    d = (b[0] - a[0], b[1] - a[1])
    return {(1, 0): 0, (0, 1): 1, (-1, 0): 2, (0, -1): 3}[d]


def _layout(rng: np.random.Generator):
    nx, ny = int(rng.integers(3, 5)), int(rng.integers(3, 5))
    margin = float(rng.uniform(70.0, 90.0))
    xs = margin + np.concatenate([[0.0], np.cumsum(rng.uniform(100.0, 150.0, nx - 1))])
    ys = margin + np.concatenate([[0.0], np.cumsum(rng.uniform(100.0, 150.0, ny - 1))])
    canvas = (float(xs[-1] + margin), float(ys[-1] + margin))
    pos = {(i, j): np.array([xs[i], ys[j]]) for i in range(nx) for j in range(ny)}
    edges = {((i, j), (i + 1, j)) for i in range(nx - 1) for j in range(ny)}
    edges |= {((i, j), (i, j + 1)) for i in range(nx) for j in range(ny - 1)}
    arms: dict[tuple[int, int], set[int]] = {n: set() for n in pos}
    for a, b in edges:
        arms[a].add(_code(a, b))
        arms[b].add(_code(b, a))
    for e in sorted(edges):
        if rng.random() > 0.3:
            continue
        a, b = e
        if len(arms[a]) <= 2 or len(arms[b]) <= 2:
            continue
        edges.discard(e)
        if not _connected(arms, edges):
            edges.add(e)
            continue
        arms[a].discard(_code(a, b))
        arms[b].discard(_code(b, a))
    stubs = set()
    for (i, j), codes in sorted(arms.items()):
        outward = [c for c, cond in ((0, i == nx - 1), (1, j == ny - 1), (2, i == 0), (3, j == 0)) if cond]
        for c in outward:
            if rng.random() < 0.3:
                stubs.add(((i, j), c))
                codes.add(c)
    return pos, arms, stubs, canvas


def _chains(pos, arms, stubs) -> list[Chain]:
    def kind(n):
        a = arms[n]
        if len(a) >= 3:
            return "junction"
        return "through" if (min(a) + 2) in a else "corner"

    done: set = set()
    chains = []
    for j in sorted(pos):
        if kind(j) != "junction":
            continue
        for a in sorted(arms[j]):
            if (j, a) in done:
                continue
            done.add((j, a))
            if (j, a) in stubs:
                chains.append(Chain(nodes=[j], dirs=[a], stub=True))
                continue
            nodes, dirs = [j], [a]
            cur, d = j, a
            while True:
                nxt = (cur[0] + int(DIRS[d][0]), cur[1] + int(DIRS[d][1]))
                nodes.append(nxt)
                if kind(nxt) == "junction":
                    done.add((nxt, (d + 2) % 4))
                    break
                d = next(c for c in arms[nxt] if c != (d + 2) % 4)
                dirs.append(d)
                cur = nxt
            chains.append(Chain(nodes=nodes, dirs=dirs, stub=False))
    return chains


def _chain_length(chain: Chain, pos) -> float:
    if chain.stub:
        return 0.0
    return float(sum(np.abs(pos[b] - pos[a]).sum() for a, b in zip(chain.nodes[:-1], chain.nodes[1:])))


def _assign_lanes(chains: list[Chain], pos, rng: np.random.Generator) -> None:
    for ch in chains:
        n = int(rng.choice([2, 3, 4, 5, 6], p=[0.3, 0.15, 0.3, 0.1, 0.15]))
        if ch.stub:
            n = min(n, 4)
        n_fwd = n // 2 + (int(rng.random() < 0.5) if n % 2 else 0)
        ch.n_right, ch.n_left = n_fwd, n - n_fwd
        ch.lane_width = float(rng.uniform(3.0, 3.7))
        if n >= 4 and not ch.stub and _chain_length(ch, pos) >= 120 and rng.random() < 0.5:
            ch.median = float(rng.uniform(2.0, 4.0))
        ch.divider = str(rng.choice(["double_yellow", "single_yellow", "single_white"], p=[0.55, 0.2, 0.25]))
    if not any(ch.median > 0 for ch in chains):
        longest = max(chains, key=lambda c: _chain_length(c, pos))
        longest.n_right, longest.n_left = max(longest.n_right, 2), max(longest.n_left, 2)
        longest.median = float(rng.uniform(2.0, 4.0))


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


def _junctions(chains, pos, arms, rng) -> dict:
    wl: dict = {}
    wr: dict = {}
    for ch in chains:
        j0, a0 = ch.nodes[0], ch.dirs[0]
        wl[(j0, a0)], wr[(j0, a0)] = ch.w_left, ch.w_right
        if not ch.stub:
            j1, a1 = ch.nodes[-1], (ch.dirs[-1] + 2) % 4
            wl[(j1, a1)], wr[(j1, a1)] = ch.w_right, ch.w_left
    out = {}
    for n in sorted(pos):
        if len(arms[n]) < 3:
            continue
        codes = sorted(arms[n])
        fillet = {a: float(rng.uniform(4.0, 9.0)) for a in codes}  # corner between a and a+1
        crossing = {a: bool(rng.random() < 0.75) for a in codes}
        if not any(crossing.values()):
            crossing[codes[int(rng.integers(len(codes)))]] = True
        overlap = overlapping_corners(codes, crossing, fillet, rng)
        D = {}
        for a in codes:
            ext = 2.0
            if (a + 1) % 4 in arms[n]:
                ext = max(ext, wr[(n, (a + 1) % 4)] + fillet[a])
            if (a - 1) % 4 in arms[n]:
                ext = max(ext, wl[(n, (a - 1) % 4)] + fillet[(a - 1) % 4])
            gap = OVERLAP_GAP_M if a in overlap or (a - 1) % 4 in overlap else 1.0  # kerb corner -> crossing
            D[a] = ext + (gap + 4.0 + 0.8 + STOP_LINE_WIDTH + 0.3 if crossing[a] else 1.0 + STOP_LINE_WIDTH + 0.3)
        out[n] = Junction(node=n, centre=pos[n], arms=codes, D=D, wl={a: wl[(n, a)] for a in codes},
                          wr={a: wr[(n, a)] for a in codes}, crossing=crossing, fillet=fillet, overlap=overlap)
        drop_far_overlaps(out[n])
    return out


def _straight_with_bend(t: Turtle, length: float, half_width: float, rng) -> None:
    """Drive `length` metres straight ahead, sometimes as a gentle S-bend back onto the same line."""
    if length >= 110 and rng.random() < 0.5:
        theta = math.radians(float(rng.uniform(10.0, 22.0)))
        r = float(rng.uniform(half_width + 20.0, 90.0))
        r = min(r, (length - 30.0) / (4 * math.sin(theta)))
        if r >= half_width + 15.0:
            side = 1.0 if rng.random() < 0.5 else -1.0
            lead = (length - 4 * r * math.sin(theta)) / 2
            t.straight(lead).arc(side * theta, r).arc(-2 * side * theta, r).arc(side * theta, r)
            t.straight(length - lead - 4 * r * math.sin(theta))
            return
    t.straight(length)


def _chain_path(ch: Chain, pos, junctions, canvas, rng):
    """Centre path of a chain and its exact end poses ((x, y), code)."""
    j0, a0 = ch.nodes[0], ch.dirs[0]
    start = pos[j0] + junctions[j0].D[a0] * DIRS[a0]
    t = Turtle(float(start[0]), float(start[1]), yaw_of(a0))
    cur = start.copy()
    half = max(ch.w_left, ch.w_right)
    for k in range(1, len(ch.nodes) - 1):
        din, dout = ch.dirs[k - 1], ch.dirs[k]
        if din == dout:
            continue
        rc = float(rng.uniform(half + 8.0, half + 25.0))
        length = float(np.dot(pos[ch.nodes[k]] - cur, DIRS[din])) - rc
        _straight_with_bend(t, length, half, rng)
        t.arc(math.pi / 2 if dout == (din + 1) % 4 else -math.pi / 2, rc)
        cur = pos[ch.nodes[k]] + rc * DIRS[dout]
    dlast = ch.dirs[-1]
    if ch.stub:
        end = cur.copy()
        axis = 0 if dlast in (0, 2) else 1
        end[axis] = canvas[axis] if dlast in (0, 1) else 0.0
        t.straight(float(np.dot(end - cur, DIRS[dlast])))
    else:
        jn = ch.nodes[-1]
        arm = (dlast + 2) % 4
        end = pos[jn] + junctions[jn].D[arm] * DIRS[arm]
        _straight_with_bend(t, float(np.dot(end - cur, DIRS[dlast])), half, rng)
    return t.path(), (start, a0), (end, dlast)


def _stretch(ch: Chain, path: Path, start, end, rng) -> Stretch:
    length = path.length
    r = ch.median / 2
    island = None
    extra = []
    if ch.median > 0:
        s_a = float(rng.uniform(10.0, 20.0))
        s_b = length - float(rng.uniform(10.0, 20.0))
        if s_b - s_a >= 2 * r + 15.0:
            island = (s_a, s_b)
            extra = [s_a, s_a + r, s_b - r, s_b]
    s = np.unique(np.concatenate([path.sample_s(4.0, 0.004), extra]))
    s = s[np.concatenate([[True], np.diff(s) > 1e-6])]
    s[-1] = length
    poses = path.pose_at(s)
    pts = poses[:, :2].copy()
    nrm = np.stack([-np.sin(poses[:, 2]), np.cos(poses[:, 2])], axis=-1)
    pts[0], nrm[0] = start[0], left_of(start[1])
    pts[-1], nrm[-1] = end[0], left_of(end[1])

    rows: list[tuple[float, str]] = [(-ch.w_right, "edge"), (ch.w_left, "edge")]
    rows += [(-(r + k * ch.lane_width), "lane") for k in range(1, ch.n_right)]
    rows += [(r + k * ch.lane_width, "lane") for k in range(1, ch.n_left)]
    rows.append((0.0, "centre"))
    if ch.median > 0:
        rows += [(-r, "median"), (r, "median")]
    rows.sort()
    offsets = np.array([d for d, _ in rows])
    kinds = [k for _, k in rows]
    return Stretch(chain=ch, path=path, s=s, pts=pts, nrm=nrm, rows=offsets, kinds=kinds,
                   ids=np.full((len(rows), len(s)), -1), island=island, start=(ch.nodes[0], ch.dirs[0]),
                   end=None if ch.stub else (ch.nodes[-1], (ch.dirs[-1] + 2) % 4))


def _register_stretch(st: Stretch, rec: MapRecords) -> list[int]:
    """Add the stretch's grid nodes; returns the island ring node ids (empty if none)."""
    n = len(st.s)
    centre = st.kinds.index("centre")
    for j, d in enumerate(st.rows):
        xy = st.pts + d * st.nrm
        keep = np.ones(n, bool)
        if j == centre and st.island is not None:
            s_a, s_b = st.island
            keep = (st.s <= s_a + 1e-9) | (st.s >= s_b - 1e-9)
        st.ids[j, keep] = rec.add_nodes(xy[keep])
    if st.island is None:
        return []
    s_a, s_b = st.island
    r = st.chain.median / 2
    jr, jl = st.kinds.index("median"), len(st.kinds) - 1 - st.kinds[::-1].index("median")
    side = (st.s >= s_a + r - 1e-9) & (st.s <= s_b - r + 1e-9)
    i_a = int(np.argmin(np.abs(st.s - s_a)))
    i_b = int(np.argmin(np.abs(st.s - s_b)))

    def nose(s_c, phis):
        poses = st.path.pose_at(s_c + r * np.cos(phis))
        nrm = np.stack([-np.sin(poses[:, 2]), np.cos(poses[:, 2])], axis=-1)
        return rec.add_nodes(poses[:, :2] + (r * np.sin(phis))[:, None] * nrm)

    m = max(3, int(math.ceil(math.pi * r / 0.5)) // 2)
    half1 = np.linspace(-math.pi / 2, 0.0, m + 1)[1:-1]
    half2 = np.linspace(0.0, math.pi / 2, m + 1)[1:-1]
    ring = list(st.ids[jr, side])
    ring += list(nose(s_b - r, half1)) + [int(st.ids[centre, i_b])] + list(nose(s_b - r, half2))
    ring += list(st.ids[jl, side][::-1])
    ring += list(nose(s_a + r, half1 + math.pi)) + [int(st.ids[centre, i_a])] + list(nose(s_a + r, half2 + math.pi))
    return [int(i) for i in ring]


def _cross_section(st: Stretch, at_start: bool) -> list[int]:
    """Node ids across the stretch end, ordered from the outward-right to the outward-left."""
    col = st.ids[:, 0] if at_start else st.ids[:, -1][::-1]
    return [int(i) for i in col if i >= 0]


def _band_ring(st: Stretch, j0: int, j1: int) -> list[int]:
    """Ring of the band between rows j0 < j1, including the intermediate row nodes at the ends."""
    ring = list(st.ids[j0])
    ring += [int(st.ids[j, -1]) for j in range(j0 + 1, j1) if st.ids[j, -1] >= 0]
    ring += list(st.ids[j1][::-1])
    ring += [int(st.ids[j, 0]) for j in range(j1 - 1, j0, -1) if st.ids[j, 0] >= 0]
    return [int(i) for i in ring]


def _edge_line(rec: MapRecords, st: Stretch, j0: int, j1: int, col: int) -> Ref:
    return rec.add_line([int(st.ids[j0, col]), int(st.ids[j1, col])])


# ---------------------------------------------------------------------------------------------
# Network
# ---------------------------------------------------------------------------------------------


def build_network(location: str, seed: int) -> RoadNetwork:
    """The road network of `location` in the world of `seed` (deterministic)."""
    if location not in LOCATIONS:
        raise ValueError(f"unknown location {location!r}; expected one of {LOCATIONS}")
    for attempt in range(50):
        rng = np.random.default_rng([seed, LOCATIONS.index(location), attempt])
        net = _try_build(location, seed, rng)
        if net is not None:
            return net
    raise RuntimeError(f"could not lay out a valid road network for {location} (seed {seed})")


def _try_build(location: str, seed: int, rng: np.random.Generator) -> RoadNetwork | None:
    """One attempt at a map: layout, stretches, road surface, lanes, markings, sidewalks, props, each
    step drawing from ``rng`` in turn. None when the draw is unusable (no 3- and 4-way junctions, no
    median island, a road surface that is not one valid polygon with its islands as holes)."""
    drive_right = location.startswith("boston")
    pos, arms, stubs, canvas = _layout(rng)
    kinds = [len(a) for a in arms.values()]
    if 3 not in kinds or 4 not in kinds:
        return None
    chains = _chains(pos, arms, stubs)
    _assign_lanes(chains, pos, rng)
    style = _draw_style(rng)
    junctions = _junctions(chains, pos, arms, rng)
    rec = MapRecords(namespace=f"{seed}/{location}")
    stretches = _build_stretches(chains, pos, junctions, canvas, rng)
    if not any(st.island is not None for st in stretches):
        return None
    surface = _add_road_surface(stretches, junctions, rec, rng)
    if surface is None:
        return None
    road, road_filled, islands = surface
    lanes = _add_lanes_and_dividers(stretches, rec, drive_right)
    markings = Markings()
    _add_crossings_and_stop_lines(stretches, junctions, rec, markings, drive_right)
    connectors = _connect_lanes(lanes, junctions, drive_right, rec)
    outer, walkway, ground, kerb = _add_sidewalks_and_ground(road, road_filled, canvas, style, rec, rng)
    for st in stretches:
        paint_stretch(st, style, markings)
    add_patches(stretches, markings, rng)
    net = RoadNetwork(
        location=location, seed=seed, canvas=canvas, drive_right=drive_right, style=style, stretches=stretches,
        junctions=junctions, lanes=lanes, connectors=connectors, records=rec, road=road, road_filled=road_filled,
        islands=islands, walkway=walkway, ground=ground, kerb=kerb, markings=markings, props=[],
    )
    net.props = place_props(net, outer, rng)
    return net


def _draw_style(rng: np.random.Generator) -> MapStyle:
    """The map's paint and sidewalk dimensions."""
    return MapStyle(
        dash=float(rng.choice([2.0, 3.0, 3.0, 4.0])), gap=float(rng.uniform(4.0, 6.5)),
        line_width=float(rng.uniform(0.12, 0.18)), double_gap=float(rng.uniform(0.1, 0.2)),
        sidewalk=float(rng.uniform(2.0, 4.0)), kerb=float(rng.uniform(0.2, 0.3)),
        island_ground=str(rng.choice(["grass", "paved"])),
    )


def _build_stretches(chains, pos, junctions, canvas, rng: np.random.Generator) -> list[Stretch]:
    """One stretch of road per chain: its path between the junctions (or to the canvas edge), rows."""
    stretches: list[Stretch] = []
    for ch in chains:
        path, start, end = _chain_path(ch, pos, junctions, canvas, rng)
        st = _stretch(ch, path, start, end, rng)
        st.tone = float(rng.uniform(-8.0, 8.0))
        stretches.append(st)
    return stretches


def _add_road_surface(stretches: list[Stretch], junctions: dict, rec: MapRecords, rng: np.random.Generator):
    """Road segments (stretches with island holes, junctions with filleted corners) and the drivable
    area; returns ``(road, road_filled, islands)``, or None when the road is not one valid polygon that
    keeps every island as a hole."""
    drivable = Ref("drivable_area", 0)
    arm_ids: dict = {}
    for st in stretches:
        island_ring = _register_stretch(st, rec)
        ring = _band_ring(st, 0, len(st.rows) - 1)
        holes = [island_ring] if island_ring else []
        poly = rec.add_polygon(ring, holes, "road_segment")
        st.shape = rec.shape_of(poly.index)
        st.segment = rec.add("road_segment", polygon_token=poly, is_intersection=False, drivable_area_token=drivable)
        arm_ids[st.start] = _cross_section(st, True)
        if st.end is not None:
            arm_ids[st.end] = _cross_section(st, False)

    for jn in junctions.values():
        ring: list[int] = []
        codes = jn.arms
        for idx, a in enumerate(codes):
            ring += arm_ids[(jn.node, a)]
            b = codes[(idx + 1) % len(codes)]
            if (b - a) % 4 == 1:
                r = jn.fillet[a]
                q = jn.centre + jn.wr[b] * DIRS[a] + jn.wl[a] * DIRS[b]
                o = q + r * DIRS[a] + r * DIRS[b]
                phi0 = math.atan2(-DIRS[b][1], -DIRS[b][0])
                m = max(4, int(math.ceil(r * math.pi / 2 / math.sqrt(8 * r * 0.004))))
                phis = phi0 - np.linspace(0.0, math.pi / 2, m + 1)
                ring += list(rec.add_nodes(o + r * np.stack([np.cos(phis), np.sin(phis)], axis=-1)))
        poly = rec.add_polygon(ring, (), "junction road_segment")
        jn.shape = rec.shape_of(poly.index)
        jn.segment = rec.add("road_segment", polygon_token=poly, is_intersection=True, drivable_area_token=drivable)
        jn.tone = float(rng.uniform(-8.0, 8.0))

    pieces = [st.shape for st in stretches] + [jn.shape for jn in junctions.values()]
    road = unary_union(pieces)
    road_filled = unary_union([Polygon(st.shape.exterior) for st in stretches]
                              + [jn.shape for jn in junctions.values()])
    if not road.is_valid or not isinstance(road, Polygon):
        return None
    islands = [Polygon(st.shape.interiors[0]) for st in stretches if st.island is not None]
    if len(road.interiors) < len(islands):
        return None
    rec.add("drivable_area", polygon_tokens=[rec.add_shapely(p, "drivable_area") for p in as_polygons(road)])
    return road, road_filled, islands


def _add_lanes_and_dividers(stretches: list[Stretch], rec: MapRecords, drive_right: bool) -> list[Lane]:
    """Road blocks (one per travel direction), lanes with their divider segments, lane and road
    dividers of every stretch; returns the lanes."""
    lanes: list[Lane] = []
    for si, st in enumerate(stretches):
        ch = st.chain
        centre = st.kinds.index("centre")
        inner_r = st.kinds.index("median") if ch.median > 0 else centre
        inner_l = (len(st.kinds) - 1 - st.kinds[::-1].index("median")) if ch.median > 0 else centre
        last = len(st.rows) - 1
        # road blocks: one per travel direction (right side, left side)
        for j0, j1, right_side in ((0, inner_r, True), (inner_l, last, False)):
            poly = rec.add_polygon(_band_ring(st, j0, j1), (), "road_block")
            col_from, col_to = (0, -1) if right_side == drive_right else (-1, 0)
            rec.add("road_block", polygon_token=poly, from_edge_line_token=_edge_line(rec, st, j0, j1, col_from),
                    to_edge_line_token=_edge_line(rec, st, j0, j1, col_to), road_segment_token=st.segment)
        lane_bands = [(j, j + 1, True) for j in range(0, inner_r)] + [(j, j + 1, False) for j in range(inner_l, last)]
        for j0, j1, right_side in lane_bands:
            forward = right_side == drive_right
            d_c = (st.rows[j0] + st.rows[j1]) / 2
            path = st.path.offset(d_c)
            kerb_rank = j0 if right_side else last - j1
            lane = Lane(index=len(lanes), stretch=si, lo=j0, hi=j1, forward=forward,
                        path=path if forward else path.reversed(), kerb_rank=kerb_rank,
                        start=st.start if forward else st.end, end=st.end if forward else st.start,
                        width=float(st.rows[j1] - st.rows[j0]))
            poly = rec.add_polygon(list(st.ids[j0]) + list(st.ids[j1][::-1]), (), "lane")
            col_from, col_to = (0, -1) if forward else (-1, 0)
            # left / right boundary of the lane in its direction of travel
            left_row, right_row = (j1, j0) if forward else (j0, j1)
            order = slice(None) if forward else slice(None, None, -1)
            lane.ref = rec.add(
                "lane", polygon_token=poly, lane_type="CAR",
                from_edge_line_token=_edge_line(rec, st, j0, j1, col_from),
                to_edge_line_token=_edge_line(rec, st, j0, j1, col_to),
                left_lane_divider_segments=_segments(st.ids[left_row][order], _segment_type(st, left_row)),
                right_lane_divider_segments=_segments(st.ids[right_row][order], _segment_type(st, right_row)),
            )
            rec.arclines[lane.ref] = lane.path.arclines()
            lanes.append(lane)
        for j, kind in enumerate(st.kinds):
            if kind == "lane":
                rec.add("lane_divider", line_token=rec.add_line(st.ids[j]),
                        lane_divider_segments=_segments(st.ids[j], "SINGLE_DASHED_WHITE"))
        for part in _runs(st.ids[centre]):
            rec.add("road_divider", line_token=rec.add_line(part), road_segment_token=st.segment)
    return lanes


def _add_crossings_and_stop_lines(stretches: list[Stretch], junctions: dict, rec: MapRecords, markings: Markings,
                                  drive_right: bool) -> None:
    """Each junction arm's zebra crossing (where it has one) and stop line, as records and paint."""
    chain_of_arm = {arm: st.chain for st in stretches for arm in (st.start, st.end) if arm is not None}
    for jn in junctions.values():
        for a in jn.arms:
            ch = chain_of_arm[(jn.node, a)]
            u, n = DIRS[a], left_of(a)
            wl, wr = jn.wl[a], jn.wr[a]
            t_stop = jn.D[a] - 0.3 - STOP_LINE_WIDTH
            crossing_ref = None
            if jn.crossing[a]:
                t0, t1 = crossing_band(jn, a)
                xy = np.array([jn.centre + t * u + lat * n for t, lat in crossing_corners(jn, a)])
                poly = rec.add_polygon(rec.add_nodes(xy), (), "ped_crossing")
                crossing_ref = rec.add("ped_crossing", polygon_token=poly, road_segment_token=jn.segment)
                markings.white.extend(zebra(jn.centre, u, n, t0, t1, -wr, wl))
            # incoming traffic drives towards the junction (-u): its lanes are on the outward-left
            # side when driving on the right, on the outward-right side when driving on the left
            half_m = ch.median / 2
            lat0, lat1 = (half_m, wl) if drive_right else (-wr, -half_m)
            corners = [(t_stop, lat0), (t_stop + STOP_LINE_WIDTH, lat0), (t_stop + STOP_LINE_WIDTH, lat1),
                       (t_stop, lat1)]
            xy = np.array([jn.centre + t * u + lat * n for t, lat in corners])
            poly = rec.add_polygon(rec.add_nodes(xy), (), "stop_line")
            markings.white.append(xy)
            rec.add("stop_line", polygon_token=poly,
                    stop_line_type="PED_CROSSING" if crossing_ref is not None else "STOP_SIGN",
                    ped_crossing_tokens=[crossing_ref] if crossing_ref is not None else [],
                    traffic_light_tokens=[], road_block_token="")


def _add_sidewalks_and_ground(road, road_filled, canvas, style: MapStyle, rec: MapRecords,
                              rng: np.random.Generator):
    """Walkway records (the sidewalk band, in 50 m tiles), the ground outside it and the kerb; returns
    ``(outer, walkway, ground, kerb)`` (outer: the road with its sidewalks)."""
    canvas_box = box(0.0, 0.0, canvas[0], canvas[1])
    outer = road_filled.buffer(style.sidewalk, quad_segs=4)
    walkway = unary_union(as_polygons(outer.difference(road_filled).intersection(canvas_box)))
    cell = 50.0
    for cx in np.arange(0.0, canvas[0], cell):
        for cy in np.arange(0.0, canvas[1], cell):
            for piece in as_polygons(walkway.intersection(box(cx, cy, cx + cell, cy + cell))):
                if piece.area > 0.5:
                    rec.add("walkway", polygon_token=rec.add_shapely(piece, "walkway"))
    ground = [(piece, str(rng.choice(["grass", "grass", "dirt", "paved"])))
              for piece in as_polygons(canvas_box.difference(outer))]
    kerb = road.boundary.buffer(style.kerb / 2, quad_segs=2)
    return outer, walkway, ground, kerb


def _segment_type(st: Stretch, j: int) -> str:
    """nuScenes segment_type of the painted line along row j of a stretch."""
    kind = st.kinds[j]
    return {"edge": "NIL", "lane": "SINGLE_DASHED_WHITE"}.get(kind) or SEGMENT_TYPE[st.chain.divider]


def _segments(ids, segment_type: str) -> list[dict]:
    return [{"node_token": Ref("node", int(i)), "segment_type": segment_type} for i in ids]


def _runs(row: np.ndarray) -> list[list[int]]:
    """Maximal runs of present ids (>= 0) of length >= 2."""
    runs = [[int(i) for i in run] for present, run in groupby(row, key=lambda i: i >= 0) if present]
    return [run for run in runs if len(run) >= 2]


def _connect_lanes(lanes: list[Lane], junctions, drive_right: bool, rec: MapRecords) -> list[Connector]:
    incoming: dict = {}
    outgoing: dict = {}
    for lane in lanes:
        if lane.end is not None:
            incoming.setdefault(lane.end, []).append(lane)
        if lane.start is not None:
            outgoing.setdefault(lane.start, []).append(lane)
    near = "right" if drive_right else "left"
    connectors: list[Connector] = []
    for jn in junctions.values():
        for a in jn.arms:
            ins = sorted(incoming.get((jn.node, a), []), key=lambda ln: ln.kerb_rank)
            for b in jn.arms:
                outs = sorted(outgoing.get((jn.node, b), []), key=lambda ln: ln.kerb_rank)
                if b == a or not ins or not outs or connect(ins[0].path.end_pose(), outs[0].path.start_pose()) is None:
                    continue
                dyaw = principal_angle(outs[0].path.start_pose()[2] - ins[0].path.end_pose()[2])
                turn = "straight" if abs(dyaw) < 0.1 else ("left" if dyaw > 0 else "right")
                if turn == "straight":
                    pairs = [(i, min(i, len(outs) - 1)) for i in range(len(ins))]
                elif turn == near:
                    pairs = [(0, 0)]
                else:
                    pairs = [(len(ins) - 1, len(outs) - 1)]
                for i, o in pairs:
                    path = connect(ins[i].path.end_pose(), outs[o].path.start_pose())
                    if path is None:
                        continue
                    con = Connector(index=len(connectors), path=path, src=ins[i].index, dst=outs[o].index, turn=turn)
                    xy = path.pose_at(path.sample_s(1.0, 0.01))[:, :2]
                    shape = LineString(xy).buffer(ins[i].width / 2, cap_style="flat", quad_segs=4)
                    con.ref = rec.add("lane_connector", polygon_token=rec.add_shapely(shape, "lane_connector"))
                    rec.arclines[con.ref] = path.arclines()
                    connectors.append(con)
    for lane in lanes:
        rec.connectivity[lane.ref] = {"incoming": [], "outgoing": []}
    for con in connectors:
        src, dst = lanes[con.src].ref, lanes[con.dst].ref
        rec.connectivity[con.ref] = {"incoming": [src], "outgoing": [dst]}
        rec.connectivity[src]["outgoing"].append(con.ref)
        rec.connectivity[dst]["incoming"].append(con.ref)
    return connectors


def map_token(location: str, seed: int) -> str:
    """Token of the v1.0 map table record (and name of its semantic prior PNG) of `location`."""
    return make_token(seed, location, "map")
