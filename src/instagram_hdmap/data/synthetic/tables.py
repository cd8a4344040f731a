"""The 13 nuScenes v1.0 tables, in the official schema.

``attribute, calibrated_sensor, category, ego_pose, instance, log, map, sample,
sample_annotation, sample_data, scene, sensor, visibility`` -- with 32-hex tokens, prev/next
links, microsecond timestamps and (as in nuScenes) ``ego_pose.token == sample_data.token``.
Only key frames are written (2 Hz; no sweeps, no radar).
"""

from __future__ import annotations

import json
from pathlib import Path as FsPath

import numpy as np
from pyquaternion import Quaternion

from ..rig import CAMERAS, Sensor
from .map_writer import make_token

TABLE_NAMES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
               "sample_annotation", "sample_data", "scene", "sensor", "visibility")

CATEGORIES = (
    ("human.pedestrian.adult", "Adult subcategory."),
    ("human.pedestrian.child", "Child subcategory."),
    ("human.pedestrian.wheelchair", "Wheelchairs."),
    ("human.pedestrian.stroller", "Strollers."),
    ("human.pedestrian.personal_mobility", "A small electric or self-propelled vehicle."),
    ("human.pedestrian.police_officer", "Police officer."),
    ("human.pedestrian.construction_worker", "Construction worker."),
    ("animal", "All animals."),
    ("vehicle.car", "Vehicle designed primarily for personal use."),
    ("vehicle.motorcycle", "Gasoline or electric powered 2-wheeled vehicle."),
    ("vehicle.bicycle", "Human or electric powered 2-wheeled vehicle."),
    ("vehicle.bus.bendy", "Bendy bus subcategory."),
    ("vehicle.bus.rigid", "Rigid bus subcategory."),
    ("vehicle.truck", "Vehicles primarily designed to haul cargo."),
    ("vehicle.construction", "Vehicles primarily designed for construction."),
    ("vehicle.emergency.ambulance", "All types of ambulances."),
    ("vehicle.emergency.police", "All types of police vehicles."),
    ("vehicle.trailer", "Any vehicle trailer."),
    ("movable_object.barrier", "Temporary road barrier placed in the scene."),
    ("movable_object.trafficcone", "All types of traffic cone."),
    ("movable_object.pushable_pullable", "Objects that a pedestrian may push or pull."),
    ("movable_object.debris", "Movable object that is left on the driveable surface."),
    ("static_object.bicycle_rack", "Area or device intended to park or secure the bicycles."),
)
ATTRIBUTES = (
    ("vehicle.moving", "Vehicle is moving."),
    ("vehicle.stopped", "Vehicle, with a driver/rider in/on it, is currently stationary but has an intent to move."),
    ("vehicle.parked", "Vehicle is stationary (usually for longer duration) with no immediate intent to move."),
    ("cycle.with_rider", "There is someone riding the bicycle or motorcycle."),
    ("cycle.without_rider", "There is NO rider on the bicycle or motorcycle."),
    ("pedestrian.sitting_lying_down", "The human is sitting or lying down."),
    ("pedestrian.standing", "The human is standing."),
    ("pedestrian.moving", "The human is moving."),
)
VISIBILITY = (
    ("1", "v0-40", "visibility of whole object is between 0 and 40%"),
    ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
    ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
    ("4", "v80-100", "visibility of whole object is between 80 and 100%"),
)


def yaw_quaternion(yaw: float) -> list[float]:
    """[w, x, y, z] of a rotation about +z."""
    return [float(v) for v in Quaternion(axis=[0.0, 0.0, 1.0], angle=float(yaw)).elements]


def sample_filename(logfile: str, channel: str, timestamp: int) -> str:
    """Path of one key frame's file, relative to the dataroot (as in nuScenes)."""
    ext = "jpg" if channel in CAMERAS else "pcd.bin"
    return f"samples/{channel}/{logfile}__{channel}__{timestamp}.{ext}"


def visibility_level(num_lidar_pts: int) -> str:
    """Visibility token from the number of lidar points on the box (a proxy for how much is seen)."""
    return "4" if num_lidar_pts >= 20 else "3" if num_lidar_pts >= 8 else "2" if num_lidar_pts >= 2 else "1"


class Tables:
    """Accumulates the records of every table; :meth:`write` dumps ``<dataroot>/<version>/*.json``."""

    def __init__(self, seed: int, sensors: dict[str, Sensor]):
        self.seed = seed
        self.t: dict[str, list[dict]] = {name: [] for name in TABLE_NAMES}
        self.category = {n: self.tok("category", n) for n, _ in CATEGORIES}
        self.attribute = {n: self.tok("attribute", n) for n, _ in ATTRIBUTES}
        self.sensor = {ch: self.tok("sensor", ch) for ch in sensors}
        self.t["category"] = [{"token": self.category[n], "name": n, "description": d} for n, d in CATEGORIES]
        self.t["attribute"] = [{"token": self.attribute[n], "name": n, "description": d} for n, d in ATTRIBUTES]
        self.t["visibility"] = [{"token": t, "level": lv, "description": d} for t, lv, d in VISIBILITY]
        self.t["sensor"] = [{"token": self.sensor[ch], "channel": ch, "modality": s.modality}
                            for ch, s in sensors.items()]
        self.sensors = sensors

    def tok(self, *parts) -> str:
        return make_token(self.seed, *parts)

    def add_map(self, token: str, location_logs: list[str], filename: str) -> None:
        self.t["map"].append({"token": token, "log_tokens": location_logs, "category": "semantic_prior",
                              "filename": filename})

    def write(self, root: FsPath) -> None:
        root.mkdir(parents=True, exist_ok=True)
        for name in TABLE_NAMES:
            with open(root / f"{name}.json", "w") as f:
                json.dump(self.t[name], f, indent=0)


