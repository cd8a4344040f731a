"""``instagram-hdmap evaluate``: a checkpoint's AP on a split, and its submission.

    result = run_evaluation(load_config("configs/synthetic/tiny.yaml"), "runs/x/best.pt", "vector", "eval")
    result["metrics"]["mAP"]; result["paths"]  # eval/submission.json, eval/metrics.json

The split is walked in order (a temporal model's scenes as streams, with its memory), every sample is
scored once (under torchrun by one rank), the evaluator and the drive meters are gathered over the ranks
and rank 0 writes the pair of files together.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from . import distributed as du
from .config import ExperimentConfig, as_config
from .data import build_dataset
from .data.base import collate_fn
from .data.streaming import StreamingBatchSampler
from .engine import evaluate, is_temporal, meter_results
from .evaluation import Evaluator, write_submission
from .files import atomic_path, check_output_dir, check_output_file, locked_folder, write_json
from .geometry import BEVGrid
from .inference import load_model
from .persistence import Persistence
from .postprocess import decode_options, postprocess_batch
from .precision import precision_of
from .predict import camera_dropout_notes, submission_meta
from .resources import check_fits, data_workers, size_notes
from .training_data import make_cmap_meter, make_flicker_meter, open_files_for_workers, unused_meter_keys


def run_evaluation(cfg: ExperimentConfig, checkpoint: str | Path, protocol: str | None = None, out: str | Path = "eval",
                   *, overrides: Sequence[str] = (), amp: str = "none", precision: str = "fp32",
                   calibration: list[dict] | None = None, compile_backbone: bool = False) -> dict:
    """Run ``checkpoint`` on the validation split (``data.val_split``), post-process, evaluate.

    Writes ``out/submission.json`` (HDMapNet format) and ``out/metrics.json`` (the evaluator's
    metrics: ``protocol``, ``thresholds``, ``classes``, ``AP``, ``AP_class``, ``mAP``, ``notes``, ...,
    plus ``meta``: checkpoint, config name, split, sample count, speed, config notes). ``protocol``
    overrides ``eval.protocol``. ``precision``: fp32 (the default), bf16, int8 or auto
    (precision.py; int8 calibrates on ``calibration`` batches, by default on training samples of
    ``cfg``). ``compile_backbone``: the image backbone through ``torch.compile`` (``precision.compile_backbone``;
    the first batch compiles it). Returns ``{"metrics", "paths", "notes", "num_samples", "samples_per_s"}``.

    Under torchrun each rank runs every world-size-th sample; the sampler's wrap-around padding is
    not scored twice (a sample is scored by the rank ``index % world_size``, once), the evaluator
    states are gathered and rank 0 writes the files. Samples are scored with their dataset index as
    ``sample_ids``, so the result does not depend on the batch size or the number of processes.

    A temporal model walks the split's scenes in order, ``eval.batch_size`` streams (per rank; each
    rank owns whole scenes, data/streaming.py) with its memory; each sample is scored once, by the rank
    that owns it. ``metrics["consistency"]`` holds the flicker rate (``eval.flicker``,
    evaluation/consistency.py), ``metrics["cmap"]`` MapTracker's consistency-aware mAP (``eval.cmap``) and,
    for a temporal model, ``metrics["memory"]`` the samples per memory
    status (fused, no memory, pose jump, missing frame).
    """
    cfg = as_config(cfg, "run_evaluation")  # a YAML path (or the checkpoint, arguments swapped): named
    check_output_dir(out, "--out")  # before the work that fills it
    for name in ("submission.json", "metrics.json"):
        check_output_file(Path(out) / name, "--out")
    device = du.init_distributed(du.resolve_device(cfg.train.device).type)
    # a second evaluation into the same --out while this one runs is refused (the pair of files of one and the
    # other could otherwise end up side by side)
    with locked_folder(out, "evaluation", "choose another --out", du.print_main, enabled=du.is_main_process()):
        return _evaluate_into(cfg, checkpoint, protocol, Path(out), device, overrides, amp, precision, calibration,
                              compile_backbone)


def _split_loader(cfg: ExperimentConfig, dataset, temporal: bool, rank: int,
                  world: int) -> tuple[DataLoader, set | None]:
    """The loader of this rank's part of the split and, for a temporal model, the samples it scores: whole
    scenes walked in order as ``eval.batch_size`` streams (data/streaming.py), else every sample in order."""
    open_files_for_workers(cfg.data.num_workers)
    if temporal:
        streams = StreamingBatchSampler(dataset.scenes.runs, cfg.eval.batch_size, shuffle=False, rank=rank,
                                        world_size=world)
        sampling = {"batch_sampler": streams}
    else:
        sampling = {"batch_size": cfg.eval.batch_size, "sampler": du.ResumableSampler(len(dataset), shuffle=False)}
    loader = DataLoader(dataset, collate_fn=collate_fn, num_workers=data_workers(cfg.data.num_workers, len(dataset)),
                        **sampling)
    return loader, streams.owned() if temporal else None


def _write_pair(out: Path, results: dict, metrics: dict, meta: dict) -> list[Path]:
    """``submission.json`` and ``metrics.json`` (rank 0): both are written to temporaries first and renamed
    together at the end, so a kill or a full disk while either is written leaves the folder's earlier pair as
    it was, not this submission beside the metrics of another evaluation (a pair that looked whole)."""
    if not du.is_main_process():
        return []
    with atomic_path(out / "submission.json") as sub_tmp, atomic_path(out / "metrics.json") as met_tmp:
        write_submission(sub_tmp, results, meta)
        write_json(metrics, met_tmp)
    return [out / "submission.json", out / "metrics.json"]


def _evaluate_into(cfg: ExperimentConfig, checkpoint, protocol: str | None, out: Path, device: torch.device,
                   overrides: Sequence[str], amp: str, precision: str = "fp32", calibration=None,
                   compile_backbone: bool = False) -> dict:
    """``run_evaluation``'s work, its output folder checked and held."""
    model, cfg, notes = load_model(checkpoint, cfg, overrides, device=device, precision=precision,
                                   calibration=calibration, compile_backbone=compile_backbone)
    if protocol is not None:
        cfg = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, protocol=protocol))
    notes += camera_dropout_notes(cfg, "the AP") + unused_meter_keys(cfg) + size_notes(cfg)
    check_fits(cfg, "infer", device)  # an eval.batch_size (or N, grid) that cannot fit: before the data workers
    grid = BEVGrid.from_config(cfg.grid)
    split = cfg.data.val_split
    dataset = build_dataset(cfg, split, augment=False)
    index_of = {t: i for i, t in enumerate(dataset.sample_tokens)}
    rank, world = du.get_rank(), du.get_world_size()
    loader, owned = _split_loader(cfg, dataset, is_temporal(model), rank, world)
    evaluator = Evaluator.from_config(cfg)
    flicker = make_flicker_meter(cfg)
    cmap = make_cmap_meter(cfg)
    results: dict[str, list[dict]] = {}
    pending_gt: dict[str, list[dict]] = {}

    def tap(batches):  # keeps each batch's GT until its predictions arrive (no second GT load)
        for batch in batches:
            pending_gt.update(zip(batch["sample_token"], batch["gt_polylines"]))
            yield batch

    def score(tokens: list[str], preds: list[list[dict]]) -> None:
        # a token may come twice (data.on_bad_sample=skip hands the next good sample for a bad one, streaming
        # padding repeats samples): scored once
        gts = [pending_gt.get(t) for t in tokens]
        for t in tokens:
            pending_gt.pop(t, None)
        mine = (lambda i: i % world == rank) if owned is None else owned.__contains__
        keep = []
        for k, t in enumerate(tokens):  # streaming padding may repeat a sample, even within a batch
            if mine(index_of[t]) and t not in results:
                keep.append(k)
                results[t] = preds[k]
        if keep:
            ids = [index_of[tokens[k]] for k in keep]
            evaluator.update([preds[k] for k in keep], [gts[k] for k in keep], sample_ids=ids,
                             tokens=[tokens[k] for k in keep])
            for meter in (flicker, cmap):
                if meter is not None:
                    meter.update([preds[k] for k in keep], [gts[k] for k in keep], [dataset.scene_of(i) for i in ids],
                                 [dataset.scenes.frame[i] for i in ids],
                                 torch.stack([dataset.ego_pose(i) for i in ids]))

    decode = decode_options(cfg.model.gnn, grid)
    persist = Persistence.from_config(cfg)
    val = evaluate(model, None, tap(loader), device,
                   postprocess=lambda outputs: postprocess_batch(outputs, grid, **decode),
                   amp=amp, on_predictions=score, total=len(loader),
                   scored=None if owned is None else {dataset.sample_tokens[i] for i in owned}, persist=persist)
    if persist is not None:
        notes.append(f"model.temporal.persist_frames={cfg.model.temporal.persist_frames}: {val['persisted']} map "
                     "elements found in earlier frames and missed later were kept (persistence.py)"
                     + (" (under torchrun a single-frame model's ranks see no consecutive frames: none kept)"
                        if world > 1 and owned is None else ""))
    for part in du.all_gather_object(results)[1:]:
        results.update(part)
    results = {t: results[t] for t in dataset.sample_tokens if t in results}  # dataset order
    if len(results) < len(dataset):  # named here too: the warnings that say why vanish under -W ignore
        left = [t for t in dataset.sample_tokens if t not in results]
        notes.append(f"{len(left)} bad sample(s) of {len(dataset)} left out (data.on_bad_sample=skip; the warnings "
                     f"say why): {', '.join(left[:5])}{' ...' if len(left) > 5 else ''}")
    metrics = meter_results(flicker, cmap, evaluator)  # (gathered over the ranks)
    metrics = {**metrics.pop("metrics"), **metrics}
    if "memory" in val:
        metrics["memory"] = val["memory"]
    samples_per_s = round(val["samples_per_s"] * world, 3)
    metrics["meta"] = {"checkpoint": str(checkpoint), "config_name": cfg.name, "dataroot": cfg.data.dataroot,
                       "version": cfg.data.version, "split": split, "num_samples": len(dataset),
                       "samples_per_s": samples_per_s, **{k: v for k, v in decode.items() if k != "max_edge_px"},
                       "max_edge_m": cfg.model.gnn.max_edge_m, "precision": precision_of(model),
                       "compile_backbone": compile_backbone, "config_notes": notes}
    paths = _write_pair(Path(out), results, metrics, submission_meta(cfg, split, f"checkpoint {checkpoint}"))
    return {"metrics": metrics, "paths": paths, "notes": notes, "num_samples": len(dataset),
            "samples_per_s": samples_per_s}
