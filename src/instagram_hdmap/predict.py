"""Pictures of trained models: one sample's pictures (``predict``), a scene as a video
(``predict --scene --video``) and one frame of your own cameras (``predict-images``); a split's AP
(``evaluate``) is evaluate_split.py, on the same loading.

    predict_sample(cfg, "out/", checkpoint="runs/x/best.pt", index=3)   # PNGs + prediction.json
    predict_video(cfg, "scene.mp4", "scene-0103", checkpoint="runs/x/best.pt")   # one frame per sample
    predict_images("rig.json", ["front.jpg", ...], "out/", checkpoint="runs/x/best.pt")

Which config a checkpoint runs with: ``inference.inference_config`` (the ``MODEL_KEYS`` from the config saved in
the checkpoint, everything else, dataroot, splits, eval settings, from the CONFIG file; a note where they disagree).
Command-line ``key=value`` overrides win over both, so ``model.gnn.num_vertices=600`` or
``model.gnn.match_threshold=0.2`` change the inference of a trained model.

``--gt-as-prediction`` draws ``inference.gt_outputs``, what a perfect model would output, so the
pictures and the evaluation path can be checked without a trained model.

Predictions are written in HDMapNet's submission format: ``{"meta": {...}, "results":
{sample_token: [{"pts": [[x, y], ...], "pts_num", "type", "confidence_level"}]}}`` (metres, ego
frame, x forward, y left; a closed shape repeats its first point).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from .config import ExperimentConfig, UserError, parse_overrides
from .data import build_dataset
from .data.base import collate_fn
from .data.rig import CameraCalibration, RigError, camera_named_by, read_rig_file
from .data.transforms import ImageError, load_image, read_image
from .engine import is_temporal
from .evaluation import write_submission
from .files import OutputError, atomic_path, check_output_dir, check_output_file
from .geometry import BEVGrid
from .inference import OnnxModel, gt_outputs, load_model, run_model
from .mapper import Frame, Mapper, image_size_of
from .persistence import Persistence, stream_tracker
from .postprocess import decode_options, graph_options, neighbours, postprocess_batch
from .visualize import figure_rgb, intermediate_figure, prediction_bev_figure, prediction_cameras_figure, save_figure


class PredictError(UserError):
    """A bad sample index or token, or a bad combination of arguments."""


# --- submission format --------------------------------------------------------------------------------


def submission_meta(cfg: ExperimentConfig, split: str, source: str) -> dict:
    g = cfg.grid
    return {
        "use_camera": True, "use_lidar": False, "use_radar": False, "use_external": False, "vector": True,
        "ground_truth": False, "source": source, "config_name": cfg.name, "dataset": cfg.data.dataset,
        "version": cfg.data.version, "split": split, "frame": "ego, x forward, y left, metres",
        "classes": list(cfg.data.classes), "xbound": list(g.xbound), "ybound": list(g.ybound),
        "resolution": g.resolution,
    }


# --- one sample: predict -------------------------------------------------------------------------------


def find_sample(dataset, index: int | None = None, token: str | None = None) -> int:
    """The dataset index of ``token``, or ``index`` checked against the split (negative counts back)."""
    n = len(dataset)
    if token is not None:
        try:
            return dataset.sample_tokens.index(token)
        except ValueError:
            raise PredictError(
                f"sample token '{token}' is not in split '{dataset.split}' of {dataset.dataroot} ({n} samples, "
                f"e.g. '{dataset.sample_tokens[0]}'); pass --split to look in another split, or use --index"
            ) from None
    if index is None:
        raise PredictError("pass --index I or --token T to choose the sample")
    if not -n <= index < n:
        raise PredictError(f"--index {index} is out of range: split '{dataset.split}' of {dataset.dataroot} "
                           f"has {n} samples (0..{n - 1})")
    return index % n


def display_images(files: Sequence[tuple[Path, tuple[int, int]]], width: int = 480) -> dict[str, torch.Tensor]:
    """Camera images ``[(path, (W, H))]`` (a sample's: ``dataset.camera_files(index)``), whole, resized to ``width``
    for drawing: ``images`` [V, 3, h, w] (normalised) with their ``post_rot`` [V, 3, 3] / ``post_tran`` [V, 3]."""
    # one picture size for all cameras, of the median aspect ratio; cameras of another one fit inside
    # (AV2's portrait front camera)
    aspects = sorted(H / W for _, (W, H) in files)
    w = min(width, max(W for _, (W, _) in files))
    out_hw = (round(w * aspects[len(aspects) // 2]), w)
    fit = "cover" if aspects[0] == aspects[-1] else "contain"
    loaded = [load_image(path, (W, H), out_hw, fit=fit) for path, (W, H) in files]  # (image, post_rot, post_tran)
    return {k: torch.stack(v) for k, v in zip(("images", "post_rot", "post_tran"), zip(*loaded))}


def adjacency_edges(log_assignment: torch.Tensor, mask: torch.Tensor, match_threshold: float,
                    neighbours: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges for the adjacency picture of one sample.

    log_assignment [N+1, N+1], mask [N] bool, neighbours [N, W] (``postprocess.neighbours``, its graphs
    side by side; -1 for none).
    Returns ``edges`` [E, 2] (indices into the *real* vertices, i < j) of the pairs whose assignment
    probability exceeds ``match_threshold`` in either direction, and ``kept`` [E] bool: the edge is one
    the post-processing follows.
    """
    real = torch.nonzero(mask.bool()).flatten()
    n = len(real)
    device = log_assignment.device
    upper = torch.ones(n, n, dtype=torch.bool, device=device).triu(1)
    probs = log_assignment[real][:, real].float().exp()  # [n, n]
    above = (probs > match_threshold) | (probs > match_threshold).T
    pos = torch.full((mask.shape[0] + 1,), -1, dtype=torch.long, device=device)  # vertex -> real index
    pos[real] = torch.arange(n, device=device)
    nbr = pos[neighbours[real]]  # [n, W]; -1 stays -1 (pos[-1] is the unused last slot)
    followed = torch.zeros(n, n, dtype=torch.bool, device=device)
    ok = nbr >= 0
    followed[torch.arange(n, device=device)[:, None].expand_as(nbr)[ok], nbr[ok]] = True
    followed = followed | followed.T
    i, j = torch.nonzero((above | followed) & upper, as_tuple=True)
    edges = torch.stack([i, j], 1)
    return edges.cpu().numpy(), followed[i, j].cpu().numpy()


def camera_dropout_notes(cfg: ExperimentConfig, what: str) -> list[str]:
    """A note when ``data.camera_dropout`` > 0 (a training config's setting, easily inherited unseen) blanks the
    split's camera images: ``what`` (the AP, the predictions) is not that of the full images."""
    if cfg.data.camera_dropout <= 0:
        return []
    return [f"data.camera_dropout={cfg.data.camera_dropout:g}: each camera image of the split is blanked in "
            f"{cfg.data.camera_dropout:.0%} of the frames (a fixed draw), so these are not {what} of the full "
            "images; set data.camera_dropout=0 for those"]


def decode_assignments(items: list[str]) -> dict:
    """``--decode name=value`` -> {name: value} (values read as YAML, as config overrides are)."""
    options = {}
    for item in items:
        if "=" not in item:
            raise UserError(f"--decode {item}: expected NAME=VALUE, e.g. match_threshold=0.05")
        name, _, value = item.partition("=")
        options[name.strip()] = parse_overrides([f"value={value}"])["value"]
    return options


def _check_onnx_precision(precision: str, compile_backbone: bool = False) -> None:
    """An --onnx export is a float32 graph run by onnxruntime: a lower --precision or --compile-backbone with it
    would be dropped with no word."""
    if precision in ("bf16", "int8"):
        raise PredictError(f"--precision {precision} runs a checkpoint; an --onnx export runs in float32 in "
                           "onnxruntime")
    if compile_backbone:
        raise PredictError("--compile-backbone compiles a checkpoint's backbone with torch.compile; an --onnx export "
                           "runs in onnxruntime: drop one of them")


def load_predictor(cfg: ExperimentConfig, *, checkpoint: str | Path | None = None, onnx: str | Path | None = None,
                   gt_as_prediction: bool = False, overrides: Sequence[str] = (), precision: str = "fp32",
                   compile_backbone: bool = False):
    """``(model, config, notes, source)`` of ``predict``'s choice of predictor: a checkpoint (in ``precision``,
    precision.py; ``compile_backbone``: its image backbone through ``torch.compile``), an ``export-onnx`` file
    (onnxruntime; its baked config must be ``cfg``'s) or, with ``gt_as_prediction``, None (``inference.gt_outputs``:
    predictions built from the GT). The notes say where its predictions are not those of the full images or of the
    config's persistence."""
    if gt_as_prediction and checkpoint is not None:
        raise PredictError("--gt-as-prediction draws predictions built from the GT and loads no model; "
                           "drop --checkpoint (or drop --gt-as-prediction to run the checkpoint)")
    if gt_as_prediction and compile_backbone:
        raise PredictError("--compile-backbone compiles a checkpoint's image backbone; --gt-as-prediction loads no "
                           "model: drop --compile-backbone")
    if sum(x is not None for x in (checkpoint, onnx)) + gt_as_prediction != 1:
        raise PredictError("pass one of --checkpoint CKPT, --onnx FILE (an export-onnx file) or --gt-as-prediction "
                           "(GT-derived predictions)")
    if onnx is not None:
        _check_onnx_precision(precision, compile_backbone)
        model, notes, source = OnnxModel(onnx, cfg), [], f"ONNX {onnx} (onnxruntime)"
    elif checkpoint is not None:
        model, cfg, notes = load_model(checkpoint, cfg, overrides, precision=precision,
                                       compile_backbone=compile_backbone)
        source = f"checkpoint {checkpoint}"
    else:
        model, notes, source = None, [], "GT-derived predictions (--gt-as-prediction)"
    notes += camera_dropout_notes(cfg, "the predictions")
    if gt_as_prediction and cfg.model.temporal.persist_frames:  # it was dropped with no word
        notes.append(f"model.temporal.persist_frames={cfg.model.temporal.persist_frames} is not applied to "
                     "--gt-as-prediction: the GT misses no element, so there is nothing to keep (persistence.py)")
    return model, cfg, notes, source


def predict_batch(model, batch: dict, cfg: ExperimentConfig, memory: dict | None = None
                  ) -> tuple[dict[str, torch.Tensor], list[list[dict]]]:
    """``(outputs, predictions)`` of ``model`` (``load_predictor``'s; None: ``gt_outputs``) on ``batch``."""
    grid = BEVGrid.from_config(cfg.grid)
    if model is None:
        outputs = gt_outputs(batch, grid, len(cfg.data.classes))
    else:
        outputs = run_model(model, batch, memory)
    return outputs, postprocess_batch(outputs, grid, **decode_options(cfg.model.gnn, grid))


def prediction_figures(outputs: dict, predictions: list[dict], ground_truth: list[dict] | None, display: dict,
                       calibration: dict, cfg: ExperimentConfig, heading: str, camera_names: Sequence[str],
                       ground_z: float = 0.0) -> dict:
    """``predict``'s three pictures of one sample (batch of one ``outputs``): ``prediction_bev.png``,
    ``prediction_cameras.png`` (``display`` images, ``calibration``: intrinsics and cam_to_ego_* [V, ...];
    the map drawn on the ground plane z = ``ground_z`` of the ego frame, the sample's ``ground_height``)
    and ``prediction_intermediate.png``; ``ground_truth`` None: your own images, no GT."""
    grid, classes = BEVGrid.from_config(cfg.grid), cfg.data.classes
    decode = decode_options(cfg.model.gnn, grid)
    threshold = decode["match_threshold"]
    mask = outputs["pred_vertex_mask"][0]
    graphs = neighbours(outputs, **graph_options(decode))[0]  # [G, N, 2], batch of one
    nbr = graphs.permute(1, 0, 2).reshape(graphs.shape[1], -1)  # [N, 2G]: a vertex's neighbours in any graph
    edges, kept = adjacency_edges(outputs["pred_log_assignment"][0], mask, threshold, nbr)
    return {
        "prediction_bev.png": prediction_bev_figure(predictions, ground_truth, grid, classes, heading),
        "prediction_cameras.png": prediction_cameras_figure(
            **display, **calibration, predictions=predictions, ground_truth=ground_truth or (),
            camera_names=camera_names, classes=classes, ground_z=ground_z),
        "prediction_intermediate.png": intermediate_figure(
            outputs["pred_heatmap"][0], outputs["pred_distance"][0] if "pred_distance" in outputs else None,
            outputs["pred_vertices_px"][0][mask],
            outputs["pred_class_log_probs"][0][mask].argmax(-1), edges, kept, grid, classes, cfg.data.dt_clip,
            f"{heading}; match threshold {threshold}"),
    }


def write_together(out: Path, figures: dict, predictions: dict, meta: dict) -> list[Path]:
    """``predict``'s pictures and ``out/prediction.json``, written to temporaries and renamed together at the
    end: a kill or a full disk part-way leaves the folder's earlier set whole (written one by one, a set over
    an earlier ``predict`` of another sample mixed both samples' pictures and the other's prediction.json)."""
    names = [*figures, "prediction.json"]
    with contextlib.ExitStack() as stack:
        tmp = {n: stack.enter_context(atomic_path(out / n, keep_suffix=n != "prediction.json")) for n in names}
        for name, fig in figures.items():
            save_figure(fig, tmp[name])
        write_submission(tmp["prediction.json"], predictions, meta)
    return [out / n for n in names]


def predict_sample(cfg: ExperimentConfig, out: str | Path, *, checkpoint: str | Path | None = None,
                   index: int | None = None, token: str | None = None, split: str | None = None,
                   overrides: Sequence[str] = (), gt_as_prediction: bool = False, camera_width: int = 480,
                   onnx: str | Path | None = None, precision: str = "fp32", compile_backbone: bool = False) -> dict:
    """Run the model (or ``gt_outputs``) on one sample and write, in ``out``:

    * ``prediction_bev.png``: predicted polylines next to the GT (x forward up, y left, metres);
    * ``prediction_cameras.png``: the six original camera images with the predictions (and, dashed,
      the GT) projected from the sample's ground plane (``ground_height``: z = 0 of the ego frame on
      nuScenes, the road below AV2's rear axle);
    * ``prediction_intermediate.png``: the paper's Fig. 6 (vertex heatmap, distance transform per
      class, vertices by GNN class, adjacency edges);
    * ``prediction.json``: the sample's predictions in the submission format.

    ``onnx``: an ``export-onnx`` file run by onnxruntime instead of a checkpoint (``inference.OnnxModel``:
    its baked config must be ``cfg``'s); its outputs go through the same post-processing and pictures.

    Returns ``{"sample_token", "index", "split", "predictions", "paths", "notes"}``.
    """
    check_output_dir(out, "--out")  # before the model runs
    model, cfg, notes, source = load_predictor(cfg, checkpoint=checkpoint, onnx=onnx, gt_as_prediction=gt_as_prediction,
                                               overrides=overrides, precision=precision,
                                               compile_backbone=compile_backbone)
    split = split or cfg.data.val_split
    dataset = build_dataset(cfg, split, augment=False)
    i = find_sample(dataset, index, token)
    sample = dataset.load_sample(i)
    persist = Persistence.from_config(cfg) if model is not None else None
    memory, walked = (walk_scene(model, dataset, i, persist, cfg) if is_temporal(model) or persist is not None
                      else (None, 0))
    if is_temporal(model):
        scene = dataset.scene_of(i)
        before = dataset.scene_indices(scene).index(i)
        if before and walked == 0:
            notes.append(f"a temporal model: no memory, as the frame before it in scene {scene} is bad "
                         "(data.on_bad_sample=skip)")
        elif before and walked < before:
            notes.append(f"a temporal model: its memory comes from the {walked} frame(s) of scene {scene} after its "
                         "last bad frame (data.on_bad_sample=skip), walked in order")
        else:
            notes.append(f"a temporal model: its memory comes from the {before} earlier frame(s) of scene {scene}, "
                         "walked in order" if before else
                         f"a temporal model: the first frame of scene {scene}, so no memory (as a single-frame model)")
    outputs, (preds,) = predict_batch(model, collate_fn([sample]), cfg, memory)
    if persist is not None:
        walked_kept = persist.kept
        preds = persist.step(preds, dataset.scene_of(i), int(dataset.scenes.frame[i]), sample["ego_pose"])
        notes.append(f"model.temporal.persist_frames={cfg.model.temporal.persist_frames}: "
                     f"{persist.kept - walked_kept} element(s) that the frames before it found and it missed are "
                     "kept (persistence.py)")
    heading = f"sample {sample['sample_token']} (split '{split}', index {i}) - {source}"
    display = display_images(dataset.camera_files(i), camera_width)
    figures = prediction_figures(outputs, preds, sample["gt_polylines"], display,
                                 {k: sample[k] for k in ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans")}, cfg,
                                 heading, dataset.camera_names, float(sample["ground_height"]))
    paths = write_together(Path(out), figures, {sample["sample_token"]: preds}, submission_meta(cfg, split, source))
    return {"sample_token": sample["sample_token"], "index": i, "split": split, "predictions": preds,
            "paths": paths, "notes": notes}


def scene_memory(model, dataset, index: int) -> dict | None:
    """A temporal model's memory just before sample ``index``: its scene walked in order from the first
    frame up to the sample (the memory a streaming evaluation gives it; None at a scene's first frame)."""
    return walk_scene(model, dataset, index)[0]


def walk_scene(model, dataset, index: int, persist: Persistence | None = None,
               cfg: ExperimentConfig | None = None) -> tuple[dict | None, int]:
    """``scene_memory`` and how many frames it was walked over: fewer after a bad frame, which with
    ``data.on_bad_sample=skip`` is a missing one (the memory starts anew after it). With ``persist`` (and
    ``cfg``), each walked frame is also decoded into it, so that the sample's output keeps what the frames
    before it found (any model, a single-frame one too)."""
    run = dataset.scene_indices(dataset.scene_of(index))
    temporal = is_temporal(model)
    memory, walked = None, 0
    for j in run[: run.index(index)]:
        sample = load_or_skip(dataset, j)
        if sample is None:
            memory, walked = None, 0
            continue
        batch = collate_fn([sample])
        if persist is not None:
            outputs, (preds,) = predict_batch(model, batch, cfg, memory)
            persist.step(preds, dataset.scene_of(j), int(dataset.scenes.frame[j]), sample["ego_pose"])
        else:
            outputs = run_model(model, batch, memory)
        memory, walked = (outputs["memory"] if temporal else None), walked + 1
    return memory, walked


def load_or_skip(dataset, index: int) -> dict | None:
    """``dataset.load_sample(index)``; with ``data.on_bad_sample=skip``, None for a bad sample (with the
    dataset's warning) instead of its error."""
    try:
        return dataset.load_sample(index)
    except UserError as e:
        if dataset.data_cfg.on_bad_sample != "skip":
            raise
        warnings.warn(f"skipping a bad sample (data.on_bad_sample=skip): {e}", stacklevel=2)
        return None


# --- your own images: predict-images ------------------------------------------------------------------


def _blank_image(path: str | Path) -> bool:
    """Whether ``path`` decodes to one colour (a failed camera's frame); False when it does not decode (named
    where it is read)."""
    try:
        image, _ = read_image(path)
    except (ImageError, OSError):
        return False
    return bool((image == image.reshape(-1, image.shape[-1])[0]).all())


def rig_frame(rig: Sequence[CameraCalibration], images: Sequence[str | Path], rig_file: str | Path,
              cameras: Sequence[str]) -> Frame:
    """The ``Frame`` of ``images`` (one file per camera of a rig file, in its order), checked: the rig's
    cameras against the model's (``cameras``), the number of images, each image's size against the
    camera's ``image_size``. Errors are one ``RigError`` line naming the camera and the field."""
    names = [c.name for c in rig]
    missing, extra = [c for c in cameras if c not in names], [n for n in names if n not in cameras]
    if missing or extra:
        parts = ([f"missing {', '.join(missing)}"] if missing else []) + (
            [f"unknown to the model: {', '.join(extra)}"] if extra else [])
        raise RigError(f"rig file {rig_file}: its cameras do not match the model's ({', '.join(cameras)}): "
                       + "; ".join(parts))
    folders = [str(p) for p in images if os.path.isdir(p)]
    if folders:  # was "1 image(s) for the 6 cameras": the folder counted as one image
        raise RigError(f"{folders[0]} is a folder: give the image files themselves, one per camera of rig file "
                       f"{rig_file}, in its order ({', '.join(names)}), e.g. {os.path.join(folders[0], names[0])}.jpg "
                       "...")
    if len(images) != len(rig):
        raise RigError(f"{len(images)} image(s) for the {len(rig)} cameras of rig file {rig_file} "
                       f"({', '.join(names)}): give one image per camera, in the rig file's order")
    firsts: dict[str, tuple[str, str]] = {}  # by content: the same file, a link or a byte-identical copy
    for cam, path in zip(rig, images):
        if os.path.exists(path) and not os.path.isfile(path):  # was "cannot be read as an image": the check below
            raise RigError(f"camera {cam.name}: image {path} is a pipe or a device, not a file (a process "  # read it
                           "substitution <(...)): an image is read more than once (checks, then the decoding); "
                           "save it to a file first")
        # one image for two cameras is a mistake, except a blank frame: the cameras that failed
        # (data.camera_dropout's case) may all be given one black image
        with contextlib.suppress(OSError):  # an unreadable file is named where it is decoded
            first = firsts.setdefault(hashlib.sha1(Path(path).read_bytes()).hexdigest(), (cam.name, str(path)))
            if first[0] != cam.name and not _blank_image(path):
                same = os.path.realpath(path) == os.path.realpath(first[1])
                raise RigError(f"cameras {first[0]} and {cam.name} are given the same image"
                               + (f" {path}" if same else f": {path} is a copy of {first[1]} (the same bytes)")
                               + "; give each camera its own image, in the rig file's order (a blank image may stand "
                               "for several failed cameras)")
        named = camera_named_by(path, names)
        if named is not None and named != cam.name:  # images given in another order than the rig file's cameras
            raise RigError(f"image {path} is named for camera {named} but is given for camera {cam.name}: give the "
                           f"images in the rig file's order ({', '.join(names)})")
        size = image_size_of(path, cam.name)
        if tuple(size) != tuple(cam.image_size):
            raise RigError(f"rig file {rig_file}: camera {cam.name}: 'image_size' is {cam.image_size[0]}x"
                           f"{cam.image_size[1]} but its image {path} is {size[0]}x{size[1]}")
    pose = {c.name: np.vstack([np.c_[c.rotation, c.translation], [0, 0, 0, 1]]) for c in rig}
    return Frame(images=dict(zip(names, images)), intrinsics={c.name: c.intrinsics for c in rig}, cam_to_ego=pose,
                 ground_height=getattr(rig, "ground_height", 0.0))


def predict_images(rig_file: str | Path, images: Sequence[str | Path], out: str | Path, *,
                   checkpoint: str | Path | None = None, onnx: str | Path | None = None,
                   config: str | Path | None = None, decode: Mapping | None = None, device: str | None = None,
                   name: str = "frame", camera_width: int = 480, precision: str = "fp32",
                   compile_backbone: bool = False) -> dict:
    """``predict-images``: the model (a checkpoint, or an ``export-onnx`` file with the ``config`` it was
    exported from, default: the one stamped in it) on one frame of your own cameras, described by a
    rig file (``data.rig.read_rig_file``), and ``predict``'s pictures (no GT) and ``prediction.json``
    (the frame under ``name``) in ``out``. ``decode``: decoding options (``inference.DECODE_OPTIONS``).
    Returns ``{"name", "elements", "paths", "source", "notes"}``."""
    if (checkpoint is None) == (onnx is None):
        raise PredictError("pass --checkpoint CKPT or --onnx FILE (one of them)")
    if checkpoint is not None and config is not None:
        raise PredictError("--config goes with --onnx (the config an export was made from); a checkpoint carries "
                           "its own config: drop --config")
    if not str(name).strip():  # `--name "$TOKEN"` of an unset variable: the frame was written under the key ""
        raise PredictError(f"--name {name!r} is empty: give the frame's name in prediction.json (e.g. its sample "
                           "token), or leave --name out for 'frame'")
    check_output_dir(out, "--out")  # before the model runs
    decode = dict(decode or {})
    if onnx is not None:
        _check_onnx_precision(precision, compile_backbone)
    with warnings.catch_warnings():  # its precision note comes back in the result's notes
        warnings.simplefilter("ignore")
        mapper = (Mapper.from_checkpoint(checkpoint, device, precision=precision, compile_backbone=compile_backbone,
                                         **decode) if checkpoint is not None
                  else Mapper.from_onnx(onnx, config, **decode))
    rig = read_rig_file(rig_file)
    frame = rig_frame(rig, images, rig_file, mapper.cameras)
    batch = mapper.batch([frame])
    outputs = mapper.forward(batch)
    (elements,) = mapper.decode(outputs)
    preds = [e.as_polyline() for e in elements]
    size = {c.name: c.image_size for c in rig}
    display = display_images([(Path(frame.images[c]), size[c]) for c in mapper.cameras], camera_width)  # model order
    figures = prediction_figures(outputs, preds, None, display,
                                 {k: batch[k][0] for k in ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans")},
                                 mapper.config, f"{name} - {mapper.source}", mapper.cameras,
                                 ground_z=float(frame.ground_height))  # the elements drawn on the rig's road
    meta = {**submission_meta(mapper.config, "", mapper.source), "rig": str(rig_file),
            "images": [str(p) for p in images]}
    paths = write_together(Path(out), figures, {name: preds}, meta)
    notes = list(mapper.notes)
    if mapper.config.model.temporal.memory != "none":  # as predict says for a scene's first frame
        notes.append(f"a temporal model ({mapper.config.model.temporal.memory} memory) on one frame: no memory, as on "
                     "a drive's first frame (a single-frame model's prediction; the Python API's mapper.stream() "
                     "carries the memory from frame to frame)")
    if mapper.config.data.dataset == "av2" and getattr(rig, "ground_height", 0.0) == 0.0:
        # AV2's ego origin (the rear axle) is 0.33-0.43 m above the road, the frame the model was trained in
        notes.append(f"the model was trained on AV2 (ego origin on the rear axle, the road about 0.38 m below it) and "
                     f"rig file {rig_file} gives no 'ground_height': the road is taken at z = 0 of the rig's ego "
                     "frame; if its translations are AV2's (rear-axle origin), add \"ground_height\": -0.38")
    return {"name": name, "elements": elements, "paths": paths, "source": mapper.source, "notes": notes}


# --- a scene as a video: predict --scene --video -------------------------------------------------------


def _side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Two RGB pictures next to each other, the right one scaled to the left one's height, padded to
    even sizes (what video encoders want)."""
    h = left.shape[0]
    right = cv2.resize(right, (max(1, round(right.shape[1] * h / right.shape[0])), h), interpolation=cv2.INTER_AREA)
    frame = np.concatenate([left, right], axis=1)
    return np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)), constant_values=255)


MAX_VIDEO_FPS = 1000.0


def _check_video(tmp: Path, video: Path) -> None:
    """OpenCV's writer reports no failed write (a full disk): check that the finished file is whole
    (its top-level MP4 boxes fill it exactly and include the index, ``moov``) before it replaces
    ``video``."""
    data = tmp.read_bytes() if tmp.is_file() else b""
    pos, boxes = 0, set()
    while pos + 8 <= len(data):
        size, kind = int.from_bytes(data[pos:pos + 4], "big"), data[pos + 4:pos + 8]
        if size == 1 and pos + 16 <= len(data):  # a 64-bit size follows the type
            size = int.from_bytes(data[pos + 8:pos + 16], "big")
        if size < 8:
            break
        boxes.add(kind)
        pos += size
    if pos != len(data) or b"moov" not in boxes or not data:
        raise OutputError(f"cannot write --video {video}: the MP4 file OpenCV wrote is incomplete (the disk is full "
                          f"or a file-size limit is reached?); {video.name} is as it was before")


def _video_frame(dataset, index: int, sample: dict, preds: list[dict], cfg: ExperimentConfig, heading: str,
                 camera_width: int) -> np.ndarray:
    """One frame of a scene's video: the BEV prediction (coloured by track ID) and GT, the cameras."""
    grid, classes = BEVGrid.from_config(cfg.grid), cfg.data.classes
    bev = figure_rgb(prediction_bev_figure(preds, sample["gt_polylines"], grid, classes, heading))
    cams = figure_rgb(prediction_cameras_figure(
        **display_images(dataset.camera_files(index), camera_width), intrinsics=sample["intrinsics"],
        cam_to_ego_rot=sample["cam_to_ego_rot"], cam_to_ego_trans=sample["cam_to_ego_trans"],
        predictions=preds, ground_truth=sample["gt_polylines"], camera_names=dataset.camera_names,
        classes=classes, ground_z=float(sample["ground_height"])))
    return _side_by_side(bev, cams)


class _VideoWriter:
    """OpenCV's MP4 writer of one video, opened at the first frame's size."""

    def __init__(self, tmp: Path, video: Path, fps: float):
        self.tmp, self.video, self.fps, self.writer, self.size = tmp, video, fps, None, None

    def write(self, frame: np.ndarray) -> None:
        if self.writer is None:
            self.size = (frame.shape[1], frame.shape[0])
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, self.size)
            if not self.writer.isOpened():
                raise PredictError(f"--video {self.video}: OpenCV cannot write MP4 (mp4v) here; check the folder is "
                                   "writable and OpenCV was built with FFmpeg")
        if (frame.shape[1], frame.shape[0]) != self.size:
            frame = cv2.resize(frame, self.size, interpolation=cv2.INTER_AREA)
        self.writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()


def predict_video(cfg: ExperimentConfig, video: str | Path, scene: str, *, checkpoint: str | Path | None = None,
                  onnx: str | Path | None = None, gt_as_prediction: bool = False, split: str | None = None,
                  overrides: Sequence[str] = (), fps: float = 2.0, camera_width: int = 320,
                  progress: bool = True, precision: str = "fp32", compile_backbone: bool = False) -> dict:
    """Every sample of ``scene`` (a nuScenes scene name or an AV2 log id) of ``split``, in time order,
    as one MP4 frame each (OpenCV's ``VideoWriter``, ``mp4v``): the BEV prediction next to the GT on
    the left, the cameras with the predictions projected on the right. Frames run through the model in
    order, each with the previous one's ``out["memory"]`` (a temporal model; ``scene_start`` on the
    first). Every element carries a track ID along the scene (``persistence.InstanceTracker``, as
    ``Mapper.stream()``), the BEV panel colours elements by it, and the predictions with their
    ``track_id`` are written beside the video in the submission format (``VIDEO`` with ``.json``). Both
    are written atomically. Returns ``{"video", "predictions", "frames", "scene", "split", "notes",
    "tracks"}``."""
    if not 1 / MAX_VIDEO_FPS < fps <= MAX_VIDEO_FPS:  # OpenCV's MP4 writer opens for neither 1000.1 nor 0.001
        raise PredictError(f"--fps {fps:g}: frames per second must be over {1 / MAX_VIDEO_FPS:g} and at most "
                           f"{MAX_VIDEO_FPS:g} (MP4's time base)")
    video = Path(video)
    if video.suffix.lower() != ".mp4":
        raise PredictError(f"--video {video}: the video is written as MP4; give a file name ending in .mp4")
    inputs = [(checkpoint, "--checkpoint"), (onnx, "--onnx")]
    for path, what in ((video, "--video"), (video.with_suffix(".json"), "--video's predictions (.json)")):
        check_output_file(path, what, inputs)  # before the frames
    model, cfg, notes, source = load_predictor(cfg, checkpoint=checkpoint, onnx=onnx, gt_as_prediction=gt_as_prediction,
                                               overrides=overrides, precision=precision,
                                               compile_backbone=compile_backbone)
    split = split or cfg.data.val_split
    dataset = build_dataset(cfg, split, augment=False)
    indices = dataset.scene_indices(scene)
    memory, skipped, scene_preds = None, 0, {}
    persist = Persistence.from_config(cfg) if not gt_as_prediction else None
    tracker = stream_tracker(cfg)
    with atomic_path(video, keep_suffix=True) as tmp, atomic_path(video.with_suffix(".json")) as tmp_json:
        writer = _VideoWriter(tmp, video, fps)
        try:
            for k, i in enumerate(tqdm(indices, desc=f"video {scene}", unit="frame", disable=not progress)):
                sample = load_or_skip(dataset, i)
                if sample is None:  # a bad frame (data.on_bad_sample=skip): no picture, and the memory starts anew
                    memory, skipped = None, skipped + 1
                    continue
                batch = collate_fn([sample])
                batch["scene_start"] = torch.tensor([k == 0])
                outputs, (preds,) = predict_batch(model, batch, cfg, memory)
                frame_index = int(dataset.scenes.frame[i])
                if persist is not None:
                    preds = persist.step(preds, scene, frame_index, sample["ego_pose"])
                ids = tracker.step(preds, scene, frame_index, sample["ego_pose"])
                preds = [{**p, "track_id": t} for p, t in zip(preds, ids)]
                memory, scene_preds[sample["sample_token"]] = outputs.get("memory"), preds
                heading = f"{scene} {k + 1}/{len(indices)}: {sample['sample_token']} - {source}"
                writer.write(_video_frame(dataset, i, sample, preds, cfg, heading, camera_width))
            if writer.writer is None:
                raise PredictError(f"every frame of scene {scene} is bad (data.on_bad_sample=skip); see the warnings")
            writer.close()
            _check_video(tmp, video)
            write_submission(tmp_json, scene_preds, {**submission_meta(cfg, split, source), "scene": scene})
        finally:
            writer.close()
    if skipped:
        notes.append(f"{skipped} bad frame(s) of scene {scene} left out (data.on_bad_sample=skip; the warnings name "
                     "them)")
    if persist is not None:  # as a single sample's note says it: what the frames show beyond the model's own output
        notes.append(f"model.temporal.persist_frames={cfg.model.temporal.persist_frames}: {persist.kept} element(s) "
                     "that earlier frames found and later ones missed were kept in the video (persistence.py)")
    return {"video": video, "predictions": video.with_suffix(".json"), "frames": len(indices) - skipped,
            "scene": scene, "split": split, "notes": notes, "persisted": None if persist is None else persist.kept,
            "tracks": tracker.next_id.get(scene, 0)}