class SceneRecorder:
    """Records of one scene: its log, calibrated sensors, samples, sample_data, ego poses and
    annotations; :meth:`finish` links prev/next and fills the scene and instance records."""

    def __init__(self, tables: Tables, index: int, name: str, description: str, location: str, logfile: str,
                 date: str):
        self.tables, self.index = tables, index
        tok = tables.tok
        self.log = tok("log", index)
        vehicle = logfile.split("-")[0]
        tables.t["log"].append({"token": self.log, "logfile": logfile, "vehicle": vehicle, "date_captured": date,
                                "location": location})
        self.logfile = logfile
        self.calib = {}
        for ch, s in tables.sensors.items():
            self.calib[ch] = tok("calibrated_sensor", index, ch)
            tables.t["calibrated_sensor"].append({
                "token": self.calib[ch], "sensor_token": tables.sensor[ch],
                "translation": [float(v) for v in s.translation], "rotation": [float(v) for v in s.rotation],
                "camera_intrinsic": s.intrinsic.tolist() if s.intrinsic is not None else [],
            })
        self.scene = tok("scene", index)
        self.name, self.description = name, description
        self.samples: list[dict] = []
        self.sample_data: dict[str, list[dict]] = {ch: [] for ch in tables.sensors}
        self.annotations: dict[int, list[dict]] = {}  # instance id -> annotations in time order
        self.categories: dict[int, str] = {}

    def add_sample(self, timestamp: int, pose: np.ndarray, image_size: tuple[int, int]) -> str:
        """A key frame at ego pose (x, y, yaw): the sample, one sample_data and ego_pose per channel."""
        t = self.tables
        k = len(self.samples)
        token = t.tok("sample", self.index, k)
        self.samples.append({"token": token, "timestamp": timestamp, "prev": "", "next": "", "scene_token": self.scene})
        for ch in t.sensors:
            sd = t.tok("sample_data", self.index, k, ch)
            t.t["ego_pose"].append({"token": sd, "timestamp": timestamp, "rotation": yaw_quaternion(pose[2]),
                                    "translation": [float(pose[0]), float(pose[1]), 0.0]})
            is_cam = ch in CAMERAS
            self.sample_data[ch].append({
                "token": sd, "sample_token": token, "ego_pose_token": sd, "calibrated_sensor_token": self.calib[ch],
                "timestamp": timestamp, "fileformat": "jpg" if is_cam else "pcd", "is_key_frame": True,
                "height": image_size[1] if is_cam else 0, "width": image_size[0] if is_cam else 0,
                "filename": sample_filename(self.logfile, ch, timestamp), "prev": "", "next": "",
            })
        return token

    def add_annotation(self, sample_token: str, instance: int, category: str, centre: np.ndarray, yaw: float,
                       size: tuple[float, float, float], attribute: str, num_lidar_pts: int) -> None:
        self.categories[instance] = category
        anns = self.annotations.setdefault(instance, [])
        anns.append({
            "token": self.tables.tok("sample_annotation", self.index, instance, len(anns)),
            "sample_token": sample_token, "instance_token": self.tables.tok("instance", self.index, instance),
            "visibility_token": visibility_level(num_lidar_pts),
            "attribute_tokens": [self.tables.attribute[attribute]],
            "translation": [float(v) for v in centre], "size": [float(v) for v in size],
            "rotation": yaw_quaternion(yaw), "prev": "", "next": "",
            "num_lidar_pts": int(num_lidar_pts), "num_radar_pts": 0,
        })

    def finish(self) -> None:
        t = self.tables
        _link(self.samples)
        for ch in t.sensors:
            _link(self.sample_data[ch])
        t.t["sample"] += self.samples
        for k in range(len(self.samples)):  # sample_data in time order, channels together
            for ch in t.sensors:
                t.t["sample_data"].append(self.sample_data[ch][k])
        for inst in sorted(self.annotations):
            anns = self.annotations[inst]
            _link(anns)
            t.t["instance"].append({
                "token": t.tok("instance", self.index, inst), "category_token": t.category[self.categories[inst]],
                "nbr_annotations": len(anns), "first_annotation_token": anns[0]["token"],
                "last_annotation_token": anns[-1]["token"],
            })
            t.t["sample_annotation"] += anns
        t.t["scene"].append({
            "token": self.scene, "log_token": self.log, "nbr_samples": len(self.samples),
            "first_sample_token": self.samples[0]["token"], "last_sample_token": self.samples[-1]["token"],
            "name": self.name, "description": self.description,
        })


def _link(records: list[dict]) -> None:
    for a, b in zip(records[:-1], records[1:]):
        a["next"] = b["token"]
        b["prev"] = a["token"]
