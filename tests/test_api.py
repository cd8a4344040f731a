"""The public Python API (``instagram_hdmap.Mapper``), ``predict-images`` with a rig file and
``predict --scene --video``: README's example run verbatim on a synthetic sample given as plain
arrays equals ``predict``; a rig file written from a sample equals ``predict``; the video has one
frame per sample; bad input is one line naming the camera and the field."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from pyquaternion import Quaternion

from instagram_hdmap import Frame, MapElement, Mapper, to_hdmapnet
from instagram_hdmap.checkpoint import CheckpointError, save_checkpoint
from instagram_hdmap.cli import main
from instagram_hdmap.config import config_to_dict, load_config
from instagram_hdmap.data import build_dataset
from instagram_hdmap.data.rig import CAMERAS, RigError
from instagram_hdmap.models import build_model

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "configs" / "synthetic" / "tiny.yaml"
# 128 x 352 network images of the world's 400 x 225 JPEGs: a resize by 0.88, so predict decodes them at
# full resolution, as the arrays given to the API are (a resize below 1/2 decodes JPEGs at a reduced
# size: file paths match predict then). A low threshold gives the random model's sharpened graph edges.
SETTINGS = ["data.image_size=[128,352]", "model.gnn.match_threshold=0.02", "model.gnn.num_vertices=128"]


def random_checkpoint(cfg, path: Path, seed: int = 0) -> Path:
    """A random model whose matching embeddings are spread (a sharper assignment: some edges)."""
    torch.manual_seed(seed)
    model = build_model(cfg)
    with torch.no_grad():
        model.graph_head.match_head.weight.mul_(10)
    return save_checkpoint({"model": model.state_dict(), "config": config_to_dict(cfg)}, path)


@pytest.fixture(scope="module")
def world(tiny_world, world_overrides) -> list[str]:
    return [*world_overrides(tiny_world), "data.num_workers=0", "train.device=cpu"]


@pytest.fixture(scope="module")
def cfg(world):
    return load_config(TINY, [*world, *SETTINGS])


@pytest.fixture(scope="module")
def checkpoint(cfg, tmp_path_factory) -> Path:
    return random_checkpoint(cfg, tmp_path_factory.mktemp("ckpt") / "runs" / "demo" / "run" / "last.pt")


@pytest.fixture(scope="module")
def sample(cfg) -> dict:
    """Sample 0 of the val split as plain data: its token, its camera files and sizes, RGB arrays and
    the calibration (numpy, from the nuScenes tables), camera by camera."""
    dataset = build_dataset(cfg, cfg.data.val_split, augment=False)
    nusc, token = dataset.nusc, dataset.sample_tokens[0]
    record = nusc.get("sample", token)
    scene = dataset.scene_of(0)
    out = {"token": token, "files": {}, "sizes": {}, "images": {}, "intrinsics": {}, "cam_to_ego": {},
           "calibrated": {}, "scene": scene, "scene_samples": len(dataset.scene_indices(scene))}
    for cam, (path, size) in zip(CAMERAS, dataset.camera_files(0)):
        cs = nusc.get("calibrated_sensor", nusc.get("sample_data", record["data"][cam])["calibrated_sensor_token"])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Quaternion(cs["rotation"]).rotation_matrix, cs["translation"]
        out["files"][cam], out["sizes"][cam] = path, size
        out["images"][cam] = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        out["intrinsics"][cam], out["cam_to_ego"][cam] = np.array(cs["camera_intrinsic"]), T
        out["calibrated"][cam] = cs
    return out


@pytest.fixture(scope="module")
def predicted(world, checkpoint, sample, tmp_path_factory) -> list[dict]:
    """``predict``'s prediction.json vectors of the sample."""
    out = tmp_path_factory.mktemp("predict")
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["predict", str(TINY), *world, "--checkpoint", str(checkpoint), "--index", "0",
                     "--out", str(out)]) == 0
    return json.loads((out / "prediction.json").read_text())["results"][sample["token"]]


