"""Per-class diagnosis of trained checkpoints: why does a class (ped crossings) score low?

For each ``NAME=CHECKPOINT`` the model runs over the validation split of a world and the table
gives, per class, vertex recall / precision, distance-transform error, adjacency accuracy, decoded
edge recall, whole-instance and closed-polygon rates (instagram_hdmap/diagnostics.py defines
them) and the vector-protocol AP.

    python benchmarks/ped_crossing_diagnosis.py --world DATAROOT before=runs/a/run/last.pt after=runs/b/run/last.pt

The config of each checkpoint is the one saved in it; ``--world`` points the data keys at a
synthetic world (its ``splits.json``, split ``val``). ``--decode key=value ...`` changes the
decoding keys (``model.gnn.decoder``, ``match_threshold``, ``class_min_prob``, ``same_class_edges``,
``max_edge_m``) of every checkpoint, e.g. to diagnose one checkpoint under two decoders:
``NAME=CKPT`` twice in two runs, or ``--decode model.gnn.decoder=mutual model.gnn.max_edge_m=null``.
"""

from __future__ import annotations

import argparse
import math

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from instagram_hdmap.checkpoint import load_checkpoint
from instagram_hdmap.config import config_from_dict
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.data.nuscenes import NuScenesMapDataset
from instagram_hdmap.diagnostics import ClassDiagnostics, format_table
from instagram_hdmap.engine import move_to
from instagram_hdmap.evaluation import Evaluator
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.inference import load_model
from instagram_hdmap.losses import Criterion
from instagram_hdmap.postprocess import decode_options, postprocess_batch


def diagnose(checkpoint: str, world: str, limit: int | None = None, threads: int | None = None,
             split: str | None = None, decode: list[str] = ()) -> dict:
    from instagram_hdmap.demo import world_overrides

    if threads:
        torch.set_num_threads(threads)
    saved = config_from_dict(load_checkpoint(checkpoint)["config"])
    model, cfg, _ = load_model(checkpoint, saved, [*world_overrides(world), "train.device=cpu", *decode],
                               device=torch.device("cpu"))
    grid = BEVGrid.from_config(cfg.grid)
    criterion = Criterion(cfg.loss, grid)
    dataset = NuScenesMapDataset(cfg, split or cfg.data.val_split, augment=False)
    n = len(dataset) if limit is None else min(limit, len(dataset))
    loader = DataLoader(torch.utils.data.Subset(dataset, range(n)), batch_size=4, collate_fn=collate_fn)
    decode = decode_options(cfg.model.gnn, grid)
    diag = ClassDiagnostics(len(cfg.data.classes), cfg.data.dt_clip, decode)
    evaluator = Evaluator.from_config(cfg)
    seen = 0
    with torch.no_grad():
        for batch in tqdm(loader, desc=checkpoint, total=math.ceil(n / 4), leave=False):
            batch = move_to(batch, torch.device("cpu"))
            outputs = model(batch)
            diag.update(outputs, batch, criterion.assign(outputs, batch))
            preds = postprocess_batch(outputs, grid, **decode)
            evaluator.update(preds, batch["gt_polylines"], sample_ids=list(range(seen, seen + len(preds))))
            seen += len(preds)
    result = diag.compute()
    metrics = evaluator.compute()
    result["AP"] = [metrics["AP_class"][c] for c in metrics["classes"]]
    result["mAP"] = metrics["mAP"]
    result["classes"] = list(metrics["classes"])
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+", help="NAME=CHECKPOINT")
    ap.add_argument("--world", required=True, help="dataroot of a synthetic world (its val split is used)")
    ap.add_argument("--limit", type=int, default=None, help="first samples of the split only")
    ap.add_argument("--split", default=None, help="split of the world (default: the config's val split)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--decode", nargs="*", default=[], help="decoding overrides (key=value) for every checkpoint")
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, limit=1, threads=1)
    results = {}
    for item in args.checkpoints:
        name, _, path = item.partition("=")
        results[name] = diagnose(path or name, args.world, args.limit, args.threads, args.split, args.decode)
    classes = next(iter(results.values()))["classes"]
    print(format_table(results, classes))
    print()
    print("| model | " + " | ".join(f"AP {c}" for c in classes) + " | mAP |")
    print("|" + " --- |" * (len(classes) + 2))
    for name, r in results.items():
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in r["AP"]) + f" | {r['mAP']:.3f} |")
    if args.json:
        from instagram_hdmap.files import write_json

        write_json(results, args.json, indent=1)  # standard JSON: a raster AP of NaN is written as null


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
