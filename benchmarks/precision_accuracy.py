"""Does a lower precision keep the accuracy? One checkpoint evaluated in fp32, bf16 and int8 (``evaluate
--precision``; precision.py) on the demo's validation world (roads never seen in training), vector protocol: AP per
class, mAP, their differences from fp32, and the evaluation's samples/s. int8 calibrates on samples of the demo's
training world (the world the checkpoint trained on), never on the validation world.

    python benchmarks/precision_accuracy.py --checkpoint runs/demo/run/last.pt

The target: every class's AP and the mAP of bf16 within 0.005 of fp32, of int8 within 0.01. The CPU's extensions
are printed with the table: on a CPU without native bfloat16 (no AVX512-BF16 / AMX-BF16) torch emulates it, so the
accuracy holds but
the speed is not the product's (benchmarks/model_speed.py measures speed).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

TARGET = {"bf16": 0.005, "int8": 0.01}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--config", default="configs/synthetic/demo.yaml", help="the config the checkpoint was trained with")
    p.add_argument("--precisions", nargs="+", default=["fp32", "bf16", "int8"],
                   choices=["fp32", "bf16", "int8"])
    p.add_argument("--cache", help="world cache (default: the demo's)")
    p.add_argument("--occluders", type=float, default=0.0, help="occluder density of the validation world")
    p.add_argument("--val-scenes", type=int, default=None,
                   help="scenes of the validation world (default the demo's 4: 80 frames, whose AP moves by a few "
                   "hundredths between equal models; more narrow it)")
    args = p.parse_args()
    from instagram_hdmap.config import load_config
    from instagram_hdmap.demo import VAL_WORLD, WORLD, default_cache_dir, ensure_world, world_overrides
    from instagram_hdmap.evaluate_split import run_evaluation
    from instagram_hdmap.precision import calibration_batches
    from instagram_hdmap.resources import cpu_capability

    world = {**VAL_WORLD, **({"occluders": args.occluders} if args.occluders else {}),
             **({"scenes_val": args.val_scenes} if args.val_scenes else {})}
    cache = Path(args.cache) if args.cache else default_cache_dir()
    root, _ = ensure_world(cache, world)
    cfg = load_config(args.config, [*world_overrides(root), "train.device=cpu"])
    calibration = None
    if "int8" in args.precisions:
        train_root, _ = ensure_world(cache, WORLD)
        calibration = calibration_batches(load_config(args.config, [*world_overrides(train_root), "train.device=cpu"]))
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for precision in args.precisions:
            result = run_evaluation(cfg, args.checkpoint, "vector", Path(tmp) / precision, precision=precision,
                                    calibration=calibration)
            rows[precision] = (result["metrics"], result["samples_per_s"])
    classes = list(next(iter(rows.values()))[0]["AP_class"])
    print(f"\ncheckpoint {args.checkpoint}; validation world {root} (unseen roads); cpu: {cpu_capability()}\n")
    print("| precision | " + " | ".join(classes) + " | mAP | samples/s |")
    print("| --- " * (len(classes) + 3) + "|")
    for precision, (m, speed) in rows.items():
        print(f"| {precision} | " + " | ".join(f"{m['AP_class'][c]:.4f}" for c in classes)
              + f" | {m['mAP']:.4f} | {speed:.2f} |")
    if "fp32" in rows:
        base = rows["fp32"][0]
        for precision, (m, _) in rows.items():
            if precision == "fp32":
                continue
            deltas = [m["AP_class"][c] - base["AP_class"][c] for c in classes] + [m["mAP"] - base["mAP"]]
            ok = all(abs(d) <= TARGET[precision] for d in deltas)
            print(f"| {precision} - fp32 | " + " | ".join(f"{d:+.4f}" for d in deltas)
                  + f" | {'within' if ok else 'NOT within'} {TARGET[precision]} |")


if __name__ == "__main__":
    main()
