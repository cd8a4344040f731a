"""Calibration and rigs: the dataset's camera calibrations and ego poses, the ``Frame`` of the Python API (``Mapper``,
``MapStream``) and the rig file of ``predict-images``. A calibration that is readable but wrong (millimetres, a
quaternion in another order, a camera upside down, intrinsics of another image size) is named, not mapped.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    REPO,
    TINY_YAML,
    add,
    av2_copy,
    av2_dataset,
    av2_error,
    camera_record,
    evaluate_world,
    first,
    forbid,
    mapper_frame,
    rig_files,
    row,
    table,
    temporal_checkpoint,
    val_dataset,
)
from instagram_hdmap.checkpoint import save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict, load_config


def _calibration_row(channel: str, edit: Callable[[dict], None], pattern: str):
    def run(env):
        def damage(tables):
            sd, cs = camera_record(tables, channel)
            edit(cs)

        root = env.shadow_world(damage)
        env.error(pattern, "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
                  "--out", env.tmp / "eval")

    return run


for _name, _channel, _edit, _pattern in (
    ("nan_camera_translation", "CAM_FRONT", lambda cs: cs["translation"].__setitem__(0, float("nan")),
     r"CAM_FRONT.*translation.*(NaN|finite)"),
    ("nan_camera_rotation", "CAM_BACK", lambda cs: cs["rotation"].__setitem__(1, float("nan")),
     r"CAM_BACK.*rotation.*(NaN|finite)"),
    ("camera_rotation_not_unit", "CAM_BACK_LEFT",
     lambda cs: cs.__setitem__("rotation", [2 * q for q in cs["rotation"]]),
     r"CAM_BACK_LEFT.*rotation.*(unit|orthonormal)"),
    ("negative_focal_length", "CAM_FRONT_LEFT", lambda cs: cs["camera_intrinsic"][0].__setitem__(0, -500.0),
     r"CAM_FRONT_LEFT.*intrinsic.*focal"),
    ("nan_intrinsics", "CAM_FRONT_RIGHT", lambda cs: cs["camera_intrinsic"][1].__setitem__(2, float("nan")),
     r"CAM_FRONT_RIGHT.*intrinsic.*(NaN|finite)"),
):
    add(_name, f"calibration: {_name}", _calibration_row(_channel, _edit, _pattern))


@row("an ego pose with NaN is named, not a GEOS exception")
def row_nan_ego_pose(env):
    def damage(tables):
        sd, _ = camera_record(tables, "CAM_FRONT")
        lidar = first(tables["sample_data"], sample_token=sd["sample_token"], fileformat="pcd")
        first(tables["ego_pose"], token=lidar["ego_pose_token"])["translation"][0] = float("nan")

    root = env.shadow_world(damage)
    env.error(r"ego.?pose.*(NaN|finite)", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt,
              "--out", env.tmp / "eval")


def _edit_feather(path: Path, column: str, row: int, value: float) -> None:
    import pyarrow as pa
    from pyarrow import feather

    table = feather.read_table(str(path))
    values = table.column(column).to_pylist()
    values[row] = value
    feather.write_feather(table.set_column(table.column_names.index(column), column, pa.array(values)), str(path))


@row("AV2: a camera calibration with NaN is named")
def row_av2_nan_calibration(env):
    root, log = av2_copy(env)
    _edit_feather(log / "calibration" / "egovehicle_SE3_sensor.feather", "tx_m", 0, float("nan"))
    av2_error(env, root, rf"log {log.name}: .*egovehicle_SE3_sensor\.feather.*(NaN|finite)")


@row("AV2: an intrinsics row with a negative focal length is named")
def row_av2_negative_focal_length(env):
    root, log = av2_copy(env)
    _edit_feather(log / "calibration" / "intrinsics.feather", "fx_px", 2, -100.0)
    av2_error(env, root, rf"log {log.name}: camera \w+ in .*intrinsics\.feather.*focal")


@row("AV2: an ego pose with NaN is named")
def row_av2_nan_ego_pose(env):
    root, log = av2_copy(env)
    _edit_feather(log / "city_SE3_egovehicle.feather", "ty_m", 0, float("nan"))
    av2_error(env, root, rf"log {log.name}: the ego pose .*city_SE3_egovehicle\.feather.*(NaN|finite)")


@row("AV2: a missing camera folder is named as such, not blamed on timestamps")
def row_av2_missing_camera_folder(env):
    root, log = av2_copy(env)
    shutil.rmtree(log / "sensors" / "cameras" / "ring_side_left")
    line = av2_error(env, root, r"camera folder .*ring_side_left does not exist")
    assert "timestamps" not in line


@row("Mapper: a ground_height of 50 (millimetres, or a height above sea level) is a RigError (the IPM plane "
          "was put 50 m under the cameras: exit 0)")
def row_mapper_ground_height_out_of_range(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    for height in (50.0, -350.0):
        with pytest.raises(RigError, match=r"ground_height is the road's height in the ego frame, within 5 m"):
            mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height=height))
    assert isinstance(mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height=-0.35)), list)  # AV2


@row("Mapper: ego -> camera poses given as cam_to_ego (the inverses) are named: a surround camera is not rolled "
          "on its side (the sweep left it: accepted, a map from the wrong rays, exit 0)")
def row_mapper_ego_to_camera_poses(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    inverse = {c: np.linalg.inv(T) for c, T in poses.items()}
    with pytest.raises(RigError, match=r"camera CAM_FRONT(_LEFT)?: .cam_to_ego.: the camera is (rolled \d+ degrees|"
                                       r"upside down).*camera -> ego rotation \(not ego -> camera"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=inverse))
    assert isinstance(mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses)), list)  # the published rig


@row("Mapper: intrinsics of another image size, transposed, or a camera 1700 m away is named (was silent)")
def row_mapper_calibration_mistakes(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env, intrinsics_size=(1600, 900))  # K of the full-size images
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'intrinsics' puts the principal point .* outside its "
                                       r"400x225 image"):
        mapper(images=images, intrinsics=K, cam_to_ego=poses)
    mapper, images, K, poses = mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'intrinsics' is not a pinhole matrix .*transposed"):
        mapper(images=images, intrinsics={**K, "CAM_FRONT": K["CAM_FRONT"].T}, cam_to_ego=poses)
    mm = poses["CAM_BACK"].copy()
    mm[:3, 3] *= 1000
    with pytest.raises(RigError, match=r"camera CAM_BACK: 'translation' .* m from the ego origin"):
        mapper(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_BACK": mm})


@row("Mapper: an ego_pose whose rotation is not one is named (a temporal model would warp by it)")
def row_mapper_ego_pose_not_rigid(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    pose = np.eye(4)
    pose[:3, :3] *= 2
    with pytest.raises(RigError, match=r"ego_pose has a rotation part that is not a rotation"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose))


def _rig_row(edit, pattern: str, *extra):
    def run(env):
        path, images = rig_files(env, edit)
        forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
        env.error(pattern, "predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out",
                  "--device", "cpu", *extra, *images)

    return run


def _full_size_intrinsics(data: dict) -> None:
    """Every camera's intrinsics for 1600 x 900 images (4x), the images staying 400 x 225."""
    for cam in data["cameras"].values():
        cam["intrinsics"] = (np.array(cam["intrinsics"]) * [[4], [4], [1]]).tolist()


