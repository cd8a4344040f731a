"""``instagram-hdmap``: one subcommand per job, each a thin wrapper over the library.

Each ``_cmd_*`` function turns the parsed arguments into one library call and prints its result.
User errors (``config.UserError``) print one line and exit with code 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from . import distributed as du
from .benchmark import format_benchmark, run_benchmark
from .config import ConfigError, UserError, load_config, repeated_overrides
from .data import build_dataset
from .data.base import gt_submission
from .data.synthetic import generate_world
from .data.synthetic.av2_writer import generate_av2_world
from .data.synthetic.preview import write_preview
from .demo import run_demo
from .deploy import DEFAULT_OPSET, export_checkpoint
from .errors import invisible_character, lookalike_dash
from .evaluate_split import run_evaluation
from .evaluation import PROTOCOLS, evaluate_files, format_table
from .files import NO_ROOM, check_name_lengths, check_output_dir, check_output_file, is_stream, os_error_in, write_json
from .geometry import BEVGrid
from .models import build_model, summarize_parameters
from .precision import PRECISIONS
from .predict import decode_assignments, find_sample, predict_images, predict_sample, predict_video
from .resources import out_of_memory, size_notes, summary_lines
from .streams import ReportStream, stdout_gone, to_devnull
from .train import data_worker_died, train
from .visualize import write_sample_pngs


def _load(args: argparse.Namespace):
    return load_config(args.config, args.overrides)


# --- synthetic world -------------------------------------------------------------------------


def _cmd_synth(args: argparse.Namespace) -> int:
    generate = generate_av2_world if args.format == "av2" else generate_world
    manifest = generate(
        out=args.out,
        scenes_train=args.scenes_train,
        scenes_val=args.scenes_val,
        samples_per_scene=args.samples_per_scene,
        seed=args.seed,
        image_size=args.image_size or ("2048x1550" if args.format == "av2" else "1600x900"),
        force=args.force,
        workers=args.workers,
        occluders=args.occluders,
    )
    layout = "the AV2 sensor layout" if args.format == "av2" else f"version {manifest['version']}"
    print(f"wrote {manifest['scenes_train']} train + {manifest['scenes_val']} val scenes, "
          f"{manifest['samples']} samples, {layout} to {args.out}")
    return 0


def _cmd_synth_preview(args: argparse.Namespace) -> int:
    check_output_file(args.out, "--out")
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    formats = FigureCanvasAgg.get_supported_filetypes()  # the picture's format comes from the name's suffix
    if Path(args.out).suffix.lower().lstrip(".") not in formats:
        raise UserError(f"--out {args.out}: the picture's format comes from its suffix; give a file name ending in "
                        ".png (or .jpg, .pdf, .svg)")
    write_preview(args.dataroot, args.out, index=args.index)
    print(f"wrote {args.out}")
    return 0


# --- dataset ground truth --------------------------------------------------------------------


def _load_data_cfg(args: argparse.Namespace):
    """The experiment config with --dataroot / --version applied (they win over the YAML)."""
    extra = [f"data.dataroot={args.dataroot}"] if args.dataroot else []
    extra += [f"data.version={args.version}"] if args.version else []
    return load_config(args.config, [*args.overrides, *extra])


def _cmd_export_gt(args: argparse.Namespace) -> int:
    cfg = _load_data_cfg(args)
    check_output_file(args.out, "--out", [(args.config, "CONFIG")])
    out, root = Path(args.out).resolve(), Path(cfg.data.dataroot).resolve()
    splits = Path(cfg.data.splits_file).resolve() if cfg.data.splits_file else None
    # a file the export reads: a table, map or log below the dataroot (a GT file right in it may be replaced)
    if out.is_file() and root in out.parents and (out.parent != root or out.name == "world.json" or out == splits):
        raise UserError(f"--out {args.out} is a file of the dataset the export reads (data.dataroot="
                        f"{cfg.data.dataroot}): writing the GT there would replace it; choose another output path")
    # the config's split by default, as evaluate's (a literal 'val' ignored data.val_split with no word)
    args.split = args.split or cfg.data.val_split
    dataset = build_dataset(cfg, args.split, augment=False)
    sub = gt_submission(dataset, progress=sys.stderr.isatty())  # (as evaluate-json: no bar drawn into a log file)
    write_json(sub, args.out)
    n = sum(len(v) for v in sub["results"].values())
    report = sys.stderr if is_stream(args.out) else sys.stdout  # --out /dev/stdout | jq: the JSON only on stdout
    print(f"wrote {args.out}: {len(sub['results'])} samples, {n} polylines", file=report)
    left = [t for t in dataset.sample_tokens if t not in sub["results"]]
    if left:  # named here too: the warnings that say why vanish under -W ignore
        print(f"note: {len(left)} bad sample(s) of {len(dataset)} left out (data.on_bad_sample=skip; the warnings "
              f"say why): {', '.join(left[:5])}{' ...' if len(left) > 5 else ''}", file=report)
    return 0


def _cmd_show_gt(args: argparse.Namespace) -> int:
    cfg = _load_data_cfg(args)
    check_output_dir(args.out, "--out")
    args.split = args.split or cfg.data.val_split
    dataset = build_dataset(cfg, args.split, augment=args.augment)
    sample = dataset.load_sample(find_sample(dataset, args.index))  # (negative counts back, as predict's)
    paths = write_sample_pngs(sample, dataset.grid, args.out, cfg.data.classes, dataset.camera_names)
    print(f"sample {sample['sample_token']}: {len(sample['gt_polylines'])} polylines, "
          f"{len(sample['gt_vertices_px'])} graph vertices; wrote {', '.join(str(p) for p in paths)}")
    return 0


# --- model -----------------------------------------------------------------------------------


def _cmd_model_summary(args: argparse.Namespace) -> int:
    cfg = _load(args)
    print(summarize_parameters(build_model(cfg)))
    print("\n".join(summary_lines(cfg) + size_notes(cfg)))
    return 0


# --- training --------------------------------------------------------------------------------


def _cmd_train(args: argparse.Namespace) -> int:
    cfg = _load(args)
    check_name_lengths(Path(cfg.train.out_dir), "train.out_dir")  # before the stat below
    written = Path(cfg.train.out_dir) / "config.yaml"  # the run writes its resolved config there
    if not args.resume and written.is_file() and written.resolve() == Path(args.config).resolve():
        raise UserError(f"CONFIG {args.config} is {written}, where the run writes its resolved config (starting over "
                        "removes it first): your file would be lost; keep the experiment YAML outside "
                        "train.out_dir or under another name")
    summary = train(cfg, resume=args.resume, force=args.force)
    if int(os.environ.get("RANK", "0")) == 0:  # under torchrun each rank returns here: one line, as the run's others
        print(f"done: epoch {summary.get('epoch')}, step {summary.get('step')}; outputs in {summary['out_dir']}")
        # docs/guide.md, "Schedules": a run cut by train.max_steps ends before its final LR "and says so"
        if cfg.train.max_steps is not None and summary.get("schedule_complete") is False:
            print(f"note: train.max_steps={cfg.train.max_steps} stopped the run before the end of its schedule "
                  f"(progress {summary.get('progress', 0):.3f}; lr {summary.get('lr', 0):.3g}, final "
                  f"{summary.get('final_lr', 0):.3g}): resume with a larger train.max_steps (or none) to finish it")
    return 0


# --- evaluation ------------------------------------------------------------------------------


# evaluate-json's options of the raster protocol and their defaults (None on the command line: not given)
RASTER_FLAGS = {"xbound": [-30.0, 30.0], "ybound": [-15.0, 15.0], "resolution": 0.15, "rank_by": "ascending",
                "fix_instance_ids": False, "device": "cpu"}


def _cmd_evaluate_json(args: argparse.Namespace) -> int:
    given = [f"--{k.replace('_', '-')}" for k in RASTER_FLAGS if getattr(args, k) not in (None, False)]
    if args.protocol == "vector" and given:  # the vector protocol has no canvas: they would be ignored
        raise UserError(f"{', '.join(given)}: options of the raster protocol; the vector protocol (MapTR) scores "
                        "every vector of the files, on no canvas: pass --protocol raster, or drop them")
    for key, default in RASTER_FLAGS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    if not (math.isfinite(args.resolution) and args.resolution > 0):
        raise UserError(f"--resolution {args.resolution}: metres per pixel of the raster canvas must be > 0")
    for flag, (lo, hi) in (("--xbound", args.xbound), ("--ybound", args.ybound)):
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise UserError(f"{flag} {lo:g} {hi:g}: two finite bounds in metres, the lower first")
        pixels = (hi - lo) / args.resolution  # named here: BEVGrid.check names the config key grid.*
        if abs(pixels - round(pixels)) > 1e-6:
            raise UserError(f"{flag} {lo:g} {hi:g}: its extent {hi - lo:g} m is not a whole number of --resolution "
                            f"{args.resolution:g} m pixels")
    if args.out:
        check_output_file(args.out, "--out", [(args.pred, "--pred"), (args.gt, "--gt")])
    grid = BEVGrid(*args.xbound, *args.ybound, args.resolution, cell_size=1)
    grid.check()
    metrics = evaluate_files(args.pred, args.gt, args.protocol, args.thresholds, grid=grid, rank_by=args.rank_by,
                             fix_instance_ids=args.fix_instance_ids, device=args.device,
                             ignore_extra_predictions=args.ignore_extra_predictions, progress=sys.stderr.isatty())
    report = sys.stderr if args.out and is_stream(args.out) else sys.stdout  # --out /dev/stdout | jq: JSON only
    print(format_table(metrics), file=report)
    _print_notes(metrics["notes"], report)
    if args.out:
        print(f"wrote {write_json(metrics, args.out, indent=2)}", file=report)  # NaN is written as null (JSON)
    return 0


# --- inference: evaluate, predict, benchmark -------------------------------------------------


def _print_notes(notes: list[str], file=None) -> None:
    for note in notes:
        print(f"note: {note}", file=file)


def _load_evaluate(args: argparse.Namespace):
    """evaluate's config with ``--protocol`` as its ``eval.protocol``, so that ``eval.also_protocols`` is checked
    against the protocol run (``--protocol raster eval.also_protocols=[vector]`` on a vector config was refused as
    listing the config's own protocol); ``eval.also_protocols`` naming ``--protocol`` itself stays taken (the
    duplicate dropped)."""
    if args.protocol is None:
        return _load(args)
    try:
        return load_config(args.config, [*args.overrides, f"eval.protocol={args.protocol}"])
    except ConfigError as e:
        if "eval.also_protocols" not in str(e):
            raise
        return _load(args)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    result = run_evaluation(_load_evaluate(args), args.checkpoint, args.protocol, args.out, overrides=args.overrides,
                            precision=args.precision, compile_backbone=args.compile_backbone)
    if not result["paths"]:  # not rank 0 under torchrun
        return 0
    metrics = result["metrics"]
    print(f"evaluated {result['num_samples']} samples of split '{metrics['meta']['split']}' "
          f"({result['samples_per_s']:.2f} samples/s) with protocol '{metrics['protocol']}'")
    print(format_table(metrics))
    if "consistency" in metrics:  # evaluation/consistency.py
        c = metrics["consistency"]
        print("flicker (GT elements seen in consecutive frames whose detected/missed status flips): "
              + ", ".join(f"{k} {v:.3f}" for k, v in c["flicker"].items()) + f"; mean {c['flicker_mean']:.3f}")
        empty = [k for k, v in c["flicker"].items() if v != v]  # NaN: no pair to count
        if empty:
            print(f"  (nan: no element of {', '.join(empty)} was seen in two consecutive frames of a scene, e.g. "
                  "scenes of one frame, so no flicker to count)")
    if "cmap" in metrics:  # evaluation/consistency.py: ConsistentAPMeter (eval.cmap)
        c = metrics["cmap"]
        print(f"consistency-aware AP (MapTracker's C-mAP: a TP whose instance ID is not its GT element's first one "
              f"is an FP), thresholds {c['thresholds']} m:")
        for k in c["C-AP_class"]:
            print(f"  {k:<14} C-AP {c['C-AP_class'][k]:.4f}  AP {c['AP_class'][k]:.4f}  TPs switched "
                  f"{c['switched'][k]}")
        print(f"  C-mAP {c['C-mAP']:.4f}  mAP {c['mAP']:.4f}  ({c['tracks']['pred']} predicted and "
              f"{c['tracks']['gt']} GT instance tracks)")
    if "memory" in metrics:  # a temporal model: what each frame did with its memory
        print("memory: " + ", ".join(f"{k.removeprefix('memory_')} {v}" for k, v in metrics["memory"].items()))
    _print_notes([*result["notes"], *metrics.get("notes", [])])
    print(f"wrote {', '.join(str(p) for p in result['paths'])}")
    return 0


def _cmd_predict(args: argparse.Namespace) -> int:
    if args.scene is not None:
        if args.video is None:
            raise UserError("--scene renders a whole scene as a video: add --video OUT.mp4 (or use --index / --token "
                            "for one sample's pictures)")
        result = predict_video(_load(args), args.video, args.scene, checkpoint=args.checkpoint, onnx=args.onnx,
                               gt_as_prediction=args.gt_as_prediction, split=args.split, overrides=args.overrides,
                               fps=args.fps if args.fps is not None else 2.0, progress=sys.stderr.isatty(),
                               precision=args.precision, compile_backbone=args.compile_backbone)
        _print_notes(result["notes"])
        print(f"scene {result['scene']} (split '{result['split']}'): {result['frames']} frames, {result['tracks']} "
              f"tracked elements; wrote {result['video']} and {result['predictions']}")
        return 0
    if args.video is not None or args.out is None:
        raise UserError("--video needs --scene NAME; one sample's pictures need --out DIR")
    if args.fps is not None:  # one sample's pictures: the frame rate was ignored with no word
        raise UserError("--fps is the frame rate of a --scene video (--scene NAME --video OUT.mp4); one sample's "
                        "pictures have none: drop --fps")
    result = predict_sample(_load(args), args.out, checkpoint=args.checkpoint, index=args.index, token=args.token,
                            split=args.split, overrides=args.overrides, gt_as_prediction=args.gt_as_prediction,
                            onnx=args.onnx, precision=args.precision, compile_backbone=args.compile_backbone)
    _print_notes(result["notes"])
    print(f"sample {result['sample_token']} (split '{result['split']}', index {result['index']}): "
          f"{len(result['predictions'])} predicted instances; wrote {', '.join(str(p) for p in result['paths'])}")
    return 0


def _cmd_predict_images(args: argparse.Namespace) -> int:
    result = predict_images(args.rig, args.images, args.out, checkpoint=args.checkpoint, onnx=args.onnx,
                            config=args.config, decode=decode_assignments(args.decode), device=args.device,
                            name=args.name, precision=args.precision, compile_backbone=args.compile_backbone)
    print(f"{result['name']} ({result['source']}): {len(result['elements'])} map elements; wrote "
          f"{', '.join(str(p) for p in result['paths'])}")
    _print_notes(result.get("notes", []))
    return 0


def _cmd_benchmark(args: argparse.Namespace) -> int:
    result = run_benchmark(_load(args), device=args.device, amp=args.amp, runs=args.runs, warmup=args.warmup,
                           checkpoint=args.checkpoint, overrides=args.overrides, compile=args.compile,
                           cuda_graphs=args.cuda_graphs, precision=args.precision,
                           compile_backbone=args.compile_backbone)
    print(format_benchmark(result, args.config))
    return 0


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    check_output_file(args.out, "--out", [(args.config, "CONFIG"), (args.checkpoint, "--checkpoint")])
    info = export_checkpoint(_load(args), args.checkpoint, args.out, overrides=args.overrides, opset=args.opset)
    print(f"wrote {info['path']}: opset {info['opset']}, {info['nodes']} nodes, static batch 1, config "
          f"{info['config'].name} (sha256 {info['config_sha256'][:12]})")
    for kind in ("inputs", "outputs"):
        print(f"{kind}: " + ", ".join(f"{name} {shape}" for name, shape in info[kind].items()))
    check = info["check"]
    graph = (f"{check['graph']:.1e} on the graph outputs" if check["same_vertices"] else
             "different vertices: top-N cut through equal scores (random weights?), graph outputs not compared")
    print(f"onnxruntime check on an example input: max |onnxruntime - torch| {check['dense']:.1e} on the dense "
          f"outputs, {graph}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    try:
        run_demo(args.out, minutes=args.minutes, cache_dir=args.cache, config=args.config,
                 overrides=args.overrides, workers=args.workers, raster=not args.no_raster)
    except KeyboardInterrupt:
        print(f"instagram-hdmap demo: interrupted; the world cache is intact and the run resumes from "
              f"{Path(args.out) / 'run' / 'last.pt'}: run the same command again", file=sys.stderr)
        return 130
    return 0


def _add_parser(sub, name: str, func, config: bool = False, **kwargs) -> argparse.ArgumentParser:
    """The subcommand ``name`` (``kwargs``: its help and description) running ``func``; with ``config``, CONFIG
    and its key=value overrides come first."""
    p = sub.add_parser(name, **kwargs)
    if config:
        p.add_argument("config", help="experiment YAML (overrides of the defaults in config.py)")
        p.add_argument("overrides", nargs="*", help="key.sub=value overrides, e.g. model.gnn.layers=9")
    p.set_defaults(func=func)
    return p


def _synth_parser(sub) -> None:
    p = _add_parser(sub, "synth", _cmd_synth,
                    help="write a synthetic world in the nuScenes (or Argoverse 2) on-disk format")
    p.add_argument("--out", required=True, help="output dataroot (must be empty or absent)")
    p.add_argument("--format", choices=["nuscenes", "av2"], default="nuscenes",
                   help="on-disk layout: nuscenes (default) or av2, the Argoverse 2 sensor dataset (extra [av2])")
    p.add_argument("--scenes-train", type=int, default=8)
    p.add_argument("--scenes-val", type=int, default=2)
    p.add_argument("--samples-per-scene", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", help="camera image WIDTHxHEIGHT (default 1600x900; av2: 2048x1550, the "
                   "landscape ring cameras, ring_front_center is HEIGHTxWIDTH)")
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out")
    p.add_argument("--occluders", type=float, default=0.0,
                   help="density in [0, 1] of parked vehicles along kerbs and trucks ahead in the ego's lane "
                        "(a world where a temporal model's memory matters; default 0: none)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes rendering scenes in parallel (0: one per CPU core); same output for any value")


def _synth_preview_parser(sub) -> None:
    p = _add_parser(sub, "synth-preview", _cmd_synth_preview,
                    help="PNG of one synthetic sample: cameras with map lines, and BEV")
    p.add_argument("dataroot")
    p.add_argument("--out", required=True)
    p.add_argument("--index", type=int, default=0, help="sample index in the dataroot (negative counts from the end)")


def _gt_parser(sub) -> None:
    for name, func, help_ in (
            ("export-gt", _cmd_export_gt, "write a split's GT polylines as HDMapNet submission JSON"),
            ("show-gt", _cmd_show_gt, "PNGs of one sample's GT: polylines, vertex cells, DT, cameras")):
        p = _add_parser(sub, name, func, config=True, help=help_)
        p.add_argument("--dataroot", help="dataset root (overrides data.dataroot)")
        p.add_argument("--version", help="version folder, e.g. v1.0-mini (overrides data.version)")
        p.add_argument("--split", help="split name (default: data.val_split, the split evaluate scores)")
        p.add_argument("--out", required=True, help="output JSON file" if name == "export-gt" else "output folder")
        if name == "show-gt":
            p.add_argument("--index", type=int, default=0, help="sample index in the split")
            p.add_argument("--augment", action="store_true", help="apply the train-time image augmentation")


def _model_summary_parser(sub) -> None:
    _add_parser(sub, "model-summary", _cmd_model_summary, config=True,
                help="parameters per component and in total, and the memory a step needs")


def _train_parser(sub) -> None:
    p = _add_parser(sub, "train", _cmd_train, config=True, help="train a model; torchrun-aware")
    p.add_argument("--resume", help="checkpoint to continue from (e.g. OUT/last.pt)")
    p.add_argument("--force", action="store_true",
                   help="start over in an output folder that holds a run (removes that run's checkpoints, log and "
                   "TensorBoard events, nothing else)")


def _evaluate_json_parser(sub) -> None:
    p = _add_parser(sub, "evaluate-json", _cmd_evaluate_json,
                    help="AP of a submission JSON against a GT JSON (vector or raster protocol)",
                    description="Chamfer AP of PRED against GT, both in the HDMapNet submission format. Prints a "
                    "table and writes --out as JSON (NaN, where the protocol yields 0/0, is written as NaN).")
    p.add_argument("--pred", required=True, help="predictions JSON (confidence_level per vector)")
    p.add_argument("--gt", required=True, help="ground-truth JSON (same format, no confidence_level)")
    p.add_argument("--protocol", choices=PROTOCOLS, default="vector",
                   help="vector: MapTR (default); raster: HDMapNet / InstaGraM paper")
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.5, 1.0, 1.5], help="Chamfer thresholds (m)")
    p.add_argument("--out", help="metrics JSON to write")
    p.add_argument("--rank-by", choices=["ascending", "descending"],
                   help="raster: PR-curve order; ascending reproduces the reference's bug (default)")
    p.add_argument("--fix-instance-ids", action="store_true",
                   help="raster: int32 instance ids, each with its own confidence (fixes the reference's misalignment)")
    p.add_argument("--xbound", type=float, nargs=2, help="raster: canvas x range (m; default -30 30)")
    p.add_argument("--ybound", type=float, nargs=2, help="raster: canvas y range (m; default -15 15)")
    p.add_argument("--resolution", type=float, help="raster: metres per pixel (default 0.15)")
    p.add_argument("--device", help="raster: where torch.cdist runs, cpu (default) or cuda (the reference ran on CUDA)")
    p.add_argument("--ignore-extra-predictions", action="store_true",
                   help="ignore prediction tokens that are not in the GT file (default: error)")


def _add_precision(p: argparse.ArgumentParser) -> None:
    p.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="the model's precision (default fp32: the same numbers on every machine; int8: the BEV encoder "
                   "in int8, calibrated on training samples, CPU only; auto: bf16 where the device computes it "
                   "natively, else fp32)")


def _add_compile_backbone(p: argparse.ArgumentParser) -> None:
    p.add_argument("--compile-backbone", action="store_true",
                   help="run the image backbone through torch.compile (the first batch compiles it, tens of seconds; "
                   "then a faster backbone, docs/deploy.md); the rest of the model stays as it is")


def _evaluate_parser(sub) -> None:
    p = _add_parser(sub, "evaluate", _cmd_evaluate, config=True,
                    help="run a checkpoint on the validation split: submission JSON + AP metrics",
                    description="Runs CKPT on data.val_split, writes OUT/submission.json (HDMapNet format) and "
                    "OUT/metrics.json, prints the AP table. The model settings come from the checkpoint's "
                    "saved config; key=value overrides win. torchrun-aware.")
    p.add_argument("--checkpoint", required=True, help="model checkpoint (e.g. runs/x/best.pt)")
    p.add_argument("--protocol", choices=PROTOCOLS, help="AP protocol (default: eval.protocol)")
    p.add_argument("--out", default="eval", help="output folder (default ./eval)")
    _add_precision(p)
    _add_compile_backbone(p)


def _predict_parser(sub) -> None:
    p = _add_parser(sub, "predict", _cmd_predict, config=True,
                    help="PNGs of one sample: prediction vs GT in BEV, cameras, intermediate results",
                    description="Writes OUT/prediction_bev.png, prediction_cameras.png, "
                    "prediction_intermediate.png (the paper's Fig. 6) and prediction.json for one sample.")
    p.add_argument("--checkpoint", help="model checkpoint (required unless --gt-as-prediction)")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--index", type=int, help="sample index in the split (negative counts from the end)")
    which.add_argument("--token", help="nuScenes sample token")
    which.add_argument("--scene", help="a whole scene (nuScenes scene name, AV2 log id) as a video: with --video")
    p.add_argument("--split", help="split to take the sample from (default: data.val_split)")
    p.add_argument("--out", help="output folder (one sample's pictures)")
    p.add_argument("--video", help="MP4 file: with --scene, one frame per sample (BEV prediction and GT, cameras)")
    p.add_argument("--fps", type=float, help="video frames per second of --video (default 2: nuScenes' key frames)")
    p.add_argument("--gt-as-prediction", action="store_true",
                   help="no model: draw the predictions a perfect model would make (GT targets -> post-processing)")
    p.add_argument("--onnx", help="run an export-onnx file in onnxruntime instead of a checkpoint ([deploy] extra)")
    _add_precision(p)
    _add_compile_backbone(p)


def _predict_images_parser(sub) -> None:
    p = _add_parser(sub, "predict-images", _cmd_predict_images,
                    help="map elements from your own cameras: a rig file and one image per camera",
                    description="Runs a checkpoint (or an export-onnx file) on one frame of your own cameras, "
                    "described by a rig file (docs/guide.md, 'Your own cameras': camera names, intrinsics, "
                    "camera-to-ego rotation and translation, image size), and writes OUT/prediction.json "
                    "(HDMapNet format) and predict's pictures.")
    p.add_argument("images", nargs="+", help="one image file per camera of the rig file, in its order")
    p.add_argument("--rig", required=True, help="rig file (JSON)")
    p.add_argument("--checkpoint", help="model checkpoint (its saved config describes the model)")
    p.add_argument("--onnx", help="an export-onnx file instead of a checkpoint ([deploy] extra)")
    p.add_argument("--config", help="with --onnx: the config it was exported from (default: the one stamped in it)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--name", default="frame", help="the frame's name in prediction.json (default: frame)")
    p.add_argument("--device", help="cpu, cuda or cuda:i (default: CUDA when available)")
    p.add_argument("--decode", action="append", default=[], metavar="NAME=VALUE",
                   help="a decoding option, e.g. match_threshold=0.05 (model.gnn.*; repeatable)")
    _add_precision(p)
    _add_compile_backbone(p)


def _benchmark_parser(sub) -> None:
    p = _add_parser(sub, "benchmark", _cmd_benchmark, config=True,
                    help="inference FPS, batch 1, six cameras, with and without post-processing")
    p.add_argument("--device", help="cpu, cuda or cuda:i (default: train.device)")
    p.add_argument("--amp", choices=["none", "bf16", "fp16"], default="none", help="autocast precision")
    p.add_argument("--precision", choices=PRECISIONS,
                   help="instead of --amp: the precision inference runs in (int8 calibrates on the training split, or "
                   "on the timed batch without --checkpoint; auto: bf16 where the device computes it natively, else "
                   "fp32)")
    p.add_argument("--runs", type=int, help="timed runs (default 50 on a GPU, 10 on the CPU)")
    p.add_argument("--warmup", type=int, help="untimed warm-up runs (default 10 on a GPU, 2 on the CPU)")
    p.add_argument("--checkpoint", help="load trained weights (post-processing cost depends on them)")
    p.add_argument("--compile", action="store_true", help="torch.compile the whole model (static shapes) first")
    _add_compile_backbone(p)
    p.add_argument("--cuda-graphs", action="store_true", help="capture the forward in a CUDA graph and replay it")


def _export_onnx_parser(sub) -> None:
    p = _add_parser(sub, "export-onnx", _cmd_export_onnx, config=True,
                    help="export a checkpoint as one static ONNX graph for onnxruntime",
                    description="Writes the whole model (images + calibration in, the model's output dict out, "
                    "batch 1, a fixed number of Sinkhorn iterations, standard ops only) to --out, checks it in "
                    "onnxruntime and prints the interface (docs/deploy.md). Needs the [deploy] extra.")
    p.add_argument("--checkpoint", required=True, help="model checkpoint; its config must match CONFIG + overrides")
    p.add_argument("--out", required=True, help="ONNX file to write")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                   help=f"ONNX opset (default {DEFAULT_OPSET}, the lowest the exporter writes)")


def _demo_parser(sub) -> None:
    p = _add_parser(sub, "demo", _cmd_demo,
                    help="the whole pipeline on the synthetic world on a CPU: train, evaluate, draw",
                    description="Generates (once, cached) a synthetic world, trains configs/synthetic/demo.yaml "
                    "within --minutes, evaluates it (vector and raster protocols, and a random-training-map "
                    "baseline), writes OUT/metrics.json, OUT/run (checkpoint, TensorBoard) and OUT/predict PNGs. "
                    "Run it again to resume an interrupted demo.")
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--minutes", type=float, default=20.0, help="wall-time budget, set-up included (default 20)")
    p.add_argument("--cache", help="world cache folder (default $INSTAGRAM_HDMAP_CACHE, else "
                   "$XDG_CACHE_HOME/instagram_hdmap, else ~/.cache/instagram_hdmap)")
    p.add_argument("--config", help="training config (default configs/synthetic/demo.yaml)")
    p.add_argument("--workers", type=int, default=2, help="processes generating the world (default 2)")
    p.add_argument("--no-raster", action="store_true", help="skip the raster-protocol evaluation")
    p.add_argument("overrides", nargs="*", help="key=value config overrides")


SUBCOMMANDS = (  # each adds one subcommand (or two alike) to the parser, in the order --help lists them
    _synth_parser,
    _synth_preview_parser,
    _gt_parser,
    _model_summary_parser,
    _train_parser,
    _evaluate_json_parser,
    _evaluate_parser,
    _predict_parser,
    _predict_images_parser,
    _benchmark_parser,
    _export_onnx_parser,
    _demo_parser,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="instagram-hdmap", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


# the options and arguments that name files or folders
PATH_ARGS = ("config", "dataroot", "out", "checkpoint", "resume", "pred", "gt", "onnx", "rig", "video", "cache",
             "images")


def _expand_home(args: argparse.Namespace) -> None:
    """``~/...`` in a path argument is the home folder: the shell leaves it unexpanded after ``=``
    (``--out=~/eval``) or in quotes, which would write into a folder named ``~`` under the working
    directory while the messages say ``~/eval`` (the config's path keys read ``~`` so too)."""
    for name in PATH_ARGS:
        value = getattr(args, name, None)  # (expanduser changes only a leading ~)
        if isinstance(value, str):
            setattr(args, name, os.path.expanduser(value))
        elif isinstance(value, list):
            setattr(args, name, [os.path.expanduser(v) if isinstance(v, str) else v for v in value])


def _say(line: str) -> None:
    """One line to stderr in one write: under torchrun the ranks share the stream, and print's separate write of
    the newline let two ranks' error lines run together on one line."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def main(argv: list[str] | None = None) -> int:
    streams = sys.stdout, sys.stderr
    report, sinks = [], []
    for attr, name in (("stdout", "the standard output"), ("stderr", "the standard error")):
        stream = getattr(sys, attr)
        if stream is None:  # closed at the start (`2>&-`, a launcher's): a progress bar or a warning written to None
            stream = open(os.devnull, "w")  # was a raw AttributeError that stopped the job, unseen
            sinks.append(stream)
        report.append(ReportStream(stream, name))
        setattr(sys, attr, report[-1])
    try:
        code = _main(argv)
        lost = report[-1].lost
        if lost is not None and not report[0].gone:
            print(f"instagram-hdmap: note: the standard error could not be written from some point on ("
                  f"{lost.strerror or lost}); its messages were dropped")
        code = 141 if code == 0 and any(r.gone for r in report) else code  # done; the report had no reader
    finally:
        sys.stdout, sys.stderr = streams
        for sink in sinks:
            sink.close()
    if argv is None and du.group_ended():  # a torchrun rank, its job done and its process group destroyed: exit now.
        for stream in streams:  # Python's own exit runs C++ destructors where gloo's threads still aborted a rank at
            try:  # random under load ("terminate called without an active exception", SIGABRT: 1 job in 51), and
                stream.flush()  # torchrun failed the job (exit 1) after its work was done and its files written
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(code)
    return code


def _long_options(parser: argparse.ArgumentParser) -> set[str]:
    """Every ``--option`` name of ``parser`` and its subcommands, without the dashes."""
    options, todo = set(), [parser]
    while todo:
        p = todo.pop()
        for action in p._actions:
            options.update(o.lstrip("-") for o in action.option_strings if o.startswith("--"))
            if isinstance(action, argparse._SubParsersAction):
                todo.extend(action.choices.values())
    return options


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    dash = lookalike_dash(sys.argv[1:] if argv is None else list(argv), _long_options(parser))
    if dash is not None:
        parser.error(dash)
    args, extra = parser.parse_known_args(argv)
    # key=value overrides may also follow the options: ``train CONFIG --resume R model.gnn.layers=9``
    stray = [a for a in extra if a.startswith("-") or "=" not in a or not hasattr(args, "overrides")]
    if stray:
        flagged = [a for a in stray if a.startswith("-") and (a.lstrip("-") in ("set", "override", "overrides",
                                                                                 "cfg-options", "options")
                                                              or "." in a.partition("=")[0])]  # --model.gnn.layers=9
        parser.error(f"unrecognized arguments: {' '.join(stray)}"
                     + ("; config overrides are key=value words after CONFIG, without a flag: model.gnn.layers=9"
                        if flagged and hasattr(args, "overrides") else ""))
    if extra:
        args.overrides = [*args.overrides, *extra]
    if os.environ.get("RANK", "0") == "0":  # (under torchrun: once)
        decode = [f"--decode {note}" for note in repeated_overrides(getattr(args, "decode", None) or [])]
        for note in repeated_overrides(getattr(args, "overrides", None) or []) + decode:
            _say(f"instagram-hdmap {args.command}: note: {note}")
    _expand_home(args)
    try:
        invisible = invisible_character(sys.argv[1:] if argv is None else argv)
        if invisible is not None:
            raise UserError(invisible)
        code = args.func(args) or 0
        # every rank of a torchrun job got here: destroy the process group before the interpreter exits, where gloo's
        # worker threads, still running, aborted a rank at random (SIGABRT, "terminate called without an active
        # exception") and the job failed with exit 1 after all its work was done (only on success: ranks that stop
        # on an error may be inside a collective, where the destruction would wait for good)
        du.barrier()
        du.cleanup()
        return code
    except UserError as e:
        _say(f"instagram-hdmap {args.command}: error: {e}")
        return 2
    except KeyboardInterrupt:
        _say(f"instagram-hdmap {args.command}: interrupted")
        return 130
    except Exception as e:  # a full disk outside the atomic writes (a log line, TensorBoard events)
        if isinstance(e, BrokenPipeError) and stdout_gone():  # the reader of the output went away (`model-summary
            to_devnull(sys.stdout)  # CONFIG | head -1`): stop quietly, as Unix tools do (exit 141, as by SIGPIPE)
            return 141
        cause = os_error_in(e)
        died = data_worker_died(e)
        if died is not None:  # evaluate, predict: nothing was written (a training saves last.pt first)
            _say(f"instagram-hdmap {args.command}: error: {died.rstrip('. ')} (the out-of-memory killer, or a "
                  "kill); nothing was written: run it again (with a lower data.num_workers or eval.batch_size if "
                  "memory ran out)")
            return 2
        if cause is None and out_of_memory(e):
            first = " ".join(str(e).split())[:300]
            _say(f"instagram-hdmap {args.command}: error: out of memory ({type(e).__name__}: {first}); make the job "
                  "smaller (train.batch_size / eval.batch_size, data.image_size, the grid's size and resolution, "
                  "model.gnn.num_vertices, evaluate-json's --resolution) or run it where there is more memory (a "
                  "training resumes with --resume OUT/last.pt)")
            return 2
        if cause is None or cause.errno not in NO_ROOM:
            raise
        where = f" writing {cause.filename}" if cause.filename else ""
        _say(f"instagram-hdmap {args.command}: error: {cause.strerror or cause}{where}: the disk is full or a "
              "file-size limit is reached; free some space and run again (a training resumes with --resume "
              "OUT/last.pt)")
        return 2


if __name__ == "__main__":
    sys.exit(main())
