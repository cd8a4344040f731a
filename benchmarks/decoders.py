"""Decoders of the adjacency compared on trained checkpoints: vector AP per class, no retraining.

    python benchmarks/decoders.py --world VAL_WORLD --world SEEN=TRAIN_WORLD \\
        A=runs/a/run/last.pt D=runs/d/run/last.pt \\
        --variant mutual=model.gnn.decoder=mutual,model.gnn.match_threshold=0.1,model.gnn.max_edge_m=null \\
        --variant official=model.gnn.decoder=official,model.gnn.match_threshold=0.1,model.gnn.max_edge_m=null \\
        --variant greedy=model.gnn.match_threshold=0.1,model.gnn.same_class_edges=false,model.gnn.max_edge_m=null

(a variant is one argument: no space after its commas). ``mutual`` is the official rule
(both ends of an edge of the same argmax class, the mean class probability as the confidence); the
figures in benchmarks/README.md's "Decoding" section were measured with the earlier class-agnostic
rule, which no decoder reproduces any more.

Each checkpoint runs once over the val split of each world (``[NAME=]DATAROOT``, a synthetic world
as the demo writes it); its post-processing inputs are kept and decoded by every ``--variant``
(``NAME=key=value,key=value``: ``model.gnn`` decoding keys applied to the checkpoint's saved config,
validated like any override), and by the checkpoint's own settings (row ``own``). The table gives the
vector-protocol AP per class, the ped-crossing AP at each threshold, the number of predicted
instances and the mAP, so that decoding rules are compared on the same network outputs. Choose
settings on one world (e.g. the training world's own val split) and read them on another.
"""

from __future__ import annotations

import argparse
import math

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from instagram_hdmap.checkpoint import load_checkpoint
from instagram_hdmap.config import (
    UserError,
    config_from_dict,
    config_to_dict,
    deep_update,
    load_config,
    parse_overrides,
)
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.data.nuscenes import NuScenesMapDataset
from instagram_hdmap.demo import world_overrides
from instagram_hdmap.errors import one_line
from instagram_hdmap.evaluation import Evaluator
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.inference import load_model
from instagram_hdmap.postprocess import DECODE_KEYS, REQUIRED_OUTPUTS, decode_options, postprocess_batch


def run_outputs(checkpoint: str, world: str) -> tuple[list[tuple[dict, list]], object]:
    """The checkpoint's post-processing inputs and the GT polylines, batch by batch, and its config."""
    saved = config_from_dict(load_checkpoint(checkpoint)["config"])
    model, cfg, _ = load_model(checkpoint, saved, [*world_overrides(world), "train.device=cpu"],
                               device=torch.device("cpu"))
    dataset = NuScenesMapDataset(cfg, cfg.data.val_split, augment=False)
    loader = DataLoader(dataset, batch_size=4, collate_fn=collate_fn, num_workers=1)
    out = []
    with torch.no_grad():
        for batch in tqdm(loader, desc=f"{checkpoint} on {world}", total=math.ceil(len(dataset) / 4), leave=False):
            outputs = model(batch)
            out.append(({k: outputs[k] for k in REQUIRED_OUTPUTS}, batch["gt_polylines"]))
    return out, cfg


def variant_config(cfg, overrides: list[str]):
    bad = [o for o in overrides if o.split("=", 1)[0] not in DECODE_KEYS]
    if bad:
        raise UserError(f"--variant takes decoding keys only ({', '.join(DECODE_KEYS)}); got {bad}")
    merged = config_to_dict(cfg)
    deep_update(merged, parse_overrides(overrides))
    return config_from_dict(merged)


def score(batches, cfg) -> dict:
    grid = BEVGrid.from_config(cfg.grid)
    opts = decode_options(cfg.model.gnn, grid)
    evaluator = Evaluator.from_config(cfg)
    seen = 0
    for outputs, gts in batches:
        preds = postprocess_batch(outputs, grid, **opts)
        evaluator.update(preds, gts, sample_ids=list(range(seen, seen + len(preds))))
        seen += len(preds)
    return evaluator.compute()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+", help="NAME=CHECKPOINT")
    ap.add_argument("--world", action="append", required=True, help="[NAME=]DATAROOT of a synthetic world (val split)")
    ap.add_argument("--variant", action="append", default=[], help="NAME=key=value,key=value (decoding keys)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, threads=1)
    torch.set_num_threads(args.threads)
    variants = []  # checked before the checkpoints run (a malformed one was an IndexError, a bad value came after)
    for v in args.variant:
        name, _, rest = v.partition("=")
        if not name or not rest:
            ap.error(f"--variant {v!r}: expected NAME=key=value[,key=value...], e.g. "
                     "t05=model.gnn.match_threshold=0.05")
        overrides = [o if o.startswith("model.gnn.") else f"model.gnn.{o}" for o in rest.split(",")]
        try:
            variant_config(load_config(None), overrides)
        except UserError as e:
            ap.error(f"--variant {v}: {one_line(e)}")
        variants.append((name, overrides))
    print("| world | checkpoint | decoding | divider | ped crossing | boundary | mAP "
          "| ped crossing at 0.5 / 1.0 / 1.5 m | instances |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for w in args.world:
        wname, _, wroot = w.rpartition("=")
        wname = wname or wroot
        for item in args.checkpoints:
            name, _, path = item.partition("=")
            batches, cfg = run_outputs(path or name, wroot)
            for vname, overrides in [("own", []), *variants]:
                m = score(batches, variant_config(cfg, overrides))
                ap_c = m["AP_class"]
                ped = " / ".join(f"{v:.3f}" for v in m["AP"]["ped_crossing"])
                print(f"| {wname} | {name} | {vname} | {ap_c['divider']:.3f} | {ap_c['ped_crossing']:.3f} | "
                      f"{ap_c['boundary']:.3f} | {m['mAP']:.3f} | {ped} | {sum(m['num_pred'].values())} |", flush=True)


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