for _name, _edit, _pattern in (
    ("rig_intrinsics_last_row", lambda d: d["cameras"]["CAM_FRONT"]["intrinsics"].__setitem__(2, [5, 5, 5]),
     r"rig\.json: camera CAM_FRONT: 'intrinsics' is not a pinhole matrix"),
    ("rig_translation_in_millimetres",
     lambda d: d["cameras"]["CAM_BACK"].__setitem__("translation", [28.3, 3.5, 1579.1]),
     r"rig\.json: camera CAM_BACK: 'translation' .* m from the ego origin"),
    ("rig_intrinsics_of_the_full_size_images", _full_size_intrinsics,
     r"'intrinsics' puts the principal point .* outside its 400x225 image"),
):
    add(_name, f"predict-images: {_name}", _rig_row(_edit, _pattern))


def _quaternions_xyzw(data: dict) -> None:
    """Every camera's quaternion written [x, y, z, w] (scipy's, ROS's order) where [w, x, y, z] is read."""
    for cam in data["cameras"].values():
        cam["quaternion"] = [*cam["quaternion"][1:], cam["quaternion"][0]]


add("rig_quaternion_xyzw", "predict-images: a rig file's quaternions in [x, y, z, w] order are named "
                "(four of six cameras looked 55-71 degrees up or down: a map from the sky, exit 0)",
                _rig_row(_quaternions_xyzw, r"camera CAM_FRONT_LEFT: the camera looks 55 degrees up.*\[x, y, z, w\]"))


