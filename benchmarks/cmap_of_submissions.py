"""MapTracker's consistency-aware mAP of finished evaluations, from their ``submission.json`` (no model run).

    python benchmarks/cmap_of_submissions.py --config configs/temporal/synthetic.yaml \\
        --dataroot ~/.cache/instagram_hdmap/synthetic-5e288385e0 runs/temporal_dropout_long/*/eval_val12*

Each submission's predictions are scored against the split's GT with ``ConsistentAPMeter`` (predicted instance
IDs: the submission's own ``track_id`` where every vector has one, as ``predict --scene`` and ``Mapper.stream()``
write them, else the persistence matcher's; GT tracks from the flicker meter's geometric link; docs/temporal.md),
with the ID switches per 100 frames at 1.0 m, and the meter's own time per sample: the cost of ``eval.cmap=true``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from instagram_hdmap.config import UserError, load_config
from instagram_hdmap.data import build_dataset
from instagram_hdmap.demo import world_overrides
from instagram_hdmap.evaluation.io import read_submission
from instagram_hdmap.train import make_cmap_meter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("evals", nargs="+", help="evaluation folders holding submission.json")
    parser.add_argument("--config", required=True)
    parser.add_argument("--dataroot", required=True, help="the world the evaluations ran on")
    parser.add_argument("--split", default="val")
    parser.add_argument("--match-m", type=float, default=None,
                        help="the tracker's match distance (default: the config's eval.cmap_match_m, 1.0 m)")
    args = parser.parse_args()
    missing = [f for f in args.evals if not (Path(f) / "submission.json").is_file()]
    if missing:  # before the dataset is read: a glob that matched nothing stays a literal pattern
        parser.error(f"no submission.json in {', '.join(missing[:3])}" + (f" and {len(missing) - 3} more" if
                                                                          len(missing) > 3 else ""))
    try:  # --match-m 0 was taken as "not given" (the default 1.0 m scored with no word); a bad value is one line
        cfg = load_config(args.config, [*world_overrides(Path(args.dataroot).expanduser()), "eval.cmap=true",
                                        *([f"eval.cmap_match_m={args.match_m}"] if args.match_m is not None else [])])
        ds = build_dataset(cfg, args.split, augment=False)
    except UserError as e:
        parser.error(str(e).replace("eval.cmap_match_m", "eval.cmap_match_m (--match-m)"))
    index = {t: i for i, t in enumerate(ds.sample_tokens)}
    gts = {t: ds.gt_polylines(i) for t, i in index.items()}
    print(f"{'evaluation':<60}{'mAP':>8}{'C-mAP':>8}  C-AP per class; switched TPs at 1.0 m; ID switches per 100 "
          "frames; IDs; ms/sample")
    for folder in args.evals:
        try:
            preds = read_submission(Path(folder) / "submission.json", "pred", len(cfg.data.classes)).samples
        except UserError as e:
            parser.error(str(e))
        missing, extra = len(set(index) - set(preds)), len(set(preds) - set(index))
        if missing == len(index):  # another world or split: C-mAP of no sample was printed as nan, exit 0
            parser.error(f"{folder}/submission.json has none of the {len(index)} samples of split '{args.split}' of "
                         f"{args.dataroot} (its {len(preds)} samples are of another split or world)")
        if missing or extra:  # scored on the samples both have, which was not said
            print(f"note: {folder}/submission.json lacks {missing} of the {len(index)} samples of split "
                  f"'{args.split}'" + (f" and has {extra} samples not in it" if extra else "")
                  + f": its C-mAP is over the {len(index) - missing} it has", file=sys.stderr)
        meter = make_cmap_meter(cfg)
        t0 = time.perf_counter()
        tokens = [t for t in ds.sample_tokens if t in preds]
        given = all("track_id" in p for t in tokens for p in preds[t])  # the submission's own IDs
        for s in range(0, len(tokens), 8):
            part = tokens[s:s + 8]
            ids = [index[t] for t in part]
            meter.update([preds[t] for t in part], [gts[t] for t in part], [ds.scene_of(i) for i in ids],
                         [ds.scenes.frame[i] for i in ids], torch.stack([ds.ego_pose(i) for i in ids]),
                         ids=[[p["track_id"] for p in preds[t]] for t in part] if given else None)
        res = meter.compute()
        ms = (time.perf_counter() - t0) / max(len(tokens), 1) * 1000
        per = ", ".join(f"{k} {v:.3f}" for k, v in res["C-AP_class"].items())
        switched = sum(v[1] for v in res["switched"].values())
        per_100 = 100 * sum(v[1] for v in res["id_switches"].values()) / max(len(tokens), 1)
        print(f"{folder[-60:]:<60}{res['mAP']:>8.3f}{res['C-mAP']:>8.3f}  {per}; {switched}; {per_100:.1f}; "
              f"{'given' if given else 'tracked'}; {ms:.0f}")


if __name__ == "__main__":
    main()
