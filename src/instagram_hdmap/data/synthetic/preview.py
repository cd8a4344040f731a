"""``write_preview``: the six camera images of one sample with the map's lines projected onto them,
and the map around the ego vehicle from above -- a visual check of a dataroot.

Everything is read back through the official devkit (``NuScenes``, ``NuScenesMap``), exactly as a
dataset loader would, so the picture checks the files, not the generator's memory. Works on any
nuScenes dataroot (real or synthetic).
"""

from __future__ import annotations

from itertools import groupby
from operator import itemgetter
from pathlib import Path as FsPath

import numpy as np
import shapely
from pyquaternion import Quaternion
from shapely import segmentize
from shapely.geometry import LineString, MultiPolygon, Polygon
from shapely.ops import unary_union

from ...config import UserError
from ...files import atomic_path
from ..nuscenes import open_nuscenes
from ..rig import CAMERAS
from .jobs import MANIFEST
from .world import read_manifest

STYLE = {  # map element: (colour, line width)
    "road_divider": ("#ffa500", 1.6),
    "lane_divider": ("#00e5ff", 1.2),
    "ped_crossing": ("#ff00ff", 1.2),
    "boundary": ("#ff2020", 1.6),
}
RADIUS_M = 60.0


def _version_of(dataroot: FsPath) -> str:
    if (dataroot / MANIFEST).is_file():
        manifest = read_manifest(dataroot)
        if not isinstance(manifest, dict):
            raise UserError(f"{dataroot / MANIFEST}: not a world manifest (a JSON {type(manifest).__name__}); is "
                            f"{dataroot} a world written by 'instagram-hdmap synth'?")
        if manifest.get("dataset") == "av2":
            raise UserError(f"{dataroot} is a synthetic world in the Argoverse 2 layout; synth-preview draws the "
                            "nuScenes layout: look at an AV2 sample with instagram-hdmap show-gt CONFIG "
                            f"data.dataset=av2 data.dataroot={dataroot}")
        if isinstance(manifest.get("version"), str):
            return manifest["version"]
    for v in ("v1.0-trainval", "v1.0-mini"):
        if (dataroot / v).is_dir():
            return v
    raise UserError(f"{dataroot}: no world.json and no v1.0-trainval / v1.0-mini folder; is it a nuScenes dataroot?")


def _lines(geoms) -> list[np.ndarray]:
    """Polylines [P, 2] of lines, and of polygons' rings (a collection: its lines only)."""
    out = []
    for g in geoms:
        parts = shapely.get_parts(g.boundary if isinstance(g, (Polygon, MultiPolygon)) else g)
        out += [np.asarray(p.coords)[:, :2] for p in parts
                if isinstance(p, LineString) and not p.is_empty and len(p.coords) >= 2]
    return out


def map_elements_ego(nusc_map, pose_xy: np.ndarray, yaw: float, radius: float = RADIUS_M) -> dict[str, list]:
    """Map lines around an ego pose in the ego frame (x forward, y left), by element, as polylines [P, 2]."""
    ex = nusc_map.explorer
    patch = (float(pose_xy[0]), float(pose_xy[1]), 2 * radius, 2 * radius)
    angle = float(np.degrees(yaw))
    out = {name: _lines(ex._get_layer_line(patch, angle, name)) for name in ("road_divider", "lane_divider")}
    out["ped_crossing"] = _lines(ex._get_layer_polygon(patch, angle, "ped_crossing"))
    road = unary_union(ex._get_layer_polygon(patch, angle, "road_segment")
                       + ex._get_layer_polygon(patch, angle, "lane"))
    out["boundary"] = _lines([road])
    return out


def _project(cam_rot: np.ndarray, cam_trans: np.ndarray, k: np.ndarray, line: np.ndarray) -> list[np.ndarray]:
    """Ego-frame ground polyline [P, 2] -> image polylines (pieces in front of the camera)."""
    dense = np.asarray(segmentize(LineString(line), 0.5).coords)[:, :2]
    p = np.concatenate([dense, np.zeros((len(dense), 1))], axis=1)
    pc = (p - cam_trans) @ cam_rot  # = R^T (p - t)
    runs = [np.array([q for _, q in run]) for front, run in groupby(zip(pc[:, 2] > 0.5, pc), key=itemgetter(0))
            if front]
    return [(q[:, :2] / q[:, 2:3]) @ k[:2, :2].T + k[:2, 2] for q in runs if len(q) >= 2]