@row("predict-images: a binary file given as --rig is named (was a UnicodeDecodeError)")
def row_rig_file_binary(env):
    path, images = rig_files(env)
    env.error(r"rig file .*CAM_FRONT\.jpg is not a JSON text file", "predict-images", "--checkpoint", env.ckpt,
              "--rig", images[1], "--out", env.tmp / "out", "--device", "cpu", *images)


@row("predict-images: --config with --checkpoint is refused (was silently ignored)")
def row_predict_images_config_with_checkpoint(env):
    path, images = rig_files(env)
    env.error(r"--config goes with --onnx", "predict-images", "--checkpoint", env.ckpt, "--config", env.yaml,
              "--rig", path, "--out", env.tmp / "out", *images)


@row("MapStream: ego poses in UTM coordinates (millions of metres) warp the memory as poses near the origin "
          "(float32 moved it by up to 0.5 m)")
def row_mapstream_utm_poses(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.models import build_model

    cfg = load_config(env.yaml, ["model.temporal.memory=bev", "model.temporal.fusion=gru"])
    torch.manual_seed(0)
    path = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    mapper = Mapper.from_checkpoint(path, device="cpu")
    _, images, K, poses = mapper_frame(env)

    def pose(x: float, yaw: float, origin) -> np.ndarray:
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[:2, 3] = [origin[0] + x, origin[1] + 0.3 * x]
        return T

    memories = []
    for origin in ((0.0, 0.0), (512_345.678, 5_412_345.678)):  # UTM easting, northing
        stream = mapper.stream()
        for x, yaw in ((0.0, 0.0), (1.3, 0.05)):
            stream.step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose(x, yaw, origin)))
        assert stream.status == "fused"
        memories.append(stream.memory["bev"])
    torch.testing.assert_close(memories[1], memories[0], atol=1e-5, rtol=1e-5)


@row("Mapper: a ground_height or an ego_pose that is not a number is a RigError (was a raw ValueError)")
def row_mapper_values_not_numbers(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    with pytest.raises(RigError, match=r"ground_height must be a finite height in metres, got \['abc'\]"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego=poses, ground_height="abc"))
    with pytest.raises(RigError, match=r"ego_pose must be a finite 4x4 .* got 'abc'"):
        mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose="abc"))


@row("an MLP view transform with another model.view_transform.num_cameras than the rig's cameras (AV2's seven) "
          "is named before the model runs (was a raw ValueError in forward)")
def row_mlp_num_cameras_of_the_rig(env):
    env.error(r"'model\.view_transform\.num_cameras' is 6, .* the 7 cameras of data\.dataset=av2 .*num_cameras=7",
              "model-summary", env.yaml, "data.dataset=av2", "data.splits_file=null", "model.view_transform.kind=mlp",
              "model.view_transform.mlp_bev_downsample=4")
    env.error(r"num_cameras' is 6, .* the 3 cameras", "model-summary", env.yaml, "data.dataset=av2",
              "data.splits_file=null", "model.view_transform.kind=mlp", "model.view_transform.mlp_bev_downsample=4",
              "data.av2_cameras=[ring_front_left,ring_front_center,ring_front_right]")
    rc, _, err = env.cli("model-summary", env.yaml, "data.dataset=av2", "data.splits_file=null",
                         "model.view_transform.kind=mlp", "model.view_transform.mlp_bev_downsample=4",
                         "model.view_transform.num_cameras=7")
    assert rc == 0, err


@row("a checkpoint's AV2 camera order wins over the CONFIG file's, with a note (an MLP model's per-camera layers "
          "met other cameras: exit 0)")
def row_checkpoint_av2_camera_order(env):
    from instagram_hdmap.config import AV2_RING_CAMERAS
    from instagram_hdmap.inference import inference_config

    order = [AV2_RING_CAMERAS[-1], *AV2_RING_CAMERAS[:-1]]
    mlp = ["data.dataset=av2", "model.view_transform.kind=mlp", "model.view_transform.num_cameras=7"]
    trained = load_config(TINY_YAML, [*mlp, f"data.av2_cameras=[{','.join(order)}]"])
    out, notes = inference_config(load_config(TINY_YAML, mlp), config_to_dict(trained))
    assert list(out.data.av2_cameras) == order
    assert any("data.av2_cameras=" in n and "using the checkpoint's" in n for n in notes), notes


