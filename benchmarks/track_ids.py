"""Map elements that keep their identity along a drive: ID switches and consistency-aware mAP of the track IDs
``Mapper.stream()`` outputs, single-frame against temporal model, on an occluded world of roads never seen in
training.

    python benchmarks/temporal.py --minutes 12 --seeds 0 --occluders 0.7 --out runs/temporal_bench   # the models
    python benchmarks/track_ids.py --runs runs/temporal_bench --seeds 0 --occluders 0.7

For each model of ``--runs`` (``single_seedS/run/last.pt``, the demo config; ``temporal_seedS/run/last.pt``, the BEV
memory) every scene of the validation world (``demo.VAL_WORLD`` with ``--occluders``, the world temporal.py
validates on) is streamed frame by frame through ``Mapper.stream()``, as a user runs it: camera images as files, the
calibration and the ego pose (float64) of the nuScenes tables. The elements' ``track_id`` (the stream's tracker,
``persistence.stream_tracker``: within 1.5 m, looking back 5 frames) are scored by ``ConsistentAPMeter`` with the
IDs given, and for comparison with the meter's own tracker (1.0 m, the previous frame only). Printed: one Markdown
table, a row per model and IDs: mAP, C-mAP, ID switches per 100 frames (a GT track's true positive at 1.0 m whose
prediction ID differs from its previous one, all classes; MOTA's IDSW), the tracks output. ``RUNS/track_ids.json``
keeps the table; ``RUNS/<model>_seedS/tracks.json`` the stream's predictions with their ``track_id`` (HDMapNet JSON,
for ``benchmarks/cmap_of_submissions.py``). Persistence is off for both (``--persist`` sets it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from pyquaternion import Quaternion
from tqdm import tqdm

MODELS = ("single", "temporal")


def frame_of(dataset, index: int):
    """Sample ``index`` of a nuScenes dataset as the ``Frame`` a user gives: image files, calibration and the
    ego pose (float64) from the tables."""
    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import CAMERAS

    def matrix(record) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Quaternion(record["rotation"]).rotation_matrix, record["translation"]
        return T

    nusc, sample = dataset.nusc, dataset.nusc.get("sample", dataset.sample_tokens[index])
    records = [nusc.get("sample_data", sample["data"][cam]) for cam in CAMERAS]
    calibrated = [nusc.get("calibrated_sensor", r["calibrated_sensor_token"]) for r in records]
    images = [str(p) for p, _ in dataset.camera_files(index)]
    return Frame(images, [np.array(c["camera_intrinsic"]) for c in calibrated], [matrix(c) for c in calibrated],
                 ego_pose=matrix(dataset._reference_pose(sample)))


def stream_split(mapper, dataset, progress: bool = True) -> dict[str, list[dict]]:
    """Every scene of ``dataset`` through one ``Mapper.stream()`` (reset at each scene): token -> polyline dicts
    with ``score`` and ``track_id``."""
    stream, out = mapper.stream(), {}
    for scene in tqdm(dataset.scenes.names, desc="scenes", disable=not progress):
        stream.reset()
        for i in dataset.scene_indices(scene):
            out[dataset.sample_tokens[i]] = [e.as_polyline() for e in stream.step(frame_of(dataset, i))]
    return out


def score(cfg, dataset, preds: dict[str, list[dict]], given: bool) -> dict:
    """``ConsistentAPMeter`` over the split: the predictions' own ``track_id`` (``given``) or the meter's tracker."""
    from instagram_hdmap.training_data import make_cmap_meter

    meter = make_cmap_meter(cfg)
    for i, token in enumerate(dataset.sample_tokens):
        polys = preds[token]
        meter.update([polys], [dataset.gt_polylines(i)], [dataset.scene_of(i)], [dataset.scenes.frame[i]],
                     torch.stack([dataset.ego_pose(i)]), ids=[[p["track_id"] for p in polys]] if given else None)
    res = meter.compute()
    at_1m = list(cfg.eval.thresholds).index(1.0)
    switches = sum(v[at_1m] for v in res["id_switches"].values())
    return {"mAP": res["mAP"], "C-mAP": res["C-mAP"], "id_switches": switches,
            "id_switches_per_100": 100 * switches / len(dataset), "tracks": res["tracks"]["pred"],
            "frames": len(dataset)}


def retrack(cfg, dataset, preds: dict[str, list[dict]], match_m: float, look_back: int) -> dict[str, list[dict]]:
    """The stream's predictions with the IDs of another ``InstanceTracker`` (its match distance and look-back)."""
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.persistence import InstanceTracker

    tracker, out = InstanceTracker(BEVGrid.from_config(cfg.grid), match_m, look_back=look_back), {}
    for i, token in enumerate(dataset.sample_tokens):
        ids = tracker.step(preds[token], dataset.scene_of(i), dataset.scenes.frame[i],
                           dataset.ego_pose(i).double().numpy())
        out[token] = [{**p, "track_id": k} for p, k in zip(preds[token], ids)]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", required=True, help="benchmarks/temporal.py's --out")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--occluders", type=float, default=0.7, help="occluder density of the validation world")
    p.add_argument("--persist", type=int, default=0, help="model.temporal.persist_frames of both models")
    p.add_argument("--cache", help="world cache (default: the demo's)")
    p.add_argument("--retrack", action="store_true",
                   help="also re-track each model's predictions offline at 1.0 / 1.5 / 2.0 m, looking back 1 and 5 "
                   "frames: what the tracker's settings do")
    args = p.parse_args()
    from instagram_hdmap import Mapper
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.demo import VAL_WORLD, default_cache_dir, ensure_world, world_overrides
    from instagram_hdmap.evaluation import write_submission
    from instagram_hdmap.persistence import TRACK_LOOK_BACK, TRACK_MATCH_M

    runs = Path(args.runs)
    checkpoints = {(m, s): runs / f"{m}_seed{s}" / "run" / "last.pt" for m in MODELS for s in args.seeds}
    missing = [str(c) for c in checkpoints.values() if not c.is_file()]
    if missing:
        p.error(f"no checkpoint {', '.join(missing)}: train them with benchmarks/temporal.py --out {runs}")
    val_root, _ = ensure_world(Path(args.cache) if args.cache else default_cache_dir(),
                               {**VAL_WORLD, "occluders": args.occluders})
    rows = []
    for (model, seed), ckpt in checkpoints.items():
        overrides = [*world_overrides(val_root), f"model.temporal.persist_frames={args.persist}", "eval.cmap=true"]
        mapper = Mapper.from_checkpoint(ckpt, "cpu", overrides=overrides)
        dataset = build_dataset(mapper.config, mapper.config.data.val_split, augment=False)
        preds = stream_split(mapper, dataset)
        write_submission(runs / f"{model}_seed{seed}" / "tracks.json", preds,
                         {"checkpoint": str(ckpt), "dataroot": str(val_root), "look_back": TRACK_LOOK_BACK})
        for given in (True, False):
            ids = (f"stream ({TRACK_MATCH_M} m, look back {TRACK_LOOK_BACK})" if given else
                   f"meter ({mapper.config.eval.cmap_match_m} m, previous frame)")
            rows.append({"model": model, "seed": seed, "ids": ids, **score(mapper.config, dataset, preds, given)})
        for match_m in (1.0, 1.5, 2.0) if args.retrack else ():
            for look_back in (1, 5):
                again = retrack(mapper.config, dataset, preds, match_m, look_back)
                rows.append({"model": model, "seed": seed, "ids": f"re-tracked ({match_m} m, look back {look_back})",
                             **score(mapper.config, dataset, again, True)})
    print(f"\nvalidation world {val_root} (roads never seen in training, occluders {args.occluders}), "
          f"persist_frames {args.persist}\n")
    print("| model | seed | IDs | mAP | C-mAP | ID switches / 100 frames | tracks | frames |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['model']} | {r['seed']} | {r['ids']} | {r['mAP']:.3f} | {r['C-mAP']:.3f} | "
              f"{r['id_switches_per_100']:.1f} | {r['tracks']} | {r['frames']} |")
    (runs / "track_ids.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