def readme_example() -> str:
    text = (REPO / "README.md").read_text()
    section = text[text.index("## From Python"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


# --- README's example ------------------------------------------------------------------------------------


def test_readme_example_runs_verbatim_on_plain_arrays_and_equals_predict(checkpoint, sample, predicted,
                                                                          monkeypatch):
    code = readme_example()
    code_lines = [line for line in code.splitlines() if line.strip() and not line.startswith("#")]
    shown = [line[2:] for line in code.splitlines() if line.startswith("# MapElement(")]
    assert len(code_lines) == 5 and shown, code
    monkeypatch.chdir(checkpoint.parents[3])  # where runs/demo/run/last.pt is
    names = {"images": sample["images"], "intrinsics": sample["intrinsics"], "cam_to_ego": sample["cam_to_ego"]}
    assert all(isinstance(v, np.ndarray) for field in names.values() for v in field.values())
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, "README.md", "exec"), names)
    elements = names["elements"]
    assert predicted, "the random model decodes no element: the comparison would be empty"
    assert to_hdmapnet({sample["token"]: elements})["results"][sample["token"]] == predicted
    assert len(printed.getvalue().splitlines()) == len(elements)
    form = r"MapElement\((divider|ped_crossing|boundary), \d+ points, (open|closed), score \d\.\d\d\)"
    assert all(re.fullmatch(form, line) for line in [*printed.getvalue().splitlines(), *shown]), printed.getvalue()
    assert all(isinstance(e, MapElement) and e.label in ("divider", "ped_crossing", "boundary") for e in elements)


# --- the API's calls ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mapper(checkpoint) -> Mapper:
    return Mapper.from_checkpoint(checkpoint, device="cpu")


def _as_list(elements: list[MapElement]) -> list[dict]:
    return [e.to_hdmapnet() for e in elements]


def test_frames_of_every_kind_give_the_same_batch_and_elements(mapper, sample):
    """Mappings or camera-ordered lists, numpy / PIL / tensor / float images: the same model input; a
    list of frames gives one element list per frame."""
    from PIL import Image

    frame = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"])
    one = _as_list(mapper(images=sample["images"], intrinsics=sample["intrinsics"], cam_to_ego=sample["cam_to_ego"]))
    in_order = Frame([sample["images"][c] for c in mapper.cameras], [sample["intrinsics"][c] for c in mapper.cameras],
                     [sample["cam_to_ego"][c] for c in mapper.cameras])
    pil = Frame({c: Image.fromarray(a) for c, a in sample["images"].items()}, sample["intrinsics"],
                sample["cam_to_ego"])
    tensors = Frame({c: torch.from_numpy(a).permute(2, 0, 1) for c, a in sample["images"].items()},
                    sample["intrinsics"], sample["cam_to_ego"])
    paths = Frame(sample["files"], sample["intrinsics"], sample["cam_to_ego"])  # full-resolution decode here
    floats = Frame({c: a / 255.0 for c, a in sample["images"].items()}, sample["intrinsics"], sample["cam_to_ego"])
    reference = mapper.batch([frame])
    for other in (in_order, pil, tensors, paths):
        assert all(torch.equal(v, reference[k]) for k, v in mapper.batch([other]).items())
    # float pixels are interpolated without rounding to whole levels: within half a level (0.5 / 255 / std)
    torch.testing.assert_close(mapper.batch([floats])["images"], reference["images"], atol=0.01, rtol=0)
    assert _as_list(mapper([in_order])[0]) == one
    two = mapper([frame, paths])
    assert len(two) == 2 and all(isinstance(e, MapElement) for els in two for e in els)
    assert mapper.cameras == CAMERAS and mapper.batch([frame])["images"].shape == (1, 6, 3, 128, 352)


