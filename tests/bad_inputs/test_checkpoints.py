"""Checkpoints and ONNX files: damaged, empty, packed, of another model or another kind of file, malicious;
``train.init_from``, ``train.trainable`` and ``model.backbone.weights``; what a checkpoint's own config decides.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    TINY_YAML,
    forbid,
    mapper_frame,
    rig_files,
    row,
    table,
    temporal_checkpoint,
    toy_run,
)
from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict, load_config


def _flip_bits(path: Path, entry: str) -> None:
    """Flip the exponent bits of the first float stored in ``entry`` of a zip checkpoint."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(entry)
    data = bytearray(path.read_bytes())
    name_len, extra_len = int.from_bytes(data[info.header_offset + 26:info.header_offset + 28], "little"), \
        int.from_bytes(data[info.header_offset + 28:info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_len + extra_len
    data[start + 3] ^= 0x7F  # float32 little-endian: the byte with the sign and most of the exponent
    path.write_bytes(bytes(data))


@row("a checkpoint with flipped bits is named by the zip CRC")
def row_flipped_bits(env):
    path = env.tmp / "flipped.pt"
    shutil.copy(env.ckpt, path)
    with zipfile.ZipFile(path) as z:
        entry = next(n for n in z.namelist() if "/data/" in n and z.getinfo(n).file_size >= 64)
    _flip_bits(path, entry)
    with pytest.raises(CheckpointError, match=rf"flipped\.pt.*{re.escape(entry.split('/', 1)[1])}.*(CRC|damaged)"):
        load_checkpoint(path)
    env.error(r"flipped\.pt.*(CRC|damaged)", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")


@row("a checkpoint with non-finite weights is named with the tensor")
def row_nonfinite_weights(env):
    state = load_checkpoint(env.ckpt)
    key = next(k for k, v in state["model"].items() if v.is_floating_point() and v.numel() > 4)
    state["model"][key][3] = float("nan")
    path = save_checkpoint(state, env.tmp / "nan.pt")
    env.error(rf"nan\.pt.*{re.escape(key)}.*(NaN|non-finite)", "evaluate", env.yaml, "--checkpoint", path,
              "--out", env.tmp / "e")


@row("predict/evaluate take data.image_fit from the checkpoint, with a note when the CONFIG differs (images were "
          "fitted unlike in training without a word)")
def row_checkpoint_image_fit(env):
    from instagram_hdmap.inference import inference_config

    trained = load_config(TINY_YAML, ["data.image_fit=contain"])
    out, notes = inference_config(load_config(TINY_YAML), config_to_dict(trained))
    assert out.data.image_fit == "contain"
    assert any("data.image_fit='contain' (CONFIG: 'cover')" in n for n in notes), notes
    out, notes = inference_config(load_config(TINY_YAML, ["data.image_fit=stretch"]), config_to_dict(trained),
                                  ["data.image_fit=stretch"])  # the command line wins, and says so
    assert out.data.image_fit == "stretch" and any("data.image_fit='contain' with 'stretch'" in n for n in notes)


@row("a checkpoint whose config is YAML text (older writers) is read as its config (the note said it held none "
          "and built the model from the CONFIG file)")
def row_checkpoint_config_as_yaml_text(env):
    import yaml

    state = load_checkpoint(env.ckpt)
    text = save_checkpoint({**state, "config": yaml.safe_dump(state["config"])}, env.tmp / "yaml_config.pt")
    assert load_checkpoint(text)["config"] == state["config"]
    rc, out, err = env.cli("evaluate", env.yaml, "--checkpoint", text, "--out", env.tmp / "e")
    assert rc == 0 and "holds no config" not in out + err, (out + err)[-2000:]
    junk = save_checkpoint({**state, "config": "- just\n- a list\n"}, env.tmp / "junk_config.pt")
    env.error(r"junk_config\.pt: its config is text that is not a YAML mapping", "evaluate", env.yaml,
              "--checkpoint", junk, "--out", env.tmp / "e2")


@row("a 0-byte .pt is named as empty")
def row_empty_checkpoint(env):
    path = env.tmp / "empty.pt"
    path.write_bytes(b"")
    env.error(r"empty\.pt.*empty", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")


@row("a binary file given as the config (checkpoint and config swapped)")
def row_config_and_checkpoint_swapped(env):
    env.error(r"random\.pt.*(binary|not a text|checkpoint)", "evaluate", env.ckpt, "--checkpoint", env.yaml,
              "--out", env.tmp / "e")


@row("a YAML config given as the checkpoint")
def row_yaml_as_checkpoint(env):
    env.error(r"tiny_world\.yaml.*not a (PyTorch )?checkpoint", "evaluate", env.yaml, "--checkpoint", env.yaml,
              "--out", env.tmp / "e")


@row("a checkpoint whose 'model' is not a state dict is named (was a TypeError)")
def row_model_not_a_state_dict(env):
    path = env.tmp / "list.pt"
    torch.save({"model": [1, 2], "config": {}}, path)
    env.error(r"list\.pt holds no 'model' state dict", "evaluate", env.yaml, "--checkpoint", path,
              "--out", env.tmp / "e")


@row("model.backbone.weights that is not a torch file: one line, not torch's multi-line text")
def row_backbone_weights_not_a_checkpoint(env):
    env.error(r"model\.backbone\.weights: cannot read .*tiny_world\.yaml as a torch checkpoint", "train", env.yaml,
              "model.backbone.name=efficientnet-b0", "data.image_size=[64,160]", f"model.backbone.weights={env.yaml}",
              f"train.out_dir={env.tmp / 'r'}")


@row("a malicious checkpoint: torch's reason for refusing it is kept whole")
def row_malicious_checkpoint(env):
    path = env.tmp / "evil.pt"
    torch.save({"model": {}, "payload": print}, path)  # any callable global: refused by weights_only
    line = env.error(r"evil\.pt.*weights_only", "evaluate", env.yaml, "--checkpoint", path, "--out", env.tmp / "e")
    assert re.search(r"reason: .*Unsupported global: GLOBAL (builtins\.)?print was not an allowed global", line), line


@row("an ONNX export with flipped bits in its weights is named before it runs (onnxruntime ran it: exit 0)")
def row_onnx_flipped_bits(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    import onnx

    from instagram_hdmap import Mapper
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.inference import DeployError
    from instagram_hdmap.models import build_model

    cfg = load_config(TINY_YAML, ["model.gnn.sinkhorn_iters=3"])
    torch.manual_seed(0)
    path = env.tmp / "m.onnx"
    export_onnx(build_model(cfg).eval(), cfg, path)
    Mapper.from_onnx(path)  # intact: loads
    weights = max(onnx.load(str(path)).graph.initializer, key=lambda t: len(t.raw_data)).raw_data
    data = bytearray(path.read_bytes())
    at = data.find(weights)
    assert at > 0
    data[at + 3] ^= 0x7F  # the first float's sign and exponent: a weight of about 1e38
    damaged = env.tmp / "damaged.onnx"
    damaged.write_bytes(bytes(data))
    with pytest.raises(DeployError, match=r"damaged\.onnx is damaged: its graph .* does not match the SHA-256"):
        Mapper.from_onnx(damaged)
    rig, images = rig_files(env)
    env.error(r"damaged\.onnx is damaged", "predict-images", "--onnx", damaged, "--rig", rig, "--out",
              env.tmp / "out", *images)


@row("export-onnx (and benchmark without a dataset) of an AV2 model takes its rig's camera count (the graph took "
          "six cameras: AV2 frames could not run it; an MLP model's export was a raw ValueError)")
def row_av2_export_takes_seven_cameras(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.models import build_model

    av2 = ["data.dataset=av2", "data.dataroot=absent", "model.gnn.sinkhorn_iters=3"]
    rc, out, err = env.cli("benchmark", TINY_YAML, *av2, "model.view_transform.kind=mlp",
                           "model.view_transform.num_cameras=7", "--device", "cpu", "--runs", "1", "--warmup", "0")
    assert rc == 0 and "Traceback" not in err, err[-2000:]
    cfg = load_config(TINY_YAML, av2)
    torch.manual_seed(0)
    info = export_onnx(build_model(cfg).eval(), cfg, env.tmp / "av2.onnx")
    assert info["inputs"]["images"][1] == 7


@row("an ONNX export of a temporal model given a memory as numpy arrays, int32 indices or a float mask: taken, "
          "or named (raw onnxruntime errors / AttributeError)")
def row_onnx_memory_dtypes(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.inference import DeployError
    from instagram_hdmap.models import build_model

    cfg = load_config(TINY_YAML, ["model.gnn.sinkhorn_iters=3", "model.temporal.memory=bev"])
    torch.manual_seed(0)
    path = env.tmp / "t.onnx"
    export_onnx(build_model(cfg).eval(), cfg, path)
    mapper = Mapper.from_onnx(path)
    _, images, K, poses = mapper_frame(env)
    batch = mapper.batch([Frame(images=images, intrinsics=K, cam_to_ego=poses, ego_pose=np.eye(4))])
    model = mapper.model
    memory = model(batch)["memory"]
    expected = model(batch, memory)["pred_heatmap"]
    numpy_memory = {k: v.numpy() for k, v in memory.items()}
    numpy_memory["frame_index"] = numpy_memory["frame_index"].astype(np.int32)
    torch.testing.assert_close(model(batch, numpy_memory)["pred_heatmap"], expected)
    with pytest.raises(DeployError, match=r"t\.onnx takes memory_valid as booleans; the batch has torch\.float32"):
        model(batch, {**memory, "valid": memory["valid"].float()})
    with pytest.raises(DeployError, match=r"t\.onnx takes scene_start as booleans; the batch has torch\.int64"):
        model({**batch, "scene_start": torch.ones(1, dtype=torch.long)}, memory)


@row("export-onnx of a temporal checkpoint with a single-frame CONFIG names model.temporal.memory='bev' (CONFIG: "
          "'none') (it listed four keys as 'CONFIG: None')")
def row_export_onnx_temporal_config_named(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.models import build_model

    cfg = load_config(env.yaml, ["model.temporal.memory=bev"])
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / "t.pt")
    forbid(env, "instagram_hdmap.deploy.export_onnx", "the export")
    line = env.error(r"t\.pt is from another config: it was trained with model\.temporal\.memory='bev' \(CONFIG: "
                     r"'none'\); pass the config", "export-onnx", env.yaml, "--checkpoint", ckpt, "--out",
                     env.tmp / "t.onnx")
    assert "None" not in line


@row("train --force with train.init_from a checkpoint of train.out_dir is refused (--force removed the "
          "checkpoint before it was read: 'checkpoint not found', the weights lost)")
def row_init_from_inside_out_dir(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=1")
    before = (run / "best.pt").read_bytes()
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.init_from=.*best\.pt is the best\.pt of train\.out_dir=.*run, which this run starts over .*copy "
              r"it out of the folder", "train", env.yaml, f"train.out_dir={run}", f"train.init_from={run / 'best.pt'}",
              "--force")
    assert (run / "best.pt").read_bytes() == before


@row("train.init_from's errors name the key, and its weights' fit and train.trainable's prefixes are checked "
          "before the data loaders (a long setup on nuScenes; the message said '--checkpoint')")
def row_init_from_and_trainable_checked_first(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.init_from: .*tiny_world\.yaml is not a PyTorch checkpoint", "train", env.yaml,
              f"train.out_dir={env.tmp / 'r1'}", f"train.init_from={env.yaml}")
    line = env.error(r"train\.trainable: \['temporl'\] name no parameter of this model", "train", env.yaml,
                     f"train.out_dir={env.tmp / 'r2'}", "train.trainable=[temporl]")
    assert "--checkpoint" not in line
    env.error(r"train\.init_from: the checkpoint's weights do not fit .*temporal\.", "train", env.yaml,
              f"train.out_dir={env.tmp / 'r3'}", "model.gnn.sinkhorn_iters=3",  # a temporal model's weights
              f"train.init_from={temporal_checkpoint(env)}")


@row("train.trainable without train.init_from is refused before the loaders (the frozen parts stayed random: a "
          "training of the rest on random features, exit 0)")
def row_trainable_without_init_from(env):
    forbid(env, "instagram_hdmap.train.build_loaders", "the data loaders")
    env.error(r"train\.trainable=\['backbone'\] without train\.init_from: the frozen parts \(bev_heads, graph_head, "
              r"view_transform\) keep their random initialisation", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}",
              "train.trainable=[backbone]")


@row("train.init_from with --resume says in one note that init_from is not read on a resume (silently ignored)")
def row_init_from_with_resume_notes(env):
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    last = env.tmp / "run" / "last.pt"
    env.capsys.readouterr()
    toy_run(env, [0.3, 0.4], "train.epochs=2", f"train.init_from={env.ckpt}", resume=str(last))
    out = env.capsys.readouterr().out
    assert len(re.findall(r"note: train\.init_from=.*random\.pt is not read on a resume: the weights are .*last\.pt's",
                          out)) == 1, out


@row("a checkpoint whose saved temporal memory holds NaN (weights finite) is named when it loads (a resume "
          "stopped on a 'non-finite loss' advising a lower learning rate)")
def row_checkpoint_with_nonfinite_memory(env):
    state = torch.load(env.ckpt, weights_only=True)
    memory = {"bev": torch.zeros(1, 4, 16, 32), "ego_pose": torch.eye(4)[None],
              "valid": torch.ones(1, dtype=torch.bool), "frame_index": torch.ones(1, dtype=torch.long)}
    save_checkpoint({**state, "memory": [memory]}, env.tmp / "ok.pt")
    load_checkpoint(env.tmp / "ok.pt")  # a finite memory loads
    memory["bev"][0, 0, 3, 4] = float("nan")
    path = save_checkpoint({**state, "memory": [memory]}, env.tmp / "last.pt")
    with pytest.raises(CheckpointError, match=r"last\.pt: the temporal streams' saved memory \('bev'\) holds NaN"):
        load_checkpoint(path)


@row("train --resume CONFIG.yaml (or a GT JSON; a text file as the checkpoint to resume) said 'give a "
            "checkpoint ... with --checkpoint', a flag train does not have; the line names no flag now")
def row_text_file_as_resume_checkpoint(env):
    gt = env.tmp / "gt.json"
    gt.write_text('{"results": {}}')
    line = env.error(r"gt.json is not a PyTorch checkpoint: it is a text file", "train", env.yaml,
                     f"train.out_dir={env.tmp / 'run'}", "--resume", gt)
    assert "--checkpoint" not in line


@row("Mapper.from_onnx / predict --onnx of a PyTorch checkpoint said 'not a readable ONNX file (DecodeError: "
            "... Wire format was corrupt)', of a folder 'ONNX file not found', and from_onnx(path, device='cuda') "
            "'unknown decoding option(s) device'; each says what it is now (device='cpu' is taken)")
def row_onnx_given_a_checkpoint(env):
    pytest.importorskip("onnx")
    from instagram_hdmap import Mapper
    from instagram_hdmap.inference import DeployError

    with pytest.raises(DeployError, match=r"random\.pt is a PyTorch checkpoint, not an ONNX file"):
        Mapper.from_onnx(env.ckpt)
    with pytest.raises(DeployError, match=r"ONNX file not found: .* \(it is a folder\)"):
        Mapper.from_onnx(env.tmp)
    with pytest.raises(TypeError, match=r"runs the ONNX file with onnxruntime on the CPU: device='cuda'"):
        Mapper.from_onnx(env.tmp / "model.onnx", device="cuda")
    env.error(r"random\.pt is a PyTorch checkpoint, not an ONNX file", "predict", env.yaml, "--onnx", env.ckpt,
              "--index", "0", "--out", env.tmp / "out")


@row("model.backbone.weights: an ImageNet file with NaN weights loaded silently (every loss NaN from the first "
            "step); a file saved from a DataParallel model ('module.' keys) was called 'another EfficientNet "
            "variant?', one wrapped as {'state_dict': ...} 'not a state dict'; a folder, the release URL or name were "
            "'weight file not found' alone. NaN is named, the wrappers are read, the others say what to give")
def row_backbone_weights_of_other_shapes(env):
    from efficientnet_pytorch import EfficientNet

    from instagram_hdmap.models import build_model

    state = EfficientNet.from_name("efficientnet-b0").state_dict()
    base = ["model.backbone.name=efficientnet-b0", "data.image_size=[64,160]", "model.gnn.num_vertices=64"]

    def build(weights):
        return build_model(load_config(None, [*base, f"model.backbone.weights={weights}"]), pretrained=True)

    files = {"nan": {k: v.float() * float("nan") if v.is_floating_point() else v for k, v in state.items()},
             "module": {f"module.{k}": v for k, v in state.items()}, "wrapped": {"state_dict": state}}
    for name, value in files.items():
        torch.save(value, env.tmp / f"{name}.pth")
    with pytest.raises(UserError, match=r"nan\.pth: the weights _conv_stem\.weight \(and \d+ more tensors\) hold NaN"):
        build(env.tmp / "nan.pth")
    for name in ("module", "wrapped"):
        stem = build(env.tmp / f"{name}.pth").backbone.trunk._conv_stem.weight
        assert torch.equal(stem, state["_conv_stem.weight"]), name
    (env.tmp / "folder").mkdir()
    with pytest.raises(UserError, match=r"folder \(it is a folder: give the \.pth file in it\)"):
        build(env.tmp / "folder")
    for given in ("efficientnet-b0", "ImageNet"):
        with pytest.raises(UserError, match=rf"not found: {given} \(to download efficientnet-b0's ImageNet release, "
                                            r"give model\.backbone\.weights=imagenet\)"):
            build(given)


@row("train.init_from of a checkpoint of another architecture (another backbone, GNN depth, a temporal one into "
            "a single-frame model): the error listed weight names only ('backbone.stages.0.0.weight (not in this "
            "model)'); it now names the model keys on which the two configs differ")
def row_init_from_other_architecture_names_the_keys(env):
    base = ["train.max_steps=1", f"train.init_from={env.ckpt}", f"train.out_dir={env.tmp / 'run'}"]
    env.error(r"do not fit this model's architecture .*, as the configs differ in model\.gnn\.layers: checkpoint 2 vs "
              r"now 3; start from", "train", env.yaml, *base, "model.gnn.layers=3")
    env.error(r"as the configs differ in model\.backbone\.name: checkpoint 'tiny' vs now 'efficientnet-b0'", "train",
              env.yaml, *base, "model.backbone.name=efficientnet-b0", "model.backbone.from_scratch=true")
    assert not (env.tmp / "run" / "last.pt").exists()


@row("train.init_from with model.backbone.weights set (a paper config, whose weights=imagenet, fine-tuned from "
            "a checkpoint): the ImageNet file was not loaded (the checkpoint's backbone wins), with no word; a note "
            "says so")
def row_init_from_with_backbone_weights_noted(env):
    from efficientnet_pytorch import EfficientNet

    from instagram_hdmap.models import build_model

    b0 = ["model.backbone.name=efficientnet-b0", "model.backbone.from_scratch=true"]
    cfg = env.cfg(*b0)
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, env.tmp / "b0.pt")
    torch.save(EfficientNet.from_name("efficientnet-b0").state_dict(), env.tmp / "imagenet.pth")
    rc, out, err = env.cli("train", env.yaml, "model.backbone.name=efficientnet-b0",
                           f"model.backbone.weights={env.tmp / 'imagenet.pth'}", f"train.init_from={ckpt}",
                           "train.max_steps=1", f"train.out_dir={env.tmp / 'run'}")
    assert rc == 0, err
    assert (f"note: model.backbone.weights={env.tmp / 'imagenet.pth'} is not loaded: the backbone starts from the "
            f"weights of train.init_from={ckpt}") in out


@row("a checkpoint as shared or downloaded, packed: best.pt.gz / .xz said 'not a PyTorch file', a zip archive "
            "holding best.pt 'truncated or corrupt (RuntimeError: Expected hasRecord(\"version\"))', a tar archive "
            "'not a PyTorch file'; each now says what it is and how to unpack it")
def row_packed_checkpoint(env):
    import gzip
    import lzma
    import tarfile

    data = env.ckpt.read_bytes()
    (env.tmp / "best.pt.gz").write_bytes(gzip.compress(data))
    (env.tmp / "best.pt.xz").write_bytes(lzma.compress(data))
    with zipfile.ZipFile(env.tmp / "best.zip", "w") as z:
        z.write(env.ckpt, "run/best.pt")
    with tarfile.open(env.tmp / "best.tar", "w") as t:
        t.add(env.ckpt, "run/best.pt")
    for name, pattern in (("best.pt.gz", r"a gzip-compressed file \(gunzip it first\)"),
                          ("best.pt.xz", r"a xz-compressed file \(unxz it first\)"),
                          ("best.zip", r"not a PyTorch checkpoint but a zip archive of 1 file\(s\) \(run/best\.pt\): "
                                       r"unzip it"),
                          ("best.tar", r"a tar archive \(tar xf it first\)")):
        with pytest.raises(CheckpointError, match=pattern):
            load_checkpoint(env.tmp / name)
    env.error(r"best\.pt\.gz is not a PyTorch checkpoint: it is a gzip-compressed file", "evaluate", env.yaml,
              "--checkpoint", env.tmp / "best.pt.gz", "--out", env.tmp / "eval")


@row("a checkpoint whose config is YAML text (written by hand from the experiment YAML) was read as YAML 1.1, "
            "not as a config file is: lr: 1e-3 was text ('holds a config this version cannot read: expected float, "
            "got '1e-3''), layers: 010 octal 8; it is read as config files are")
def row_checkpoint_config_text_read_as_a_config_file(env):
    import yaml

    from instagram_hdmap.config import config_from_dict

    state = load_checkpoint(env.ckpt)
    text = yaml.safe_dump(state["config"]).replace("lr: 0.001", "lr: 1e-3").replace("seed: 0\n", "seed: 010\n")
    assert "lr: 1e-3" in text and "seed: 010" in text
    path = save_checkpoint({**state, "config": text}, env.tmp / "text_config.pt")
    cfg = config_from_dict(load_checkpoint(path)["config"])
    assert (cfg.train.lr, cfg.train.seed) == (1e-3, 10)


@row("train.init_from of a checkpoint of another model config whose weights have the same names and shapes "
            "(model.gnn.heads 4 -> 8: each attention projection split into other heads; another model.gnn.nms or "
            "num_vertices) loaded with no word; now a note names the model keys that differ")
def row_init_from_other_model_settings_noted(env):
    toy_run(env, [0.2], "train.epochs=1", "train.max_steps=1")
    ckpt = shutil.copy(env.tmp / "run" / "last.pt", env.tmp / "heads4.pt")
    env.capsys.readouterr()
    toy_run(env, [0.2], "train.epochs=1", "train.max_steps=1", f"train.init_from={ckpt}", "model.gnn.heads=8",
             "model.gnn.decoder=mutual", force=True)
    out = env.capsys.readouterr().out
    note = next((ln for ln in out.splitlines() if ln.startswith("note: the checkpoint of train.init_from")), "")
    assert "model.gnn.heads: checkpoint 4 vs now 8" in note, out
    assert "decoder" not in note  # read at inference only: nothing to say


@row("evaluate --checkpoint RUN (a training run's folder, as train.out_dir names it): 'checkpoint not found: "
            "RUN (it is a folder)', not which file to give; now it names RUN/best.pt and RUN/last.pt")
def row_checkpoint_given_as_a_run_folder(env):
    run = env.tmp / "run"
    run.mkdir()
    shutil.copy(env.ckpt, run / "best.pt")
    shutil.copy(env.ckpt, run / "last.pt")
    env.error(rf"checkpoint not found: .*run \(it is a folder: a training run's; give the checkpoint in it, "
              rf"{re.escape(str(run / 'best.pt'))} or {re.escape(str(run / 'last.pt'))}\)",
              "evaluate", env.yaml, "--checkpoint", run, "--out", env.tmp / "eval")


@row("export-onnx under PYTHONWARNINGS=error (-W error, as CI runs): torch's FutureWarning about its own "
            "internals ('isinstance(treespec, LeafSpec) is deprecated') stopped the export with torch's traceback, "
            "exit 1, nothing a user could change; now those notices of torch are ignored during the export")
def row_export_onnx_under_warnings_as_errors(env):
    import warnings

    pytest.importorskip("onnx")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc, out, err = env.cli("export-onnx", env.yaml, "model.gnn.sinkhorn_iters=3", "--checkpoint", env.ckpt,
                               "--out", env.tmp / "m.onnx")
    assert rc == 0 and (env.tmp / "m.onnx").is_file(), err[-2000:]


@row("a checkpoint that is a plain pickle (not torch's zip) of protocol 4 with an object that runs code: the "
            "one-line refusal came under torch's 'Detected pickle protocol 4' UserWarning and its source line")
def row_plain_pickle_checkpoint_one_line(env):
    import pickle

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))

    bad = env.tmp / "evil.pt"
    bad.write_bytes(pickle.dumps({"model": Evil()}, protocol=4))
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}  # a process of its own: pytest catches warnings
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "evaluate", str(env.yaml), "--checkpoint",
                        str(bad), "--out", str(env.tmp / "eval")], capture_output=True, text=True, env=env_vars,
                       timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "evil.pt was refused by the safe loader" in lines[0], p.stderr


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_checkpoints(case, env):
    case.run(env)
