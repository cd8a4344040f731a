"""Is int8 worth it here? A checkpoint's ONNX export against its onnxruntime static int8 quantization (the
convolutions only: QOperator or QDQ, per-channel int8 weights, uint8 activations with reduced range, calibrated on
training samples; the geometry, score matrix and Sinkhorn stay float32), batch-1 latency interleaved in one run and
vector AP on the demo's validation world (roads never seen in training).

    python benchmarks/int8_onnx.py --checkpoint runs/demo/run/last.pt --config configs/synthetic/demo.yaml \\
        --train-occluders 0.7 --formats qoperator qdq

The CPU's extensions are printed with the table: onnxruntime's int8 convolutions use VNNI (AVX512-VNNI, AVX-VNNI,
AMX-INT8) where the CPU has it; on AVX2 alone they multiply in 16 bits. Nothing here is a product path: this
measures whether one should be built.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path


def quantize(fp32: Path, out: Path, calibration: list[dict], fmt: str) -> None:
    """onnxruntime's static quantization of the convolutions of ``fp32``, its metadata's graph hash stamped
    again (``inference.read_metadata`` checks it)."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    from instagram_hdmap.inference import META_GRAPH_SHA, graph_sha256

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.feeds = iter(calibration)

        def get_next(self):
            return next(self.feeds, None)

    quantize_static(str(fp32), str(out), Reader(), quant_format=QuantFormat.QDQ if fmt == "qdq" else
                    QuantFormat.QOperator, op_types_to_quantize=["Conv"], per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, reduce_range=True)
    proto = onnx.load(str(out))
    for prop in proto.metadata_props:
        if prop.key == META_GRAPH_SHA:
            prop.value = graph_sha256(proto)
    onnx.save(proto, str(out))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--config", default="configs/synthetic/demo.yaml")
    p.add_argument("--formats", nargs="+", default=["qoperator"], choices=["qoperator", "qdq"])
    p.add_argument("--calibration", type=int, default=16, help="training samples the activation ranges come from")
    p.add_argument("--train-occluders", type=float, default=0.0, help="occluders of the training world it trained on")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    from instagram_hdmap.config import load_config
    from instagram_hdmap.data import build_dataset
    from instagram_hdmap.data.base import collate_fn
    from instagram_hdmap.demo import VAL_WORLD, WORLD, default_cache_dir, ensure_world, world_overrides
    from instagram_hdmap.deploy import export_checkpoint
    from instagram_hdmap.evaluation import Evaluator
    from instagram_hdmap.geometry import BEVGrid
    from instagram_hdmap.inference import OnnxModel
    from instagram_hdmap.postprocess import decode_options, postprocess_batch
    from instagram_hdmap.resources import cpu_capability

    world = {**WORLD, **({"occluders": args.train_occluders} if args.train_occluders else {})}
    train_root, _ = ensure_world(default_cache_dir(), world)
    val_root, _ = ensure_world(default_cache_dir(), VAL_WORLD)
    cfg = load_config(args.config, [*world_overrides(train_root), "train.device=cpu"])
    val_cfg = load_config(args.config, [*world_overrides(val_root), "train.device=cpu"])
    with tempfile.TemporaryDirectory() as tmp:
        fp32 = Path(tmp) / "fp32.onnx"
        export_checkpoint(cfg, args.checkpoint, fp32, verify=False)
        models = {"fp32": OnnxModel(fp32, cfg, threads=args.threads)}
        train = build_dataset(cfg, cfg.data.train_split, augment=False)
        ref = models["fp32"]
        step = max(1, len(train) // args.calibration)
        calibration = [{n: ref._input(n, b[n]).contiguous().numpy() for n in ref.input_names}
                       for b in (collate_fn([train[i]]) for i in range(0, len(train), step)[: args.calibration])]
        for fmt in args.formats:
            out = Path(tmp) / f"int8_{fmt}.onnx"
            quantize(fp32, out, calibration, fmt)
            models[f"int8 {fmt}"] = OnnxModel(out, cfg, threads=args.threads)
        val = build_dataset(val_cfg, val_cfg.data.val_split, augment=False)
        first = collate_fn([val[0]])
        times = {k: [] for k in models}
        for m in models.values():
            m(first)  # warm
        for _ in range(args.runs):  # interleaved rounds
            for name, m in models.items():
                t0 = time.perf_counter()
                m(first)
                times[name].append(time.perf_counter() - t0)
        grid = BEVGrid.from_config(cfg.grid)
        options = decode_options(cfg.model.gnn, grid)
        print(f"\ncheckpoint {args.checkpoint}; {len(val)} validation frames (unseen roads); cpu: {cpu_capability()}; "
              f"{args.threads} thread(s)\n")
        print("| model | median ms | x fp32 | divider | ped_crossing | boundary | mAP |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        base = statistics.median(times["fp32"])
        for name, m in models.items():
            ev = Evaluator.from_config(val_cfg)
            for i in range(len(val)):
                sample = val[i]
                ev.update(postprocess_batch(m(collate_fn([sample])), grid, **options), [sample["gt_polylines"]],
                          sample_ids=[i])
            r, ms = ev.compute(), statistics.median(times[name])
            print(f"| {name} | {1000 * ms:.1f} | {ms / base:.2f} | " + " | ".join(f"{v:.4f}" for v in
                                                                               r["AP_class"].values())
                  + f" | {r['mAP']:.4f} |")


if __name__ == "__main__":
    main()
