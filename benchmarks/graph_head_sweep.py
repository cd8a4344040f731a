"""Graph-head variants trained on a trained model's *predicted* vertices and distance transforms.

    python benchmarks/graph_head_sweep.py --checkpoint runs/demo/run/last.pt --world TRAIN_WORLD \\
        --val-world VAL_WORLD --steps 1500 base= wide=model.gnn.dim=64,model.gnn.layers=4

The GNN oracle (oracle_gnn.py) feeds the graph head ground truth; this feeds it what the image side
of a trained checkpoint really predicts (its vertex logits and distance transform, computed once
per sample with the image side frozen), so graph-head settings (width, depth, positional bands,
vertex count, thresholds, loss weights) can be compared in minutes instead of full trainings. Each
``NAME=key=value,key=value`` variant builds a fresh graph head from the checkpoint's config with
those overrides, trains it with Adam (cosine LR over ``--steps``) on the adjacency and class terms
of ``losses.Criterion``, and is scored on the validation world: per-class diagnostics
(diagnostics.py) and vector-protocol AP after post-processing. The checkpoint's own graph head is
scored too (row ``checkpoint``).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from tqdm import tqdm

from instagram_hdmap.checkpoint import load_checkpoint
from instagram_hdmap.config import UserError, config_from_dict, config_to_dict, deep_update, parse_overrides
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.data.nuscenes import NuScenesMapDataset
from instagram_hdmap.demo import world_overrides
from instagram_hdmap.diagnostics import ClassDiagnostics, format_table
from instagram_hdmap.errors import one_line
from instagram_hdmap.evaluation import Evaluator
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.inference import load_model
from instagram_hdmap.losses import Criterion
from instagram_hdmap.models import build_model
from instagram_hdmap.postprocess import decode_options, postprocess_batch

KEEP = ("gt_vertices_px", "gt_vertex_mask", "gt_vertex_labels", "gt_vertex_instance", "gt_vertex_order",
        "gt_vertex_next", "gt_vertex_prev", "gt_vertex_cells", "gt_distance", "gt_polylines", "sample_token")


@torch.no_grad()
def cache_outputs(model, cfg, world: str, split: str, limit: int | None) -> list[dict]:
    """Per sample: the frozen image side's vertex logits and distance transform, and the targets."""
    wcfg = _with_world(cfg, world)
    ds = NuScenesMapDataset(wcfg, split, augment=False)
    n = len(ds) if limit is None else min(limit, len(ds))
    out = []
    for i in tqdm(range(n), desc=f"cache {split}", leave=False):
        s = ds[i]
        batch = collate_fn([s])
        feats = model.backbone(batch["images"].flatten(0, 1)).unflatten(0, batch["images"].shape[:2])
        bev = model.view_transform(feats, {k: batch[k] for k in ("intrinsics", "cam_to_ego_rot", "cam_to_ego_trans",
                                                                 "post_rot", "post_tran")})
        heads = model.bev_heads(bev)
        out.append({"pred_vertex_logits": heads["pred_vertex_logits"][0], "pred_distance": heads["pred_distance"][0],
                    **{k: s[k] for k in KEEP if k in s}})
    return out


def _with_world(cfg, world: str):
    d = config_to_dict(cfg)
    for item in world_overrides(world):
        key, _, value = item.partition("=")
        d["data"][key.split(".", 1)[1]] = value
    return config_from_dict(d)


def collate(items: list[dict]) -> dict:
    batch = collate_fn([{k: v for k, v in it.items() if k not in ("pred_vertex_logits", "pred_distance")}
                        for it in items])
    batch["pred_vertex_logits"] = torch.stack([it["pred_vertex_logits"] for it in items])
    batch["pred_distance"] = torch.stack([it["pred_distance"] for it in items])
    return batch


def head_outputs(head, batch: dict) -> dict:
    logits, distance = batch["pred_vertex_logits"], batch["pred_distance"]
    return {"pred_vertex_logits": logits, "pred_distance": distance,
            **head(logits, distance, distance.new_zeros(distance.shape[0], 0, 1, 1))}