def test_a_frames_ground_height_reaches_the_model(mapper, sample):
    """Frame.ground_height (default 0: the ego origin on the road) is the batch's ground_height, one per
    frame (the IPM / MLP ground plane); a non-finite one is a RigError."""
    on_road = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"])
    raised = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"], ground_height=-0.38)
    assert mapper.batch([on_road, raised])["ground_height"].tolist() == pytest.approx([0.0, -0.38])
    with pytest.raises(RigError, match="ground_height"):
        mapper.batch([Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"], ground_height=math.nan)])


def test_stream_carries_the_models_memory_and_resets(mapper, sample):
    """A single-frame model runs frame by frame; a model that returns ``out["memory"]`` gets it back
    with the next frame, and ``scene_start`` marks the first frame after a reset."""
    frame = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"])
    stream = mapper.stream()
    assert _as_list(stream.step(frame)) == _as_list(mapper(frame)) and stream.memory is None

    seen = []

    class Temporal(torch.nn.Module):
        def __init__(self, inner):
            super().__init__()
            self.inner = inner

        def forward(self, batch, memory=None):
            seen.append((memory, bool(batch["scene_start"][0])))
            out = self.inner(batch)
            out["memory"] = {"bev": torch.full((1,), float(len(seen)))}
            return out

    temporal = Mapper(Temporal(mapper.model), mapper.config, source="temporal stub").stream()
    for _ in range(3):
        temporal.step(frame)
    temporal.reset()
    temporal.step(frame)
    assert [(None if m is None else float(m["bev"][0]), start) for m, start in seen] == [
        (None, True), (1.0, False), (2.0, False), (None, True)]


def test_a_mapper_with_its_backbone_compiled_maps_as_the_eager_one(checkpoint, sample, mapper):
    """``compile_backbone=True``: the backbone through torch.compile (precision.compile_backbone), the same map."""
    from instagram_hdmap.precision import CompiledBackbone

    fast = Mapper.from_checkpoint(checkpoint, "cpu", compile_backbone=True)
    assert isinstance(fast.model.backbone, CompiledBackbone) and not isinstance(mapper.model.backbone, CompiledBackbone)
    inputs = {k: sample[k] for k in ("images", "intrinsics", "cam_to_ego")}
    got, expected = _as_list(fast(**inputs)), _as_list(mapper(**inputs))
    assert fast.model.backbone.compiled is not None and expected  # it compiled (no fallback to eager), it maps
    assert [(e["type"], len(e["pts"])) for e in got] == [(e["type"], len(e["pts"])) for e in expected]
    for a, b in zip(got, expected):
        np.testing.assert_allclose(a["pts"], b["pts"], atol=1e-3)


def test_decoding_options_and_their_errors(checkpoint, sample):
    loose = Mapper.from_checkpoint(checkpoint, "cpu", match_threshold=0.01, min_vertices=3)
    assert loose.config.model.gnn.match_threshold == 0.01 and loose.decode_options["min_vertices"] == 3
    assert all(len(e.points) >= 3 for e in loose(images=sample["images"], intrinsics=sample["intrinsics"],
                                                 cam_to_ego=sample["cam_to_ego"]))
    with pytest.raises(Exception, match="unknown decoding option.*threshold.*match_threshold"):
        Mapper.from_checkpoint(checkpoint, threshold=0.1)
    with pytest.raises(Exception, match="model.gnn.match_threshold"):
        Mapper.from_checkpoint(checkpoint, match_threshold=2.0)


@pytest.mark.parametrize("case", ["missing", "extra", "count", "intrinsics", "focal", "rotation", "pose"])
def test_bad_frames_name_the_camera_and_the_field(mapper, sample, case):
    images, K, T = dict(sample["images"]), dict(sample["intrinsics"]), dict(sample["cam_to_ego"])
    if case == "missing":
        del images["CAM_BACK"]
        match = r"images.*missing CAM_BACK"
    elif case == "extra":
        images["CAM_ROOF"] = images["CAM_FRONT"]
        match = r"images.*not in the checkpoint's rig: CAM_ROOF"
    elif case == "count":
        images = list(images.values())[:5]
        match = r"5 images for the checkpoint's 6 cameras"
    elif case == "intrinsics":
        K["CAM_FRONT"] = np.eye(3)[:2]
        match = r"camera CAM_FRONT: 'intrinsics' must be 3x3, got 2x3"
    elif case == "focal":
        K["CAM_FRONT"] = np.diag([0.0, 500.0, 1.0])
        match = r"camera CAM_FRONT: 'intrinsics' has a focal length <= 0"
    elif case == "rotation":
        T["CAM_BACK_LEFT"] = np.diag([2.0, 1.0, 1.0, 1.0])
        match = r"camera CAM_BACK_LEFT: 'rotation' is not a rotation matrix"
    else:
        T["CAM_FRONT"] = np.eye(3)
        match = r"camera CAM_FRONT: 'cam_to_ego' must be a 4x4"
    with pytest.raises(RigError, match=match):
        mapper(images=images, intrinsics=K, cam_to_ego=T)


def test_a_checkpoint_of_another_architecture_names_the_keys(cfg, tmp_path, capsys, sample):
    """Weights of a 3-layer GNN under a config that says 2 layers: one line naming the parameters."""
    other = load_config(TINY, [*_world_of(cfg), *SETTINGS, "model.gnn.layers=3"])
    torch.manual_seed(0)
    state = build_model(other).state_dict()
    path = save_checkpoint({"model": state, "config": config_to_dict(cfg)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match=r"do not fit .*not in the model: graph_head\.gnn\.layers\.2\."):
        Mapper.from_checkpoint(path)
    rig = _write_rig(sample, tmp_path / "rig.json")
    assert main(["predict-images", "--checkpoint", str(path), "--rig", str(rig), "--out", str(tmp_path / "o"),
                 *[str(sample["files"][c]) for c in CAMERAS]]) == 2
    assert "graph_head.gnn.layers.2" in _error_line(capsys)


def _world_of(cfg) -> list[str]:
    return [f"data.dataroot={cfg.data.dataroot}", f"data.version={cfg.data.version}",
            f"data.splits_file={cfg.data.splits_file}"]


# --- predict-images and the rig file -----------------------------------------------------------------------


def _write_rig(sample: dict, path: Path, edit=None) -> Path:
    """A rig file of the sample's cameras (CAMERAS order), from its nuScenes calibration records."""
    cameras = {}
    for cam in CAMERAS:
        cs = sample["calibrated"][cam]
        cameras[cam] = {"intrinsics": cs["camera_intrinsic"],
                        "rotation": Quaternion(cs["rotation"]).rotation_matrix.tolist(),
                        "translation": cs["translation"]}
    rig = json.loads(json.dumps({"image_size": list(sample["sizes"]["CAM_FRONT"]), "cameras": cameras}))  # a copy
    if edit is not None:
        edit(rig)
    path.write_text(json.dumps(rig, indent=1))
    return path


def test_predict_images_on_a_rig_file_equals_predict(checkpoint, sample, predicted, tmp_path):
    rig = _write_rig(sample, tmp_path / "rig.json")
    out = tmp_path / "out"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["predict-images", "--checkpoint", str(checkpoint), "--rig", str(rig), "--out", str(out),
                     "--name", sample["token"], *[str(sample["files"][c]) for c in CAMERAS]]) == 0
    assert json.loads((out / "prediction.json").read_text())["results"][sample["token"]] == predicted
    for name in ("prediction_bev.png", "prediction_cameras.png", "prediction_intermediate.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"{len(predicted)} map elements" in printed.getvalue()
    # the same with quaternions and the cameras in another order (the images in the rig file's order)

    def quaternions_reversed(rig):
        for name, cam in rig["cameras"].items():
            cam["quaternion"] = sample["calibrated"][name]["rotation"]
            del cam["rotation"]
        rig["cameras"] = dict(reversed(list(rig["cameras"].items())))

    rig_q = _write_rig(sample, tmp_path / "rig_q.json", quaternions_reversed)
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["predict-images", "--checkpoint", str(checkpoint), "--rig", str(rig_q), "--out",
                     str(tmp_path / "q"), "--name", sample["token"],
                     *[str(sample["files"][c]) for c in reversed(CAMERAS)]]) == 0
    assert json.loads((tmp_path / "q" / "prediction.json").read_text())["results"][sample["token"]] == predicted


def _rename(rig, old, new):
    rig["cameras"] = {new if k == old else k: v for k, v in rig["cameras"].items()}


@pytest.mark.parametrize("case", ["unknown", "missing", "intrinsics", "focal", "rotation", "size", "count",
                                  "undecodable", "field"])
def test_bad_rig_files_and_images_are_one_line_naming_camera_and_field(checkpoint, sample, tmp_path, capsys, case):
    images = [str(sample["files"][c]) for c in CAMERAS]
    edit, expect = None, []
    if case == "unknown":
        def edit(r):
            _rename(r, "CAM_BACK", "CAM_REAR")
        expect = ["CAM_REAR", "CAM_BACK", "missing", "unknown"]
    elif case == "missing":
        def edit(r):
            del r["cameras"]["CAM_FRONT_RIGHT"]
        images = images[:5]
        expect = ["missing CAM_FRONT_RIGHT"]
    elif case == "intrinsics":
        def edit(r):
            r["cameras"]["CAM_FRONT"]["intrinsics"] = [[1.0, 0.0], [0.0, 1.0]]
        expect = ["camera CAM_FRONT", "'intrinsics' must be 3x3"]
    elif case == "focal":
        def edit(r):
            r["cameras"]["CAM_BACK"]["intrinsics"][0][0] = -5.0
        expect = ["camera CAM_BACK", "'intrinsics' has a focal length <= 0"]
    elif case == "rotation":
        def edit(r):
            r["cameras"]["CAM_BACK_RIGHT"]["rotation"] = [[1, 0, 0], [0, 1, 0], [0, 0.5, 1]]
        expect = ["camera CAM_BACK_RIGHT", "'rotation' is not a rotation matrix"]
    elif case == "size":
        def edit(r):
            r["cameras"]["CAM_FRONT_LEFT"]["image_size"] = [1600, 900]
        expect = ["camera CAM_FRONT_LEFT", "'image_size' is 1600x900", "400x225"]
    elif case == "count":
        images = images[:4]
        expect = ["4 image(s) for the 6 cameras"]
    elif case == "undecodable":
        bad = tmp_path / "broken.jpg"
        bad.write_bytes(b"not an image at all")
        images[2] = str(bad)
        expect = [f"camera {CAMERAS[2]}", "broken.jpg"]
    else:
        def edit(r):
            r["cameras"]["CAM_FRONT"]["translation_m"] = r["cameras"]["CAM_FRONT"].pop("translation")
        expect = ["camera CAM_FRONT", "translation"]
    rig = _write_rig(sample, tmp_path / "rig.json", edit)
    assert main(["predict-images", "--checkpoint", str(checkpoint), "--rig", str(rig), "--out", str(tmp_path / "o"),
                 *images]) == 2
    line = _error_line(capsys)
    assert all(e in line for e in expect), line
    assert not (tmp_path / "o" / "prediction.json").exists()


# --- a scene as a video ------------------------------------------------------------------------------------


def test_video_has_one_frame_per_sample_of_the_scene(world, sample, tmp_path, capsys):
    cfg = load_config(TINY, world)
    ckpt = random_checkpoint(cfg, tmp_path / "tiny.pt")
    video = tmp_path / "scene.mp4"
    assert main(["predict", str(TINY), *world, "--checkpoint", str(ckpt), "--scene", sample["scene"],
                 "--video", str(video)]) == 0
    assert f"{sample['scene_samples']} frames" in capsys.readouterr().out
    capture = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == sample["scene_samples"] >= 2
    assert frames[0].shape[0] > 200 and frames[0].shape[1] > frames[0].shape[0]
    # the predictions beside it, each element with its track ID; no temporary file left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.json", "scene.mp4", "tiny.pt"]
    from instagram_hdmap.evaluation.io import read_submission

    tracked = read_submission(tmp_path / "scene.json", "pred", 3).samples
    assert len(tracked) == sample["scene_samples"]
    assert all(isinstance(p["track_id"], int) for polys in tracked.values() for p in polys)
    assert main(["predict", str(TINY), *world, "--checkpoint", str(ckpt), "--scene", "scene-9999",
                 "--video", str(tmp_path / "x.mp4")]) == 2
    assert "scene 'scene-9999' is not in split" in _error_line(capsys)
    assert main(["predict", str(TINY), *world, "--checkpoint", str(ckpt), "--scene", sample["scene"],
                 "--out", str(tmp_path)]) == 2
    assert "--video OUT.mp4" in _error_line(capsys)


# --- ONNX through the same class ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def exported(world, tmp_path_factory):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    cfg = load_config(TINY, [*world, *SETTINGS, "model.gnn.sinkhorn_iters=5"])
    folder = tmp_path_factory.mktemp("onnx")
    ckpt = random_checkpoint(cfg, folder / "fast.pt")
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["export-onnx", str(TINY), *world, *SETTINGS, "model.gnn.sinkhorn_iters=5", "--checkpoint",
                     str(ckpt), "--out", str(folder / "m.onnx")]) == 0
    return ckpt, folder / "m.onnx"


def test_onnx_runs_through_the_same_class_and_checks_its_config(exported, sample):
    ckpt, path = exported
    frame = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"])
    onnx = Mapper.from_onnx(path)  # the config stamped in the export: rig, image fit, decoding
    torch_mapper = Mapper.from_checkpoint(ckpt, "cpu")
    assert onnx.cameras == torch_mapper.cameras and onnx.decode_options == torch_mapper.decode_options

    def rounded(elements):
        return sorted((e.label, e.closed, tuple(np.round(e.points, 3).ravel().tolist())) for e in elements)

    assert rounded(onnx(frame)) == rounded(torch_mapper(frame))
    assert Mapper.from_onnx(path, decoder="mutual").config.model.gnn.decoder == "mutual"
    with pytest.raises(Exception, match=r"exported from another config: model\.gnn\.layers=2 \(CONFIG: 3\)"):
        Mapper.from_onnx(path, overrides=["model.gnn.layers=3"])


def test_the_readme_rig_example_reads(tmp_path):
    """The example rig of docs/guide.md is valid JSON once its ellipses are filled in."""
    text = (REPO / "docs" / "guide.md").read_text()
    block = re.search(r"```json\n(.*?)```", text[text.index("## Your own cameras"):], re.S).group(1)
    first = block.split('"CAM_FRONT":')[0].rstrip().rstrip(",") + "}}"
    data = json.loads(first)
    from instagram_hdmap.data.rig import read_rig_file

    (tmp_path / "rig.json").write_text(json.dumps(data))
    (cam,) = read_rig_file(tmp_path / "rig.json")
    assert cam.name == "CAM_FRONT_LEFT" and cam.image_size == (1600, 900)


def test_a_misspelt_frame_field_lists_every_field():
    """mapper(images=..., intrinsic=...): the message lists every field of a Frame, the optional ones too (ego_pose,
    which a temporal model needs, among them)."""
    import dataclasses

    with pytest.raises(TypeError) as info:
        Mapper._frame({"images": [], "intrinsic": []})
    message = str(info.value)
    assert all(f.name in message for f in dataclasses.fields(Frame)), message
    assert "got ['images', 'intrinsic']" in message


def test_stream_keeps_an_element_the_model_misses_with_persistence(checkpoint, sample, monkeypatch):
    """model.temporal.persist_frames: MapStream.step keeps an element of the previous frame that this one's output
    misses, moved by the ego motion between the frames' poses and with its score decayed; reset() forgets it;
    a frame without an ego pose is named (the kept elements move with the ego)."""
    import instagram_hdmap.mapper as mapper_module

    mapper = Mapper.from_checkpoint(checkpoint, overrides=["model.temporal.persist_frames=1",
                                                           "model.temporal.persist_decay=0.5"])
    line = {"pts": np.array([[1.0, 2.0], [5.0, 2.0]], np.float32), "label": 0, "closed": False, "score": 0.8}
    outputs = iter([[[line]], [[]], [[line]], [[]]])
    monkeypatch.setattr(mapper_module, "postprocess_batch", lambda *a, **k: next(outputs))
    at = np.eye(4)
    moved = np.eye(4)
    moved[:3, 3] = [2.0, 0.0, 0.0]  # the ego drove 2 m forward
    frame = Frame(sample["images"], sample["intrinsics"], sample["cam_to_ego"])
    stream = mapper.stream()
    with pytest.raises(RigError, match="persist_frames moves the elements it keeps with the ego"):
        stream.step(frame)
    assert len(stream.step(dataclasses.replace(frame, ego_pose=at))) == 1
    (kept,) = stream.step(dataclasses.replace(frame, ego_pose=moved))
    np.testing.assert_allclose(kept.points, [[-1.0, 2.0], [3.0, 2.0]], atol=1e-5)  # inside the tiny grid
    assert kept.score == pytest.approx(0.4) and kept.label == "divider"
    stream.reset()
    assert len(stream.step(dataclasses.replace(frame, ego_pose=at))) == 1
    stream.reset()
    assert stream.step(dataclasses.replace(frame, ego_pose=moved)) == []  # a new scene: nothing remembered
