"""Ground-truth statistics of the ped-crossing conventions (data.ped_crossing: edges, union, each; and
the exterior-only union this project used earlier), on the real AV2 log of ../shared/av2_real
and on the synthetic world's road networks.

Per convention and per setting (the paper's grid, 60 m x 30 m at 0.15 m, S = 8, sample_dist 1.5; the
demo's, 30 m x 15 m at 0.25 m, S = 4, sample_dist 0.5), averaged over the poses:

* crossings: crossing instances (polylines) per sample;
* vertices: GT graph vertices of the crossing class per sample (targets.vertex_graph), and of all classes;
* own outline: the fraction of each crossing's own outline inside the patch that lies within 0.3 m of
  the GT crossing polylines (pooled over crossings and poses);
* union outline: the same for the outline (every ring) of the crossings' union;
* two edges: the same for each crossing's two edges (its two longest; AV2: edge1, edge2), what ``edges``
  represents.

Poses: the real log's pose table, every ``--real-step``-th (2706 poses over 16 s); the synthetic world's
drives (world.py's scene i: ``plan_drive`` seeded by (seed, 1000 + i)) over its four road networks,
``--scenes`` scenes of ``--samples`` samples for each of ``--seeds`` (0: the demo's training world,
1: its unseen validation world). Only the map files are written (no images).

    python benchmarks/crossing_conventions.py [--real-step 10] [--seeds 0 1] [--scenes 8] [--samples 20]
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LinearRing, LineString, box

from instagram_hdmap.data.local_map import PED_CROSSING, LocalMapBuilder
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.targets import vertex_graph

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "av2_real" / "val"
SETTINGS = {"paper": (BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8), 1.5),
            "demo": (BEVGrid(-15.0, 15.0, -7.5, 7.5, 0.25, 4), 0.5)}
CONVENTIONS = ("edges", "union", "each", "exterior-only")
TOL_M = 0.3


def _points(lines, step: float = 0.1) -> np.ndarray:
    pts = [shapely.get_coordinates(shapely.line_interpolate_point(ln, np.arange(0.0, ln.length, step)))
           for ln in lines if ln.length > 0]
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def _near(points: np.ndarray, polylines: list[dict]) -> np.ndarray:
    if not polylines:
        return np.zeros(len(points), bool)
    got = shapely.union_all([LineString(p["pts"]) for p in polylines])
    return shapely.distance(shapely.points(points), got) < TOL_M


def sample_stats(builders: dict, grid: BEVGrid, location: str, x: float, y: float, yaw: float) -> dict:
    """One pose: per convention (crossings, crossing vertices, all vertices, own-outline hits [P] bool,
    union-outline hits [Q] bool, two-edge hits [R] bool)."""
    lmap = builders["each"].location_map(location)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    clip = box(grid.xmin + 0.01, grid.ymin + 0.01, grid.xmax - 0.01, grid.ymax - 0.01)
    local = [shapely.transform(p, lambda q: (q - [x, y]) @ rot) for p in lmap.peds]
    local = [p for p in local if p.intersects(clip)]
    own = _points([g for p in local for g in shapely.get_parts(LineString(p.exterior.coords).intersection(clip))])
    union = shapely.union_all(local) if local else shapely.Polygon()
    rings = [LineString(r.coords) for part in shapely.get_parts(union) for r in (part.exterior, *part.interiors)]
    union_pts = _points([g for r in rings for g in shapely.get_parts(r.intersection(clip))])
    edges = [shapely.transform(e, lambda q: (q - [x, y]) @ rot) for e in lmap.ped_edges]
    edge_pts = _points([g for e in edges for g in shapely.get_parts(e.intersection(clip))])
    out = {}
    for name in CONVENTIONS:
        polys = builders["union" if name == "exterior-only" else name](location, x, y, yaw)
        if name == "exterior-only":  # the union's exterior rings only (clockwise): the earlier code
            polys = [p for p in polys if p["label"] != PED_CROSSING or not LinearRing(p["pts"]).is_ccw]
        peds = [p for p in polys if p["label"] == PED_CROSSING]
        labels = vertex_graph(polys, grid)["gt_vertex_labels"].numpy()
        out[name] = (len(peds), int((labels == PED_CROSSING).sum()), len(labels), _near(own, peds),
                     _near(union_pts, peds), _near(edge_pts, peds))
    return out


def table(title: str, rows: list[dict]) -> None:
    print(f"\n{title} ({len(rows)} poses)")
    print(f"| convention | crossings / sample | crossing vertices / sample | all vertices / sample | within {TOL_M} m: "
          "own outline | union outline | two edges |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in CONVENTIONS:
        per = [r[name] for r in rows]
        own = np.concatenate([p[3] for p in per])
        uni = np.concatenate([p[4] for p in per])
        edg = np.concatenate([p[5] for p in per])
        print(f"| {name} | {np.mean([p[0] for p in per]):.2f} | {np.mean([p[1] for p in per]):.1f} | "
              f"{np.mean([p[2] for p in per]):.1f} | {own.mean():.3f} | {uni.mean():.3f} | {edg.mean():.3f} |")


def real_rows(setting: str, step: int) -> list[dict]:
    from av2.utils.io import read_city_SE3_ego

    from instagram_hdmap.data.av2 import AV2LocalMapBuilder

    grid, sample_dist = SETTINGS[setting]
    rows = []
    for log_dir in sorted(p for p in REAL.iterdir() if p.is_dir()):
        builders = {c: AV2LocalMapBuilder(REAL, grid, sample_dist, c) for c in ("edges", "union", "each")}
        table_ = read_city_SE3_ego(log_dir)
        for t in sorted(table_)[::step]:
            pose = table_[t]
            yaw = math.atan2(pose.rotation[1, 0], pose.rotation[0, 0])
            rows.append(sample_stats(builders, grid, log_dir.name, *map(float, pose.translation[:2]), yaw))
    return rows


def synthetic_rows(setting: str, seeds, scenes: int, samples: int, root: Path) -> list[dict]:
    from instagram_hdmap.data.synthetic.map_writer import write_map_json
    from instagram_hdmap.data.synthetic.roads import LOCATIONS, build_network
    from instagram_hdmap.data.synthetic.traffic import plan_drive

    grid, sample_dist = SETTINGS[setting]
    rows = []
    for seed in seeds:
        folder = root / f"seed{seed}"
        nets = {loc: build_network(loc, seed) for loc in LOCATIONS}
        for loc, net in nets.items():
            path = folder / "maps" / "expansion" / f"{loc}.json"
            if not path.is_file():
                write_map_json(net.records, net.canvas, path)
        builders = {c: LocalMapBuilder(folder, grid, sample_dist, c) for c in ("edges", "union", "each")}
        for i in range(scenes):
            loc = LOCATIONS[i % len(LOCATIONS)]
            drive = plan_drive(nets[loc], samples, np.random.default_rng([seed, 1000 + i]))
            for x, y, yaw in drive.poses():
                rows.append(sample_stats(builders, grid, loc, float(x), float(y), float(yaw)))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real-step", type=int, default=10, help="every N-th pose of the real log's pose table")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="synthetic worlds (0: demo train, 1: unseen)")
    ap.add_argument("--scenes", type=int, default=8, help="synthetic drives per seed (over the four road networks)")
    ap.add_argument("--samples", type=int, default=20, help="samples per synthetic drive (0.5 s apart)")
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, real_step=1, seeds=0, scenes=1, samples=1)
    for setting in SETTINGS:
        if REAL.is_dir():
            table(f"Real AV2 log ({REAL}), {setting} setting, every {args.real_step}-th pose",
                  real_rows(setting, args.real_step))
        else:
            print(f"\n(no real log at {REAL}: skipped)")
        with tempfile.TemporaryDirectory() as tmp:
            title = (f"Synthetic world, seeds {args.seeds}, {args.scenes} drives x {args.samples} samples, "
                     f"{setting} setting")
            table(title, synthetic_rows(setting, args.seeds, args.scenes, args.samples, Path(tmp)))


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