@row("Mapper: a transposed 4x4 cam_to_ego (its rotation still a rotation, the translation dropped), a (R, t) "
          "pair and intrinsics that require grad are named or taken (silently wrong / raw ValueError / raw "
          "RuntimeError)")
def row_mapper_cam_to_ego_transposed(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'cam_to_ego' has the last row \[1\.70.*, 1\.0\], not "
                                       r"\[0, 0, 0, 1\]: transposed"):
        mapper(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_FRONT": poses["CAM_FRONT"].T})
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'cam_to_ego' must be one 4x4 .* np\.c_\[R, t\]"):
        mapper(images=images, intrinsics=K, cam_to_ego={c: (T[:3, :3], T[:3, 3]) for c, T in poses.items()})
    grads = {c: torch.tensor(k, requires_grad=True) for c, k in K.items()}
    assert mapper(images=images, intrinsics=grads, cam_to_ego=poses) == mapper(images=images, intrinsics=K,
                                                                              cam_to_ego=poses)


@row("Mapper / predict-images: intrinsics normalised by the image size (fx ~ 1) are named (accepted: the "
          "principal point (0.5, 0.5) lies inside the image)")
def row_normalised_intrinsics(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    normalised = {c: k / np.array([[400.0], [225.0], [1.0]]) for c, k in K.items()}
    with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'intrinsics' has a focal length of .* field of view "
                                       r"over 175 degrees .* normalised by the image size"):
        mapper(images=images, intrinsics=normalised, cam_to_ego=poses)

    def normalise(data):
        for cam in data["cameras"].values():
            cam["intrinsics"] = (np.array(cam["intrinsics"]) / [[400], [225], [1]]).tolist()

    _rig_row(normalise, r"rig\.json: camera CAM_FRONT_LEFT: 'intrinsics' has a focal length")(env)


@row("Mapper: a camera upside down (an OpenGL / Blender pose, y up and z backward, or a 180 degree roll) is "
          "named (accepted: rays from the wrong side of the car, exit 0), and a roll of 120 degrees is not reported "
          "as 60")
def row_mapper_camera_upside_down(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    for flip in (np.diag([1.0, -1.0, -1.0, 1.0]), np.diag([-1.0, -1.0, 1.0, 1.0])):  # OpenGL axes; rolled 180
        with pytest.raises(RigError, match=r"camera CAM_FRONT_LEFT: 'cam_to_ego': the camera is upside down .*OpenGL"):
            mapper(images=images, intrinsics=K, cam_to_ego={c: T @ flip for c, T in poses.items()})
    c, s = np.cos(np.radians(120)), np.sin(np.radians(120))
    roll = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # about the optical axis
    with pytest.raises(RigError, match=r"rolled 120 degrees"):
        mapper(images=images, intrinsics=K, cam_to_ego={c: T @ roll for c, T in poses.items()})
    c, s = np.cos(np.radians(-20)), np.sin(np.radians(-20))
    pitched = np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])  # 20 degrees down: a real rig
    assert isinstance(mapper(images=images, intrinsics=K, cam_to_ego={c: T @ pitched for c, T in poses.items()}), list)


@row("predict-images: images named for other cameras than the rig file's order gives them (in the model's order, "
          "or shuffled) are named (a map from swapped cameras, exit 0)")
def row_images_named_for_other_cameras(env):
    def reverse(data):
        data["cameras"] = dict(reversed(list(data["cameras"].items())))

    rig, images = rig_files(env, reverse)  # the images in the model's order, the rig file's cameras reversed
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"image .*CAM_FRONT_LEFT\.jpg is named for camera CAM_FRONT_LEFT but is given for camera CAM_BACK_RIGHT: "
              r"give the images in the rig file's order", "predict-images", "--checkpoint", env.ckpt, "--rig", rig,
              "--out", env.tmp / "out", "--device", "cpu", *images)
    mapper, arrays, K, poses = mapper_frame(env)
    with pytest.raises(UserError, match=r"camera CAM_FRONT_LEFT: its image .*CAM_FRONT\.jpg is named for camera "
                                        r"CAM_FRONT"):
        mapper(images=[images[1], images[0], *images[2:]], intrinsics=[K[c] for c in mapper.cameras],
               cam_to_ego=[poses[c] for c in mapper.cameras])


@row("MapStream: float32 ego poses at UTM coordinates are named (float32 had rounded them to 0.5 m before the "
          "stream's float64 shift: the memory misplaced by that much, exit 0)")