def write_preview(dataroot, out_png, index: int = 0) -> None:
    """Draw sample `index` of `dataroot`: 6 cameras with projected map lines, and the BEV map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.image import imread
    from nuscenes.map_expansion.map_api import NuScenesMap

    dataroot = FsPath(dataroot)
    if not dataroot.is_dir():
        raise UserError(f"{dataroot}: no such folder")
    nusc = open_nuscenes(dataroot, _version_of(dataroot))
    if not -len(nusc.sample) <= index < len(nusc.sample):  # negative counts from the end, as show-gt / predict
        raise UserError(f"--index {index}: {dataroot} has {len(nusc.sample)} samples (0..{len(nusc.sample) - 1}, or "
                        f"-{len(nusc.sample)}..-1 from the end)")
    index %= len(nusc.sample)  # the title names the sample by its place
    sample = nusc.sample[index]
    scene = nusc.get("scene", sample["scene_token"])
    location = nusc.get("log", scene["log_token"])["location"]
    nusc_map = NuScenesMap(dataroot=str(dataroot), map_name=location)
    ref = nusc.get("sample_data", sample["data"]["CAM_FRONT"])
    ego = nusc.get("ego_pose", ref["ego_pose_token"])
    yaw = Quaternion(ego["rotation"]).yaw_pitch_roll[0]
    elements = map_elements_ego(nusc_map, np.asarray(ego["translation"][:2]), yaw)

    fig = plt.figure(figsize=(26, 8.2))
    grid = fig.add_gridspec(2, 4, width_ratios=[1, 1, 1, 1.15], wspace=0.03, hspace=0.08)
    for i, ch in enumerate(CAMERAS):
        ax = fig.add_subplot(grid[i // 3, i % 3])
        sd = nusc.get("sample_data", sample["data"][ch])
        cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        img = imread(nusc.get_sample_data_path(sd["token"]))
        ax.imshow(img)
        rot, trans, k = Quaternion(cs["rotation"]).rotation_matrix, np.asarray(cs["translation"]), np.asarray(
            cs["camera_intrinsic"])
        for name, lines in elements.items():
            color, lw = STYLE[name]
            for line in lines:
                for uv in _project(rot, trans, k, line):
                    ax.plot(uv[:, 0], uv[:, 1], "-", color=color, lw=lw, alpha=0.85)
        ax.set_xlim(0, img.shape[1])
        ax.set_ylim(img.shape[0], 0)
        ax.set_title(ch, fontsize=9)
        ax.axis("off")

    ax = fig.add_subplot(grid[:, 3])
    for name, lines in elements.items():
        color, lw = STYLE[name]
        for j, line in enumerate(lines):
            ax.plot(line[:, 0], line[:, 1], "-", color=color, lw=lw, label=name if j == 0 else None)
    _, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
    cs = nusc.get("calibrated_sensor", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["calibrated_sensor_token"])
    for b in boxes:  # lidar frame -> ego frame
        b.rotate(Quaternion(cs["rotation"]))
        b.translate(np.asarray(cs["translation"]))
        c = b.bottom_corners()[:2].T
        ax.fill(c[:, 0], c[:, 1], color="#777777", alpha=0.6)
    ax.fill([-1.0, 3.9, 3.9, -1.0], [-0.95, -0.95, 0.95, 0.95], color="#2060ff")
    ax.plot([-30, 30, 30, -30, -30], [-15, -15, 15, 15, -15], "k--", lw=0.8, label="60 m x 30 m")
    ax.set_xlim(-40, 40)
    ax.set_ylim(-30, 30)
    ax.set_aspect("equal")
    ax.set_facecolor("#f4f4f4")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{scene['name']} ({location}), sample {index}: map in the ego frame", fontsize=9)
    with atomic_path(out_png, keep_suffix=True) as tmp:  # a full disk leaves no half-written PNG
        fig.savefig(tmp, dpi=80, bbox_inches="tight")
    plt.close(fig)