def train_head(head, cfg, data: list[dict], steps: int, lr: float, batch_size: int, seed: int) -> float:
    criterion = Criterion(cfg.loss, BEVGrid.from_config(cfg.grid))
    opt = torch.optim.Adam(head.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    head.train()
    t0 = time.perf_counter()
    order: list[int] = []
    bar = tqdm(range(steps), desc="train head", leave=False)
    for step in bar:
        for g in opt.param_groups:
            g["lr"] = 0.5 * lr * (1 + math.cos(math.pi * step / steps))
        if len(order) < batch_size:
            order = list(rng.permutation(len(data)))
        batch = collate([data[order.pop()] for _ in range(batch_size)])
        losses = criterion(head_outputs(head, batch), batch)
        opt.zero_grad(set_to_none=True)
        losses["loss_total"].backward()
        torch.nn.utils.clip_grad_norm_(head.parameters(), cfg.train.grad_clip)
        opt.step()
        if step % 20 == 0:
            bar.set_postfix(adj=f"{float(losses['loss_adjacency']):.3f}",
                            acc=f"{float(losses['adjacency_accuracy']):.3f}")
    return time.perf_counter() - t0


@torch.no_grad()
def score(head, cfg, data: list[dict]) -> dict:
    head.eval()
    grid = BEVGrid.from_config(cfg.grid)
    criterion = Criterion(cfg.loss, grid)
    decode = decode_options(cfg.model.gnn, grid)
    diag = ClassDiagnostics(len(cfg.data.classes), cfg.data.dt_clip, decode)
    evaluator = Evaluator.from_config(cfg)
    for start in range(0, len(data), 8):
        batch = collate(data[start:start + 8])
        outputs = head_outputs(head, batch)
        diag.update(outputs, batch, criterion.assign(outputs, batch))
        preds = postprocess_batch(outputs, grid, **decode)
        evaluator.update(preds, batch["gt_polylines"], sample_ids=list(range(start, start + len(preds))))
    res = diag.compute()
    m = evaluator.compute()
    res["AP"] = [m["AP_class"][c] for c in m["classes"]]
    res["mAP"] = m["mAP"]
    res["classes"] = list(m["classes"])
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("variants", nargs="+", help="NAME=key=value,key=value (overrides of the checkpoint's config)")
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--world", required=True, help="training world (its train split)")
    ap.add_argument("--val-world", required=True, help="validation world (its val split)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--limit", type=int, default=None, help="first training samples only")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, steps=1, batch=1, limit=1, threads=1)
    if args.threads:
        torch.set_num_threads(args.threads)
    saved = config_from_dict(load_checkpoint(args.checkpoint)["config"])
    for item in args.variants:  # checked before the outputs are cached (a typo failed after that work)
        name, _, spec = item.partition("=")
        if not name:  # a bare NAME (or NAME=) is the checkpoint's own config, retrained
            ap.error(f"variant {item!r}: expected NAME=key=value[,key=value...], e.g. l3=model.gnn.layers=3")
        d = config_to_dict(saved)
        try:
            deep_update(d, parse_overrides([s for s in spec.split(",") if s]))
            config_from_dict(d)
        except UserError as e:
            ap.error(f"variant {item}: {one_line(e)}")
    model, cfg, _ = load_model(args.checkpoint, saved, ["train.device=cpu"], device=torch.device("cpu"))
    train = cache_outputs(model, cfg, args.world, cfg.data.train_split, args.limit)
    val = cache_outputs(model, cfg, args.val_world, cfg.data.val_split, None)
    results = {"checkpoint": score(model.graph_head, cfg, val)}
    for item in args.variants:
        name, _, spec = item.partition("=")
        overrides = [s for s in spec.split(",") if s]
        d = config_to_dict(cfg)
        deep_update(d, parse_overrides(overrides))
        vcfg = config_from_dict(d)
        torch.manual_seed(0)
        head = build_model(vcfg).graph_head
        seconds = train_head(head, vcfg, train, args.steps, args.lr, args.batch, 0)
        results[name] = score(head, vcfg, val)
        print(f"{name}: {args.steps} steps in {seconds:.0f} s, mAP {results[name]['mAP']:.3f}", flush=True)
    classes = results["checkpoint"]["classes"]
    print(format_table(results, classes))
    print("\n| variant | " + " | ".join(f"AP {c}" for c in classes) + " | mAP |")
    print("|" + " --- |" * (len(classes) + 2))
    for name, r in results.items():
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in r["AP"]) + f" | {r['mAP']:.3f} |")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