def row_mapstream_float32_utm_poses(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import RigError

    _, images, K, poses = mapper_frame(env)
    mapper = Mapper.from_checkpoint(temporal_checkpoint(env), device="cpu")
    pose = np.eye(4)
    pose[:3, 3] = [4.4e6, 5.8e5, 300.0]  # UTM northing, easting, height
    for given in (pose.astype(np.float32), torch.tensor(pose, dtype=torch.float32)):
        with pytest.raises(RigError, match=r"ego_pose is float32 at 4\.4e\+06 m .* only to 0\.5 m.* float64"):
            mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=given))
    assert isinstance(mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose)), list)


@row("nuScenes tables: a camera calibration in millimetres, intrinsics of another image size, a quaternion in "
          "x, y, z, w order or an ego -> camera rotation are named (the Mapper refused them; the dataset ran, exit 0)")
def row_dataset_calibration_consistent_but_wrong(env):
    from pyquaternion import Quaternion

    def edit(change, channel="CAM_FRONT"):
        return lambda tables: change(camera_record(tables, channel)[1])

    def mm(cs):
        cs["translation"] = [v * 1000 for v in cs["translation"]]

    def intrinsics_1600x900(cs):
        cs["camera_intrinsic"] = (np.array(cs["camera_intrinsic"]) * [[4], [4], [1]]).tolist()

    def xyzw(cs):
        w, x, y, z = cs["rotation"]
        cs["rotation"] = [x, y, z, w]

    def inverse(cs):
        cs["rotation"] = list(Quaternion(cs["rotation"]).inverse.elements)

    where = r"camera CAM_FRONT: calibrated_sensor \w+ in .*calibrated_sensor\.json: "
    evaluate_world(env, edit(mm), where + r"its translation .* puts the camera \d{4} m from the ego .*millimetres")
    evaluate_world(env, edit(intrinsics_1600x900),
                   where + r"its intrinsics matrix puts the principal point .* outside its 400x225 image")
    for change in (xyzw, inverse):  # CAM_FRONT's quaternion read so still gives a level camera: a rig's trips on others
        evaluate_world(env, edit(change, "CAM_FRONT_LEFT"), r"camera CAM_FRONT_LEFT: .*: the camera (looks|is "
                        r"rolled|is upside down).*\(w, x, y, z\) order")


@row("AV2: an egovehicle_SE3_sensor translation in millimetres or intrinsics of the full-size image are named "
          "(ran, exit 0)")
def row_av2_calibration_consistent_but_wrong(env):
    from pyarrow import feather

    root, log = av2_copy(env)
    extrinsics = log / "calibration" / "egovehicle_SE3_sensor.feather"
    _edit_feather(extrinsics, "tx_m", 0, 1000 * feather.read_table(str(extrinsics)).column("tx_m")[0].as_py())
    av2_error(env, root, rf"log {log.name}: camera \w+ in .*egovehicle_SE3_sensor\.feather .*from the ego origin")
    root, log = av2_copy(env) if shutil.rmtree(root) is None else (None, None)
    intrinsics = log / "calibration" / "intrinsics.feather"
    _edit_feather(intrinsics, "cx_px", 0, 5 * feather.read_table(str(intrinsics)).column("cx_px")[0].as_py())
    av2_error(env, root, rf"log {log.name}: camera \w+ in .*intrinsics\.feather: its intrinsics matrix puts the "
                         r"principal point .* outside")


@row("nuScenes tables: ego poses whose quaternion is in x, y, z, w order, or in millimetres, are named (the GT "
          "map was cut at another heading or far off the map, exit 0)")
def row_dataset_ego_pose_consistent_but_wrong(env):
    from pyquaternion import Quaternion

    def xyzw(tables):
        for pose in tables["ego_pose"]:
            w, x, y, z = Quaternion(axis=[0, 0, 1], degrees=90).elements  # heading 90 degrees, read in xyzw order
            pose["rotation"] = [x, y, z, w]

    def mm(tables):
        for pose in tables["ego_pose"]:
            pose["translation"] = [v * 1000 for v in pose["translation"]]

    evaluate_world(env, xyzw, r"ego_pose \w+ of LIDAR_TOP .*: its rotation tilts the vehicle 90 degrees .*"
                               r"\(x, y, z, w\)")
    evaluate_world(env, mm, r"the ego position \(\d+\.\d, \d+\.\d\) lies \d+ km outside the map of location "
                             r".*millimetres")


