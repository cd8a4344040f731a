"""nuScenes dataset for HD-map learning: six camera images, calibration, ego pose, the local
vectorized map (data/local_map.py) and the InstaGraM targets (targets.py), as a dict per sample
with the keys of docs/conventions.md; ``data.base.collate_fn`` batches them.

    ds = NuScenesMapDataset(cfg, "train")          # cfg.data.dataroot / version / splits_file
    loader = DataLoader(ds, batch_size=4, collate_fn=collate_fn, num_workers=cfg.data.num_workers)

Splits: ``v1.0-trainval`` uses the devkit's official train/val scenes, ``v1.0-mini`` its
mini_train/mini_val (asked for as "train"/"val"), and ``data.splits_file`` (a JSON
``{"train": [scene names], "val": [...]}``) overrides both and works with any version folder.
``data.split_scheme=geo`` takes StreamMapNet's geographically disjoint scene lists instead
(data/geo_split.py), on any version folder: a listed scene the folder lacks is named.

Poses: the map and ``ego_pose`` use the ego pose of the sample's LIDAR_TOP record (the keyframe
reference, as HDMapNet/MapTR; CAM_FRONT when a dataroot has no lidar). The cameras' ego poses at
their own timestamps are not used (lift-splat-shoot's simplification): the camera -> ego transform is
each camera's calibrated sensor. Bad input: data/base.py.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from pyquaternion import Quaternion

from ..config import ExperimentConfig
from ..files import relative_path_note
from .base import (
    DatasetError,
    MapDataset,
    check_camera_plausible,
    check_camera_time,
    check_distinct_images,
    check_ego_level,
    check_finite,
    check_intrinsics,
    check_translation,
)
from .geo_split import GeoSplit, from_list, from_networks, synthetic_manifest
from .local_map import LocalMapBuilder, MapError, heading
from .rig import CAMERAS

OFFICIAL_SPLITS = {
    "v1.0-trainval": {"train": "train", "val": "val"},
    "v1.0-mini": {"train": "mini_train", "val": "mini_val"},
    "v1.0-test": {"test": "test"},  # no annotations, but the maps: the devkit's split 'test' (was refused)
}
SPLITS_FILE_FORM = '{"train": [scene names], "val": [scene names]}'  # data.splits_file


def open_nuscenes(dataroot: str | Path, version: str):
    """``NuScenes(version, dataroot)`` with errors that say what is wrong with the folder."""
    from nuscenes.nuscenes import NuScenes

    root = Path(dataroot)
    if not root.is_dir():
        if root.exists():  # data.dataroot=gt.json, a file given where the dataset's folder goes
            raise DatasetError(f"nuScenes dataroot {root} is a file, not a folder; set data.dataroot (or --dataroot) "
                               "to the folder that holds the version folder (v1.0-trainval, v1.0-mini), maps and "
                               "samples")
        raise DatasetError(f"nuScenes dataroot not found: {root} (set data.dataroot or --dataroot"
                           f"{relative_path_note(root)})")
    table_root = root / version
    if not (table_root / "sample.json").is_file():
        found = sorted(p.name for p in root.iterdir() if (p / "sample.json").is_file())
        if (table_root / version / "sample.json").is_file():  # an archive extracted into a folder of its own name
            raise DatasetError(f"nuScenes version '{version}': its tables are one folder too deep, in "
                               f"{table_root / version}: move them up into {table_root}")
        archives = sorted(p.name for p in root.iterdir() if p.name.endswith((".tgz", ".tar", ".tar.gz", ".zip")))
        if archives and not found:  # "versions in X: none" beside the downloaded archives
            raise DatasetError(f"nuScenes version '{version}' not found in {root}, which holds the archives "
                               f"{', '.join(archives[:4])}{' ...' if len(archives) > 4 else ''}: extract them there "
                               f"(tar -xzf FILE -C {root}), so that {table_root} holds the tables")
        av2 = not found and any(root.glob("*/*/city_SE3_egovehicle.feather"))  # <split>/<log>/: an AV2 root
        below = [] if found else sorted(p.parent.parent for p in root.glob(f"*/{version}/sample.json"))
        hint = ("(it is an Argoverse 2 sensor-dataset root: set data.dataset=av2)" if av2 else
                f"({root} is a version folder itself: set data.dataroot to the folder above it, {root.parent})"
                if (root / "sample.json").is_file() else
                f"(the dataroot is the folder that holds {version}: set data.dataroot to {below[0]})" if below else
                "(set data.version or --version)")
        raise DatasetError(f"nuScenes version '{version}' not found: {table_root}/sample.json does not exist; "
                           f"versions in {root}: {', '.join(found) or 'none'} " + hint)
    try:
        nusc = NuScenes(version=version, dataroot=str(root), verbose=False)
    except KeyError as e:  # the devkit's reverse index: a record names a token that its table does not hold
        raise DatasetError(f"cannot load nuScenes tables from {table_root}: a record refers to token {e} that no "
                           "record of the table it points into holds (a record removed from one table but still named "
                           "by another, e.g. a sample_annotation of a removed sample); remove or fix the referring "
                           "records") from None
    except (AssertionError, ValueError, OSError, json.JSONDecodeError) as e:
        if str(e).startswith("map mask ") and str(e).endswith(" does not exist"):  # the devkit's own assert
            raise DatasetError(f"nuScenes version '{version}' in {root}: the {e}: the basemap PNGs (maps/*.png) come "
                               f"with the metadata archive ({version}_meta): extract its maps/ folder into "
                               f"{root}") from None
        raise DatasetError(f"cannot load nuScenes tables from {table_root}: "
                           f"{_unparsable_table(table_root) or f'{type(e).__name__}: {e}'}") from None
    except Exception as e:  # the devkit indexes records without checking them (TypeError, IndexError, ...)
        raise DatasetError(f"cannot load nuScenes tables from {table_root}: "
                           f"{_malformed_table(table_root) or f'{type(e).__name__}: {e}'}") from None
    check_unique_tokens(nusc, table_root)
    return nusc


def check_unique_tokens(nusc, table_root: Path) -> None:
    """Every record's token once in its table, every scene name once: the devkit's index keeps the last record of a
    token (``nusc.get``), so a duplicate silently shadowed the first (a scene's chain cut short, another image), and
    two scenes of one name were read as one drive."""
    for name in nusc.table_names:
        records = getattr(nusc, name, None) or ()
        index = getattr(nusc, "_token2ind", {}).get(name)  # the devkit's token -> index: shorter with a duplicate
        if index is not None and len(index) == len(records):
            continue
        repeat = _first_repeat(r["token"] for r in records)
        if repeat is not None:
            j, i = repeat
            raise DatasetError(f"cannot load nuScenes tables from {table_root}: {name}.json holds two records "
                               f"with token {records[i]['token']} (records {j} and {i}); a token names one record: "
                               "remove or re-token the copy")
    repeat = _first_repeat(scene.get("name") for scene in nusc.scene)
    if repeat is not None:
        (j, i), scene = repeat, nusc.scene[repeat[1]]
        raise DatasetError(f"cannot load nuScenes tables from {table_root}: scene.json names two scenes "
                           f"{scene.get('name')!r} (records {j} and {i}, tokens {nusc.scene[j]['token']} and "
                           f"{scene['token']}); splits and temporal models tell scenes apart by name: rename one")


def _first_repeat(keys) -> tuple[int, int] | None:
    """The positions ``(first, later)`` of the first key of ``keys`` that came before, or None."""
    seen: dict = {}
    for i, key in enumerate(keys):
        j = seen.setdefault(key, i)
        if j != i:
            return j, i
    return None


def _unparsable_table(table_root: Path) -> str | None:
    """The first table file of ``table_root`` that the devkit's ``json.load`` cannot read, with why (a UTF-8
    byte-order mark, which Windows editors write and the devkit refuses, said as such); None if all parse."""
    for path in sorted(table_root.glob("*.json")):
        try:
            data = path.read_bytes()
            json.loads(data.decode("utf-8"))
        except OSError:
            continue
        except UnicodeDecodeError as e:
            return f"{path.name} is not UTF-8 text ({e.reason} at byte {e.start})"
        except ValueError as e:
            if data.startswith(b"\xef\xbb\xbf"):
                return (f"{path.name} starts with a UTF-8 byte-order mark, which the nuScenes devkit cannot read; "
                        "save it as UTF-8 without one")
            if not data.strip():  # "Expecting value: line 1 column 1" for a download cut short
                return (f"{path.name} is empty ({len(data)} bytes): a download or extraction cut short? extract the "
                        "metadata archive again")
            return f"{path.name} is not valid JSON: {e}"
    return None


def _malformed_table(table_root: Path) -> str | None:
    """The first table file of ``table_root`` that is not a non-empty JSON list of records with a
    'token' (what the devkit assumes without checking), said in words; None if all are."""
    for path in sorted(table_root.glob("*.json")):
        try:
            records = json.loads(path.read_text())
        except (OSError, ValueError):
            continue  # the devkit's own error names these
        if not isinstance(records, list):
            return f"{path.name} holds a JSON {type(records).__name__}, not a list of records"
        if not records and path.stem in ("map", "sensor", "log", "scene", "sample"):
            return f"{path.name} holds no records"
        bad = next((i for i, r in enumerate(records) if not isinstance(r, dict) or "token" not in r), None)
        if bad is not None:
            return f"{path.name}: record {bad} is not an object with a 'token' ({records[bad]!r:.80})"
    return None


def split_scene_names(nusc, version: str, split: str, splits_file: str | None = None) -> list[str]:
    """Scene names of ``split``, in the order of the dataroot's scene table."""
    present = [s["name"] for s in nusc.scene]
    if splits_file is not None:
        path = Path(splits_file)
        if not path.is_file() and (Path(nusc.dataroot) / path).is_file():
            path = Path(nusc.dataroot) / path
        if path.is_dir():
            raise DatasetError(f"splits file {splits_file} is a folder (config key data.splits_file): give the JSON "
                               "file of scene names per split")
        if not path.is_file():
            raise DatasetError(f"splits file not found: {splits_file} (config key data.splits_file"
                               f"{relative_path_note(splits_file)})")
        try:  # a byte-order mark (Windows editors; PowerShell's UTF-16) was refused or a raw UnicodeDecodeError
            raw = path.read_bytes()
            splits = json.loads(raw.decode("utf-16" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"))
        except OSError as e:
            raise DatasetError(f"splits file {path} cannot be read ({e.strerror or e})") from None
        except UnicodeDecodeError:
            raise DatasetError(f"splits file {path} is not a JSON text file (UTF-8); expected {SPLITS_FILE_FORM}"
                               ) from None
        except json.JSONDecodeError as e:
            yaml = path.suffix.lower() in (".yaml", ".yml")
            hint = f" (a YAML file? write it as JSON: {SPLITS_FILE_FORM})" if yaml else ""
            raise DatasetError(f"splits file {path} is not valid JSON: {e}{hint}") from None
        if not isinstance(splits, dict):  # a list of lists said "it has: none"
            raise DatasetError(f"splits file {path} holds a JSON {type(splits).__name__}, not an object of splits: "
                               f"write it as {SPLITS_FILE_FORM}")
        if split not in splits or not isinstance(splits[split], list):
            raise DatasetError(f"splits file {path} has no list of scene names for split '{split}'; it has: "
                               f"{', '.join(splits)} (set data.train_split / data.val_split to the file's names)")
        odd = [n for n in splits[split] if not isinstance(n, str)]
        if odd:  # a nested list ({"val": [names]} with names a list already) was a raw TypeError
            raise DatasetError(f"splits file {path}: split '{split}' must list scene names (strings), got "
                               f"{odd[0]!r:.80}")
        wanted = set(splits[split])
        missing = sorted(wanted - set(present))
        if missing:
            hint = ""  # tokens of samples or scenes were taken for unknown scene names, with no word on why
            for table, what in (("sample", "sample tokens"), ("scene", "scene tokens")):
                if set(missing) <= {r.get("token") for r in getattr(nusc, table, [])}:
                    hint = (f" (these are {what}: a splits file lists scene names, the 'name' of scene.json, "
                            f"e.g. {present[:1]})")
            raise DatasetError(f"splits file {path}: split '{split}' names {len(missing)} scene(s) not in version "
                               f"'{version}' of {nusc.dataroot}, e.g. {missing[:3]}{hint}")
    elif version in OFFICIAL_SPLITS:
        from nuscenes.utils.splits import create_splits_scenes

        official = create_splits_scenes()
        name = OFFICIAL_SPLITS[version].get(split, split)
        if name not in official:
            raise DatasetError(f"unknown split '{split}' for {version}; use one of "
                               f"{', '.join(OFFICIAL_SPLITS[version])}, {', '.join(official)}, or set data.splits_file")
        wanted = set(official[name])
        if present and not wanted & set(present):  # was "split 'mini_train' ... has no samples", with no word on why
            holding = [k for k, v in official.items() if set(present) & set(v)]
            raise DatasetError(
                f"split '{split}' of {version}: the nuScenes devkit's official split '{name}' ({len(wanted)} scenes, "
                f"e.g. {sorted(wanted)[:2]}) names none of the {len(present)} scene(s) of version '{version}' in "
                f"{nusc.dataroot} (e.g. {present[:2]}); "
                + (f"its scenes are in the official split(s) {', '.join(holding)}: set data.train_split / "
                   "data.val_split to one of them" if holding else
                   f"they are not official nuScenes scenes: set data.splits_file to a JSON file {SPLITS_FILE_FORM}"))
    else:
        raise DatasetError(f"version '{version}' has no official split; set data.splits_file to a JSON file "
                           f"{SPLITS_FILE_FORM}")
    return [n for n in present if n in wanted]


def geo_split_scenes(nusc, version: str, split: str) -> GeoSplit:
    """The scenes of ``split`` under ``data.split_scheme=geo`` (data/geo_split.py): StreamMapNet's list, or the
    held-out road network of a synthetic world."""
    where = f"{nusc.dataroot} ({version})"
    if synthetic_manifest(nusc.dataroot) is not None:
        logs = {r["token"]: r for r in nusc.log}
        return from_networks(split, {s["name"]: logs.get(s.get("log_token"), {}).get("location", "?")
                                     for s in nusc.scene}, where)
    return from_list("nuscenes", split, [s["name"] for s in nusc.scene], where)


QUATERNION_NORM_TOL = 1e-3  # nuScenes stores unit quaternions to ~1e-8; pyquaternion would normalise any


def _field(record: dict, key: str, table: str):
    """``record[key]`` of a nuScenes table record, or a DatasetError naming the table and the field."""
    try:
        return record[key]
    except KeyError:
        raise DatasetError(f"{table} record {record.get('token', '?')} has no '{key}' field: the {table}.json table "
                           "is incomplete or not in the nuScenes format") from None


def check_pose_record(record: dict, table: str, where: str) -> None:
    """A calibrated_sensor or ego_pose record: finite translation, finite unit quaternion (w, x, y, z)."""
    check_translation(_field(record, "translation", table), "its translation", where)
    q = check_finite(_field(record, "rotation", table), "its rotation", where)
    if q.shape != (4,):
        raise DatasetError(f"{where}: its rotation must be 4 numbers (a quaternion w, x, y, z), got {q.tolist()}")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1) > QUATERNION_NORM_TOL:
        raise DatasetError(f"{where}: its rotation {q.tolist()} is not a unit quaternion (norm {norm:.6g}); the "
                           "record is corrupt")


def _pose_matrix(rotation_wxyz, translation) -> torch.Tensor:
    T = np.eye(4)
    T[:3, :3] = Quaternion(rotation_wxyz).rotation_matrix
    T[:3, 3] = translation
    return torch.from_numpy(T).float()


class NuScenesMapDataset(MapDataset):
    """Samples of one split (data/base.py). ``nusc``: an already loaded ``NuScenes`` of ``cfg.data.version``
    (shared between splits)."""

    camera_names = CAMERAS

    def __init__(self, cfg: ExperimentConfig, split: str, nusc=None, augment: bool | None = None):
        super().__init__(cfg, split, augment)
        d = cfg.data
        self.nusc = nusc if nusc is not None else open_nuscenes(d.dataroot, d.version)
        self.dataroot = Path(self.nusc.dataroot)
        geo = geo_split_scenes(self.nusc, d.version, split) if d.split_scheme == "geo" else None
        names = set(geo.names if geo else split_scene_names(self.nusc, d.version, split, d.splits_file))
        self.sample_tokens: list[str] = []
        self._scene_of: dict[str, dict] = {}
        table = self.dataroot / d.version / "sample.json"
        per_scene: dict[str, list[str]] = {}  # the samples of each scene by their scene_token, in table order
        for s in self.nusc.sample:
            per_scene.setdefault(s.get("scene_token"), []).append(s["token"])
        for scene in self.nusc.scene:
            if scene["name"] not in names:
                continue
            token, seen, last = scene["first_sample_token"], set(), None
            while token:
                if token in seen:  # a corrupt chain would be walked forever
                    raise DatasetError(f"scene {scene['name']}: its samples' 'next' links loop back to sample {token} "
                                       f"in {table}; the table is corrupt")
                sample = self._get("sample", token)
                if sample.get("scene_token", scene["token"]) != scene["token"]:  # a chain run into another scene
                    raise DatasetError(
                        f"scene {scene['name']}: its samples' chain (first_sample_token, then 'next') reaches sample "
                        f"{token}, whose scene_token is {sample['scene_token']}, not this scene's {scene['token']}, "
                        f"in {table}; the chain is corrupt")
                seen.add(token)
                self.sample_tokens.append(token)
                self._scene_of[token] = scene
                last, token = token, _field(sample, "next", "sample")
            lost = [t for t in per_scene.get(scene["token"], []) if t not in seen]
            if lost:  # a chain cut short: its other samples were silently left out of the split
                raise DatasetError(
                    f"scene {scene['name']}: {len(lost)} of its samples in {table} (scene_token {scene['token']}, "
                    f"e.g. {lost[0]}) are not on its chain, which ends at sample {last} ('next' empty); the chain is "
                    "broken: fix the 'next' links")
        if not self.sample_tokens:
            raise DatasetError(f"split '{split}' of {self.dataroot} ({d.version}) has no samples")
        if geo is not None:
            print(geo.line(f"{self.dataroot} ({d.version})", len(self.sample_tokens)), flush=True)
        self.map_builder = LocalMapBuilder(self.dataroot, self.grid, d.sample_dist, d.ped_crossing)
        self.set_scenes([self._scene_of[t]["name"] for t in self.sample_tokens],
                        [self.nusc.get("sample", t)["timestamp"] for t in self.sample_tokens])
        self._map_errors: dict[str, MapError] = {}
        for loc in sorted({self._location(t) for t in self.sample_tokens}):
            try:
                self.map_builder.location_map(loc)
            except MapError as e:
                if d.on_bad_sample == "raise":
                    raise
                warnings.warn(f"samples at location '{loc}' will be skipped: {e}", stacklevel=2)
                self._map_errors[loc] = e

    def _location(self, token: str) -> str:
        scene = self._scene_of[token]
        return _field(self._get("log", _field(scene, "log_token", "scene")), "location", "log")

    def _get(self, table: str, token: str) -> dict:
        """``nusc.get(table, token)``, or a DatasetError naming the table and the missing token."""
        try:
            return self.nusc.get(table, token)
        except KeyError:
            raise DatasetError(f"{table}.json in {self.dataroot / self.data_cfg.version} has no record {token}, "
                               "which another table refers to: the tables are inconsistent") from None

    def _reference_pose(self, sample: dict) -> dict:
        """The ego pose of the sample's LIDAR_TOP record (CAM_FRONT without lidar), checked."""
        data = _field(sample, "data", "sample")
        channel = "LIDAR_TOP" if "LIDAR_TOP" in data else "CAM_FRONT"
        if channel not in data:
            raise DatasetError(f"sample {sample['token']} has neither a LIDAR_TOP nor a CAM_FRONT record in "
                               f"{self.dataroot}")
        sd = self._get("sample_data", data[channel])
        pose = self._get("ego_pose", _field(sd, "ego_pose_token", "sample_data"))
        where = f"ego_pose {pose.get('token')} of {channel} in {self.dataroot / self.data_cfg.version}/ego_pose.json"
        check_pose_record(pose, "ego_pose", where)
        check_ego_level(_pose_matrix(pose["rotation"], pose["translation"])[:3, :3], where,
                        "a quaternion in (x, y, z, w) order? nuScenes writes (w, x, y, z)")
        return pose

    # --- pieces -----------------------------------------------------------------------------------
    def gt_polylines(self, index: int) -> list[dict]:
        token = self.sample_tokens[index]
        loc = self._location(token)
        if loc in self._map_errors:
            raise MapError(f"sample {token}: {self._map_errors[loc]}")
        pose = self._reference_pose(self.nusc.get("sample", token))
        x, y = pose["translation"][:2]
        return self.map_builder(loc, x, y, heading(Quaternion(pose["rotation"]).rotation_matrix))

    def camera_calibration(self, index: int) -> list[tuple]:
        sample = self.nusc.get("sample", self.sample_tokens[index])
        out = []
        for cam in CAMERAS:
            cs = self._camera_records(sample, cam)[1]
            out.append((cs["camera_intrinsic"], Quaternion(cs["rotation"]).rotation_matrix, cs["translation"]))
        return out

    def missing_image_hint(self, path: Path) -> str | None:
        """Why a camera image of the tables is not on disk, for a dataset downloaded in parts: no ``samples/`` at
        all (the metadata alone), the file under another case, or how many of the split's images are missing
        (some blob parts only). None when the file exists. (Each was one "not found" naming one file.)"""
        if path.exists():
            return None
        samples = self.dataroot / "samples"
        if samples.is_symlink() and not samples.exists():  # the blobs on another disk: not "not downloaded"
            return (f"{samples} is a symbolic link to {os.readlink(samples)}, which does not exist (a disk not "
                    "mounted, or the images moved?)")
        if not samples.is_dir():
            return (f"{self.dataroot} has no samples/ folder: the camera images are not downloaded, only the "
                    f"metadata ({self.data_cfg.version}/); download the nuScenes camera blobs (e.g. "
                    f"{self.data_cfg.version}01..10_blobs) and extract them into {self.dataroot} (export-gt needs "
                    "no images)")
        if path.parent.is_dir():
            names = self.__dict__.setdefault("_folder_names", {})  # folder -> its file names by lower case
            if path.parent not in names:
                names[path.parent] = {p.name.lower(): p.name for p in path.parent.iterdir()}
            other = names[path.parent].get(path.name.lower())
            if other is not None:
                return (f"the folder holds {other}, its name in another case (the tables name {path.name}, and file "
                        "names are case-sensitive): rename the files as the tables name them")
        if getattr(self, "_missing_count", None) is None:
            n = missing = 0
            for token in self.sample_tokens:
                data = self.nusc.get("sample", token).get("data") or {}
                for cam in CAMERAS:
                    try:
                        name = self.nusc.get("sample_data", data[cam])["filename"]
                    except (KeyError, TypeError):
                        continue
                    n += 1
                    missing += not (self.dataroot / name).exists()
            self._missing_count = (missing, n)
        missing, n = self._missing_count
        skip = ("" if self.data_cfg.on_bad_sample == "skip" else
                ", or set data.on_bad_sample=skip to use only the samples whose images are present")
        return (f"{missing} of the {n} camera images of split '{self.split}' are not in {self.dataroot} (a partial "
                f"download? the nuScenes camera blobs come in parts): download and extract the missing parts{skip}")

    def _camera_records(self, sample: dict, cam: str) -> tuple[dict, dict]:
        """(sample_data, calibrated_sensor) of camera ``cam`` of ``sample``, their fields checked: a
        file name and size, a finite translation, a unit quaternion (so an orthonormal rotation) and a
        pinhole matrix with positive focal lengths."""
        data = _field(sample, "data", "sample")
        if cam not in data:
            raise DatasetError(self._shared_calibration(sample, cam)
                               or f"sample {sample['token']} has no {cam} image in {self.dataroot}")
        sd = self._get("sample_data", data[cam])
        for key in ("filename", "width", "height"):
            _field(sd, key, "sample_data")
        name = sd["filename"]
        if isinstance(name, str) and "\\" in name and not (self.dataroot / name).exists():
            sd = {**sd, "filename": name.replace("\\", "/")}  # a table written on Windows (str() of a WindowsPath)
        for key in ("width", "height"):  # the image's size: it scales the resize and the intrinsics' use
            if isinstance(sd[key], bool) or not isinstance(sd[key], int) or sd[key] < 1:
                table = self.dataroot / self.data_cfg.version / "sample_data.json"
                raise DatasetError(f"sample_data {sd.get('token', '?')} ({cam}) in {table}:"
                                   f" '{key}' must be the image's size in pixels, a whole number "
                                   f">= 1, got {sd[key]!r}")
        cs = self._get("calibrated_sensor", _field(sd, "calibrated_sensor_token", "sample_data"))
        where = (f"camera {cam}: calibrated_sensor {cs.get('token')} in "
                 f"{self.dataroot / self.data_cfg.version}/calibrated_sensor.json")
        check_pose_record(cs, "calibrated_sensor", where)
        check_intrinsics(_field(cs, "camera_intrinsic", "calibrated_sensor"), where)
        check_camera_plausible(cs["camera_intrinsic"], _pose_matrix(cs["rotation"], cs["translation"])[:3, :3].double(),
                               cs["translation"], (sd["width"], sd["height"]), where,
                               "is its rotation the camera -> ego quaternion, in (w, x, y, z) order (not ego -> "
                               "camera, its inverse; not x, y, z, w)?", channel=cam)
        check_camera_time(_field(sample, "timestamp", "sample"), _field(sd, "timestamp", "sample_data"),
                          f"sample {sample['token']}: camera {cam}: sample_data {sd.get('token', '?')} in "
                          f"{self.dataroot / self.data_cfg.version}/sample_data.json")
        return sd, cs

    def _shared_calibration(self, sample: dict, cam: str) -> str | None:
        """Why ``sample`` lacks camera ``cam`` when its key-frame images share calibrated_sensor records (the
        devkit files each image under its calibration's channel, so the others' channels vanish), else None."""
        channels: dict[str, list[str]] = {}
        for sd in self.nusc.sample_data:
            if sd.get("sample_token") == sample["token"] and sd.get("is_key_frame") and sd.get("channel"):
                channels.setdefault(sd["channel"], []).append(sd.get("calibrated_sensor_token", "?"))
        shared = {ch: toks for ch, toks in channels.items() if len(toks) > 1}
        if not shared:
            return None
        ch, toks = max(shared.items(), key=lambda kv: len(kv[1]))
        return (f"sample {sample['token']} has no {cam} image: {len(toks)} of its key-frame sample_data records "
                f"(calibrated_sensor {', '.join(sorted(set(toks)))[:120]}) are calibrated as {ch} in "
                f"{self.dataroot / self.data_cfg.version}/sample_data.json: a duplicate calibration (each camera's "
                "images have their own calibrated_sensor record, of that camera's sensor)")

    def ego_pose(self, index: int) -> torch.Tensor:
        """[4, 4] ego -> global of the sample's reference pose (LIDAR_TOP, else CAM_FRONT)."""
        pose = self._reference_pose(self.nusc.get("sample", self.sample_tokens[index]))
        return _pose_matrix(pose["rotation"], pose["translation"])

    def ground_height(self, index: int) -> float:
        """0: nuScenes' ego frame lies on the ground (its ego poses have z = 0, the sensors' heights are
        above the road)."""
        return 0.0

    def camera_files(self, index: int) -> list[tuple[Path, tuple[int, int]]]:
        sample = self.nusc.get("sample", self.sample_tokens[index])
        out = []
        for cam in CAMERAS:
            sd, _ = self._camera_records(sample, cam)
            out.append((self.dataroot / sd["filename"], (sd["width"], sd["height"])))
        check_distinct_images([path for path, _ in out], CAMERAS,
                              f"sample {sample['token']} in {self.dataroot / self.data_cfg.version}/sample_data.json")
        return out