@row("nuScenes tables: a camera image taken seconds from its sample (timestamps of another moment or unit) is "
          "named with the sample, the camera and the gap (ran, exit 0); every sample of the synthetic worlds passes")
def row_camera_image_of_another_moment(env):
    from instagram_hdmap.data.base import check_camera_time

    def late(tables):
        for sd in tables["sample_data"]:
            if sd["fileformat"] == "jpg" and "CAM_BACK__" in sd["filename"]:
                sd["timestamp"] += 5_000_000

    evaluate_world(env, late, r"sample \w+: camera CAM_BACK: sample_data \w+ in .*sample_data\.json: the image's "
                               r"timestamp \d+ us is 5 s from its sample's")
    for split in ("train", "val"):  # the synthetic worlds' every sample (AV2: av2's 25 ms synchronisation, checked)
        for ds in (val_dataset(env.cfg(f"data.val_split={split}")), av2_dataset(env, split)):
            for i in range(len(ds)):
                ds.camera_files(i)
    with pytest.raises(UserError, match=r"camera ring_rear_left: .* 0\.6 s from its sample's"):
        check_camera_time(1_000_000, 1_600_000, "camera ring_rear_left: x.jpg")
    check_camera_time(1_000_000, 1_050_000, "a real rig's 50 ms")


REAL_AV2 = REPO.parent / "shared" / "av2_real"


@row("a camera whose optical axis points where its channel does not (CAM_FRONT and CAM_BACK swapped in the "
          "sensor table, a Mapper given the back camera's pose as the front's) is named (ran, exit 0); every camera "
          "of the real nuScenes rig, the real AV2 log and the synthetic worlds passes")
def row_camera_heading_of_another_channel(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.base import NOMINAL_CAMERA_YAW_DEG, camera_heading_problem
    from instagram_hdmap.data.rig import RigError, rig
    from instagram_hdmap.data.synthetic.av2_writer import av2_rig

    def swap(tables):
        for s in tables["sensor"]:
            s["channel"] = {"CAM_FRONT": "CAM_BACK", "CAM_BACK": "CAM_FRONT"}.get(s["channel"], s["channel"])

    evaluate_world(env, swap, r"camera CAM_(FRONT|BACK): calibrated_sensor \w+ in .*: its optical axis points "
                               r"-?\d+ degrees left of the vehicle's forward direction, 180 degrees off where a CAM_")
    mapper, images, K, poses = mapper_frame(env)
    with pytest.raises(RigError, match=r"camera CAM_FRONT: 'cam_to_ego': its optical axis points 180 degrees left .* "
                                       r"off where a CAM_FRONT camera looks \(0;"):
        mapper(Frame(images=images, intrinsics=K, cam_to_ego={**poses, "CAM_FRONT": poses["CAM_BACK"]}))
    # the real rigs and the synthetic ones pass; the AV2 world's cameras pass when its dataset loads them
    real = {c: s.rot for c, s in rig().items() if s.modality == "camera"}
    real |= {c: s.rot for c, s in av2_rig().items() if s.modality == "camera"}
    if (REAL_AV2 / "val").is_dir():
        from av2.utils.io import read_ego_SE3_sensor

        for log in (REAL_AV2 / "val").iterdir():
            real |= {f"{c} of {log.name}": p.rotation for c, p in read_ego_SE3_sensor(log).items()
                     if c.startswith("ring")}
        real_ds = av2_dataset(env, "val", REAL_AV2)
        real_ds._log_cameras(real_ds.samples[0][0])  # the dataset's own checks (heading included) pass
    assert len(real) >= 13 and set(NOMINAL_CAMERA_YAW_DEG) <= {c.split(" ")[0] for c in real}
    assert {c: camera_heading_problem(c.split(" ")[0], R) for c, R in real.items()} == dict.fromkeys(real)
    ds = av2_dataset(env, "val")
    ds._log_cameras(ds.samples[0][0])
    assert camera_heading_problem("my_roof_camera", poses["CAM_BACK"][:3, :3]) is None  # unknown names: not checked


@row("nuScenes tables: every camera image of a sample given one calibrated_sensor is named as a duplicate "
          "calibration (was 'has no CAM_FRONT_LEFT image', naming no cause)")
def row_cameras_share_one_calibration(env):
    def share(tables):
        token = camera_record(tables, "CAM_FRONT")[1]["token"]
        for sd in tables["sample_data"]:
            if sd["fileformat"] == "jpg":
                sd["calibrated_sensor_token"] = token

    evaluate_world(env, share, r"sample \w+ has no CAM_FRONT_LEFT image: 6 of its key-frame sample_data records "
                                r"\(calibrated_sensor \w+\) are calibrated as CAM_FRONT .*a duplicate calibration")


@row("an image cropped off-centre (the rows below the horizon, the right part of a wide image) with its "
          "intrinsics shifted puts the principal point outside the image, validly: the Mapper and the datasets "
          "refused it as intrinsics of another image size; those (beyond both far edges) are still named")
def row_principal_point_of_a_cropped_image(env):
    from instagram_hdmap.data.base import DatasetError, check_camera_plausible
    from instagram_hdmap.data.rig import RigError, rig

    mapper, images, K, poses = mapper_frame(env)
    for axis, cut in ((0, 130), (1, 220)):  # rows 130.. (cy < 0), columns 220.. of CAM_FRONT (cx < 0)
        cropped, shifted = dict(images), {c: k.copy() for c, k in K.items()}
        for cam in (mapper.cameras if axis == 0 else ["CAM_FRONT"]):
            cropped[cam] = np.ascontiguousarray(images[cam][cut:] if axis == 0 else images[cam][:, cut:])
            shifted[cam][1 - axis, 2] -= cut
        assert min(k[1 - axis, 2] for k in shifted.values()) < 0
        mapper(images=cropped, intrinsics=shifted, cam_to_ego=poses)  # runs
    sensor = rig((1600, 900))["CAM_FRONT"]
    crop = sensor.intrinsic.copy()
    crop[1, 2] -= 520  # the 1600 x 380 rows below the horizon
    check_camera_plausible(crop, sensor.rot, sensor.trans, (1600, 380), "CAM_FRONT", "hint", channel="CAM_FRONT")
    with pytest.raises(DatasetError, match=r"principal point .* outside its 400x225 image"):  # K of 1600 x 900
        check_camera_plausible(sensor.intrinsic, sensor.rot, sensor.trans, (400, 225), "CAM_FRONT", "hint")
    mapper, images, K, poses = mapper_frame(env, intrinsics_size=(800, 450))  # K of twice the size
    with pytest.raises(RigError, match=r"principal point .* outside its 400x225 image"):
        mapper(images=images, intrinsics=K, cam_to_ego=poses)


@row("AV2: a camera frame dropped at a lidar sweep (no image within 25 ms) was two lines: av2's own logging "
          "warning ('No corresponding ring image at ...') above the one-line error")
def row_av2_dropped_camera_frame_one_line(env):
    root, log = av2_copy(env)
    sorted((log / "sensors" / "cameras" / "ring_side_left").iterdir())[0].unlink()
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "show-gt", str(env.yaml), "data.dataset=av2",
                        "data.splits_file=null", "data.av2_frame_step=1", "data.image_fit=contain",
                        f"data.dataroot={root}", "--split", "train", "--index", "0", "--out", str(env.tmp / "show")],
                       capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1, p.stderr[-2000:]
    assert re.search(r"no ring_side_left image within 25 ms of lidar sweep", lines[0]), lines[0]


@row("predict-images: a rig file saved with a UTF-8 byte-order mark (Windows Notepad, PowerShell's "
            "Out-File) and CRLF line ends was refused as 'not valid JSON (Unexpected UTF-8 BOM)'; a submission "
            "file with one was read already (S9)")
def row_rig_file_with_a_byte_order_mark(env):
    path, images = rig_files(env)
    text = json.dumps(json.loads(path.read_text()), indent=1).replace("\n", "\r\n")
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out",
                           "--device", "cpu", *images)
    assert rc == 0 and (env.tmp / "out" / "prediction.json").is_file(), err[-2000:]


@row("Mapper: an ego_pose with NaN was refused as 'must be a finite 4x4 ... got shape [4, 4]' (the right "
            "shape); the RigError says it has NaN or infinite values")
def row_mapper_nan_ego_pose(env):
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    pose = np.eye(4)
    pose[0, 3] = np.nan
    with pytest.raises(RigError, match=r"the frame's ego_pose has NaN or infinite values"):
        mapper.stream().step(Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=pose))


@row("Mapper / MapStream: an ego_pose whose last row is not [0, 0, 0, 1] (a transposed pose, the translation in "
            "the last row: its rotation part is still a rotation and its translation column 0, so a temporal model "
            "fused its memory as if the ego stood still) was taken with no word; it is a RigError as cam_to_ego was. "
            "MapStream.step(frame, images=...) dropped the fields with no word; it is a TypeError")
def row_ego_pose_transposed(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import RigError, rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    images = dict(zip(mapper.cameras, np.zeros((len(mapper.cameras), 36, 64, 3), dtype=np.uint8)))
    pose = np.eye(4)
    pose[:3, 3] = [12.0, -3.0, 0.0]
    frame = Frame(images, {c: calib[c].intrinsic for c in mapper.cameras},
                  {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras},
                  ego_pose=pose)
    mapper(frame)  # the right way round maps
    with pytest.raises(RigError, match=r"ego_pose has the last row \[12.0, -3.0, 0.0, 1.0\], not \[0, 0, 0, 1\]: "
                                       r"transposed"):
        mapper(Frame(frame.images, frame.intrinsics, frame.cam_to_ego, ego_pose=pose.T.copy()))
    with pytest.raises(TypeError, match="MapStream.step takes a Frame or the fields .* not both"):
        mapper.stream().step(frame, images=images)


@row("predict-images --rig RIG FOLDER (the folder of the camera images instead of the files) said '1 image(s) "
            "for the 6 cameras'; the folder is named as a folder. --name '' (an unset shell variable) wrote the frame "
            "under the key '' with exit 0; it is refused")
def row_predict_images_folder(env):
    path, images = rig_files(env)
    env.error(r"--name '' is empty: give the frame's name in prediction\.json", "predict-images", "--checkpoint",
              env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu", "--name", "", *images)
    env.error(r"is a folder: give the image files themselves, one per camera of rig file .*CAM_FRONT_LEFT",
              "predict-images", "--checkpoint", env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu",
              env.tmp)


@row("predict-images: a rig file could not give the road's height in its ego frame (the Python API's "
            "Frame(ground_height=...)): a rig in AV2's rear-axle frame (the road 0.38 m below the origin) ran with the "
            "ground plane at z = 0, 0.38 m too high for the IPM / MLP view transforms, with no word, and "
            "'ground_height' in the file was an unknown field. The rig file takes \"ground_height\" and passes it to "
            "the model")
def row_predict_images_rig_ground_height(env):
    from instagram_hdmap.mapper import Mapper

    rig, images = rig_files(env, lambda d: d.__setitem__("ground_height", -0.38))
    seen = []
    forward = Mapper.forward

    def spy(self, batch, memory=None):
        seen.append(batch["ground_height"].tolist())
        return forward(self, batch, memory)

    env.monkeypatch.setattr(Mapper, "forward", spy)
    from instagram_hdmap import predict

    drawn = []
    figures = predict.prediction_figures

    def spy_figures(*args, ground_z=0.0, **kwargs):
        drawn.append(ground_z)  # the pictures project the elements onto the same road
        return figures(*args, ground_z=ground_z, **kwargs)

    env.monkeypatch.setattr(predict, "prediction_figures", spy_figures)
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                         "--device", "cpu", *images)
    assert rc == 0, err[-2000:]
    assert seen and np.allclose(seen[0], [-0.38]), seen
    assert drawn and np.isclose(drawn[0], -0.38), drawn
    rig, _ = rig_files(env, lambda d: d.__setitem__("ground_height", "low"))
    env.error(r"rig\.json: 'ground_height' must be a number of metres", "predict-images", "--checkpoint", env.ckpt,
              "--rig", rig, "--out", env.tmp / "out2", "--device", "cpu", *images)


@row("predict-images with a temporal checkpoint ran it on one frame with an empty memory and no word, where "
            "predict says so for a scene's first frame; it now notes that the frame has no memory and how to carry one")
def row_predict_images_temporal_model(env):
    from instagram_hdmap.models import build_model

    cfg = env.cfg("model.temporal.memory=bev", "model.gnn.sinkhorn_iters=3")
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    rig, images = rig_files(env)
    rc, out, err = env.cli("predict-images", "--checkpoint", ckpt, "--rig", rig, "--out", env.tmp / "out", *images)
    assert rc == 0 and "a temporal model (bev memory) on one frame: no memory" in out + err, (out + err)[-2000:]
    rc, out, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "o2", *images)
    assert rc == 0 and "temporal" not in out + err, (out + err)[-2000:]


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_cameras(case, env):
    case.run(env)
