"""Training: exact resume, refusal to overwrite, DDP weight agreement, and overfitting a few samples.

The data here is a small in-memory dataset (random images, hand-made polylines turned into targets
by targets.build_targets) so these tests exercise the engine, not the loader; the synthetic-world
loader is covered in test_dataset.py and the demo test.
"""

import math
import os

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from instagram_hdmap import train as train_module
from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint
from instagram_hdmap.config import ConfigError, UserError, load_config
from instagram_hdmap.data.base import collate_fn
from instagram_hdmap.distributed import ResumableSampler
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.targets import build_targets
from instagram_hdmap.train import train

TINY = [
    "model.backbone.name=tiny", "model.backbone.out_channels=16", "data.image_size=[32,64]",
    "grid.xbound=[-8.0,8.0]", "grid.ybound=[-4.0,4.0]", "grid.resolution=0.25", "grid.cell_size=4",
    "model.view_transform.depth_bound=[1.0,12.0,1.0]", "model.bev_heads.channels=32",
    "model.bev_heads.stage_channels=[16,32,32]", "model.bev_heads.head_channels=16",
    "model.gnn.num_vertices=48", "model.gnn.dim=32", "model.gnn.layers=1", "model.gnn.sinkhorn_iters=20",
    "train.batch_size=2", "train.log_every=1", "train.checkpoint_every=0", "data.num_workers=0",
    "train.deterministic=true",
]


def _tiny_cfg(tmp_path, *extra):
    return load_config(None, [*TINY, f"train.out_dir={tmp_path / 'run'}", *extra])


class ToyMaps(Dataset):
    """n samples: one divider, one ped crossing (closed), one boundary at seeded random offsets."""

    def __init__(self, cfg, n: int = 4, seed: int = 0):
        self.cfg, self.grid = cfg, BEVGrid.from_config(cfg.grid)
        self.items = []
        rng = np.random.default_rng(seed)
        h, w = cfg.data.image_size
        for i in range(n):
            dy = rng.uniform(-2, 2)
            x = np.linspace(-7, 7, 12)
            polys = [
                {"pts": np.stack([x, np.full_like(x, dy)], 1), "label": 0, "closed": False},
                {"pts": np.array([[2, -3.5], [4, -3.5], [4, -1.5], [2, -1.5], [2, -3.5]]) + [rng.uniform(-4, 2), 0],
                 "label": 1, "closed": True},
                {"pts": np.stack([x, np.full_like(x, 3.0 + 0.3 * dy)], 1), "label": 2, "closed": False},
            ]
            eye = torch.eye(3).expand(6, 3, 3).clone()
            self.items.append({
                "images": torch.from_numpy(rng.standard_normal((6, 3, h, w)).astype(np.float32)),
                "intrinsics": torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]).expand(6, 3, 3).clone(),
                "cam_to_ego_rot": torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]).expand(6, 3, 3).clone(),
                "cam_to_ego_trans": torch.tensor([0.0, 0, 1.5]).expand(6, 3).clone(),
                "post_rot": eye, "post_tran": torch.zeros(6, 3), "ego_pose": torch.eye(4),
                "ground_height": torch.tensor(0.0),
                "sample_token": f"toy{i}", "gt_polylines": polys,
                **build_targets(polys, self.grid, 3, cfg.data.dt_clip),
            })

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]


def _loaders(cfg, n=4):
    ds = ToyMaps(cfg, n)
    sampler = ResumableSampler(len(ds), seed=cfg.train.seed)
    loader = DataLoader(ds, batch_size=cfg.train.batch_size, sampler=sampler, collate_fn=collate_fn,
                        generator=torch.Generator().manual_seed(0))
    return loader, sampler, None


def _weights(path):
    return load_checkpoint(path)["model"]


def test_resume_reaches_exactly_the_uninterrupted_weights(tmp_path):
    # 3 epochs x 2 steps; the interrupted run stops after 3 steps (mid-epoch 1) and resumes.
    full = _tiny_cfg(tmp_path / "a", "train.epochs=3")
    train(full, loaders=_loaders(full), validate=False)
    part = _tiny_cfg(tmp_path / "b", "train.epochs=3", "train.max_steps=3")
    train(part, loaders=_loaders(part), validate=False)
    state = load_checkpoint(tmp_path / "b" / "run" / "last.pt")
    assert (state["epoch"], state["step"], state["step_in_epoch"]) == (1, 3, 1)
    rest = _tiny_cfg(tmp_path / "b", "train.epochs=3")
    train(rest, loaders=_loaders(rest), validate=False, resume=str(tmp_path / "b" / "run" / "last.pt"))
    a, b = _weights(tmp_path / "a" / "run" / "last.pt"), _weights(tmp_path / "b" / "run" / "last.pt")
    assert a.keys() == b.keys()
    for k in a:
        # to float32 rounding: oneDNN's convolution kernels may round a last bit differently in a
        # fresh process (seen: 1.5e-8 on a few weights); a wrong batch, LR or state is >= 1e-4 off
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)
    assert load_checkpoint(tmp_path / "b" / "run" / "last.pt")["step"] == 6


def test_refuses_to_overwrite_a_run_and_checks_resume_config(tmp_path):
    cfg = _tiny_cfg(tmp_path, "train.epochs=1")
    train(cfg, loaders=_loaders(cfg), validate=False)
    with pytest.raises(UserError, match="already holds a run"):
        train(cfg, loaders=_loaders(cfg), validate=False)
    other = _tiny_cfg(tmp_path, "train.epochs=2", "model.gnn.layers=2")
    with pytest.raises(CheckpointError, match=r"model\.gnn\.layers: checkpoint 1 vs now 2"):
        train(other, loaders=_loaders(other), validate=False, resume=str(tmp_path / "run" / "last.pt"))
    with pytest.raises(CheckpointError, match="not found"):
        train(cfg, loaders=_loaders(cfg), validate=False, resume=str(tmp_path / "missing.pt"))


def _ddp_worker(rank: int, world: int, port: int, out: str, cfg_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from instagram_hdmap import distributed as du
    from instagram_hdmap.engine import EpochHooks, Position, train_one_epoch
    from instagram_hdmap.losses import Criterion
    from instagram_hdmap.models import build_model

    cfg = load_config(None, [*TINY, f"train.out_dir={cfg_dir}"])
    device = du.init_distributed("cpu")
    torch.manual_seed(0)  # same initial weights on both ranks (DDP also broadcasts them)
    model = build_model(cfg)
    net = torch.nn.parallel.DistributedDataParallel(model)
    ds = ToyMaps(cfg, 4)
    sampler = ResumableSampler(len(ds), seed=0)
    loader = DataLoader(ds, batch_size=1, sampler=sampler, collate_fn=collate_fn)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    checks = []

    def on_step(info):
        flat = torch.cat([p.detach().flatten() for p in model.parameters()])
        gathered = du.all_gather_object(flat)
        checks.append(all(torch.equal(gathered[0], g) for g in gathered))

    train_one_epoch(net, Criterion(cfg.loss, BEVGrid.from_config(cfg.grid)), loader, opt, device, Position(0),
                    hooks=EpochHooks(on_step=on_step))
    if rank == 0:
        torch.save({"checks": checks, "samples": len(sampler)}, out)
    du.cleanup()


def test_ddp_two_cpu_processes_keep_identical_weights(tmp_path):
    import socket

    import torch.multiprocessing as mp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "ddp.pt"
    mp.spawn(_ddp_worker, args=(2, port, str(out), str(tmp_path / "run")), nprocs=2, join=True)
    res = torch.load(out, weights_only=True)
    assert res["samples"] == 2  # each rank saw half of the 4 samples
    assert res["checks"] == [True, True]  # identical weights on both ranks after each step


def test_nonfinite_loss_stops_with_the_step_and_terms(tmp_path, monkeypatch):
    from instagram_hdmap import losses
    from instagram_hdmap.engine import NonFiniteLossError

    cfg = _tiny_cfg(tmp_path, "train.epochs=1")
    real = losses.Criterion.forward

    def poisoned(self, outputs, batch, assignment=None):
        out = real(self, outputs, batch, assignment)
        out["loss_total"] = out["loss_total"] * math.nan
        return out

    monkeypatch.setattr(losses.Criterion, "forward", poisoned)
    with pytest.raises(NonFiniteLossError, match=r"step 1: .*loss_vertex="):
        train(cfg, loaders=_loaders(cfg), validate=False)


def test_training_with_validation_on_the_synthetic_world(tiny_world, tmp_path):
    from instagram_hdmap.train import build_loaders

    cfg = load_config(None, [*TINY, f"train.out_dir={tmp_path / 'run'}", f"data.dataroot={tiny_world}",
                             "data.version=v1.0-trainval", "train.epochs=1", "train.max_steps=2", "eval.cmap=true"])
    summary = train(cfg, loaders=build_loaders(cfg, 1), validate=True)
    metrics = summary["val"]["metrics"]
    assert metrics["protocol"] == "vector" and set(metrics["AP"]) == {"divider", "ped_crossing", "boundary"}
    assert 0.0 <= metrics["mAP"] <= 1.0
    cmap = summary["val"]["cmap"]  # eval.cmap: MapTracker's consistency-aware mAP in the validation too
    assert cmap["mAP"] == pytest.approx(metrics["mAP"], abs=1e-6) and cmap["C-mAP"] <= cmap["mAP"]
    assert (tmp_path / "run" / "best.pt").is_file() and (tmp_path / "run" / "config.yaml").is_file()


def test_resume_is_exact_with_augmentation_and_a_data_worker(tiny_world, tmp_path):
    """Augmentation draws come from (seed, epoch, index): a run interrupted mid-epoch and resumed,
    with augmentation on and a worker process loading the data, ends on the uninterrupted weights."""
    from instagram_hdmap.train import build_loaders

    def cfg(where, *extra):
        return load_config(None, [*TINY, f"train.out_dir={where}", f"data.dataroot={tiny_world}",
                                  f"data.splits_file={tiny_world / 'splits.json'}", "data.version=v1.0-trainval",
                                  "data.augment=true", "data.num_workers=1", "train.epochs=2", *extra])

    full = cfg(tmp_path / "a")
    train(full, loaders=build_loaders(full, 1, with_val=False), validate=False)
    part = cfg(tmp_path / "b", "train.max_steps=4")  # 6 samples / batch 2: mid-epoch 1
    train(part, loaders=build_loaders(part, 1, with_val=False), validate=False)
    rest = cfg(tmp_path / "b")
    train(rest, loaders=build_loaders(rest, 1, with_val=False), validate=False,
          resume=str(tmp_path / "b" / "last.pt"))
    a, b = _weights(tmp_path / "a" / "last.pt"), _weights(tmp_path / "b" / "last.pt")
    assert load_checkpoint(tmp_path / "b" / "last.pt")["step"] == load_checkpoint(tmp_path / "a" / "last.pt")["step"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)  # see the test above


def test_augmentation_depends_on_seed_epoch_and_index_only(tiny_world_cfg):
    from instagram_hdmap.data.nuscenes import NuScenesMapDataset

    ds = NuScenesMapDataset(tiny_world_cfg, "train", augment=True)
    first = ds.load_cameras(1)["post_rot"]
    other = NuScenesMapDataset(tiny_world_cfg, "train", nusc=ds.nusc, augment=True)
    torch.manual_seed(123)  # the global RNG plays no part
    assert torch.equal(other.load_cameras(1)["post_rot"], first)
    assert not torch.equal(ds.load_cameras(2)["post_rot"], first)
    ds.set_epoch(1)
    assert not torch.equal(ds.load_cameras(1)["post_rot"], first)


def test_cpu_threads_leave_a_core_to_each_data_worker(tmp_path, monkeypatch):
    """Automatic intra-op threads = usable cores - data workers (>= 1), per local process; an explicit
    train.cpu_threads wins; OMP_NUM_THREADS set by the user leaves torch's own setting alone."""
    from instagram_hdmap import train as train_module

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(train_module, "usable_cores", lambda: 8)
    threads = train_module.cpu_threads
    assert threads(_tiny_cfg(tmp_path, "data.num_workers=2")) == 6
    assert threads(_tiny_cfg(tmp_path, "data.num_workers=2"), local_processes=4) == 1  # 8 // 4 - 2 = 0 -> 1
    assert threads(_tiny_cfg(tmp_path, "data.num_workers=0"), local_processes=2) == 4
    assert threads(_tiny_cfg(tmp_path, "data.num_workers=12")) == 1
    assert threads(_tiny_cfg(tmp_path, "train.cpu_threads=3", "data.num_workers=2")) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "5")
    assert threads(_tiny_cfg(tmp_path, "data.num_workers=2")) is None
    assert threads(_tiny_cfg(tmp_path, "train.cpu_threads=3")) == 3
    with pytest.raises(ConfigError, match="cpu_threads"):
        _tiny_cfg(tmp_path, "train.cpu_threads=0")


def test_training_runs_with_its_threads_and_gives_the_setting_back(tmp_path, monkeypatch):
    """A CPU run trains with its threads (given back afterwards), and with the freed blocks kept for the next step
    (``resources.reuse_freed_memory``) from before its first step."""
    from instagram_hdmap import train as train_module

    seen, kept = [], []
    original = train_module.train_one_epoch

    def spy(*args, **kwargs):
        seen.append((torch.get_num_threads(), len(kept)))
        return original(*args, **kwargs)

    monkeypatch.setattr(train_module, "train_one_epoch", spy)
    monkeypatch.setattr(train_module, "reuse_freed_memory", lambda: kept.append(True) or True)
    before = torch.get_num_threads()
    cfg = _tiny_cfg(tmp_path, "train.epochs=1", "train.cpu_threads=1")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert seen == [(1, 1)] and summary["cpu_threads"] == 1
    assert torch.get_num_threads() == before


def test_a_model_without_a_distance_head_trains(tmp_path):
    """The official visual-descriptor variant (configs/paper/fig7_vd_*): no distance head, no distance
    loss, the descriptor read at the vertex's cell."""
    cfg = _tiny_cfg(tmp_path, "train.epochs=1", "model.bev_heads.distance_head=false", "model.gnn.embedding=pe+vd",
                    "model.gnn.vd_sampling=cell")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert summary["step"] == 2 and "loss_distance" not in summary["train"]
    assert math.isfinite(summary["train"]["loss_total"]) and summary["train"]["loss_adjacency"] > 0
    assert not any(k.startswith("bev_heads.distance_head") for k in _weights(tmp_path / "run" / "last.pt"))


B0 = ["model.backbone.name=efficientnet-b0", "train.max_steps=1", "train.epochs=1"]


def test_random_efficientnet_weights_warn_loudly_unless_deliberate(tmp_path, capsys, monkeypatch):
    """A paper config starts from ImageNet weights; an EfficientNet left random says so at the start of
    training, unless model.backbone.from_scratch makes it deliberate; weights=imagenet downloads them
    (mocked here: never the network) and a failed download is one UserError line."""
    from instagram_hdmap.models import backbone as backbone_module

    cfg = _tiny_cfg(tmp_path / "random", *B0)
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert "WARNING: efficientnet-b0 starts from RANDOM weights" in capsys.readouterr().out
    assert "model.backbone.from_scratch=true" in summary["warnings"][0]

    cfg = _tiny_cfg(tmp_path / "scratch", *B0, "model.backbone.from_scratch=true")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert "RANDOM" not in capsys.readouterr().out and "warnings" not in summary
    tiny = _tiny_cfg(tmp_path / "tiny", "train.max_steps=1", "train.epochs=1")  # the tiny backbone: no warning
    train(tiny, loaders=_loaders(tiny), validate=False)
    assert "RANDOM" not in capsys.readouterr().out

    def offline(name):
        raise OSError("[Errno -3] Temporary failure in name resolution")

    monkeypatch.setattr(backbone_module, "download_imagenet", offline)
    cfg = _tiny_cfg(tmp_path / "offline", *B0, "model.backbone.weights=imagenet")
    with pytest.raises(UserError, match="model.backbone.weights=/path/to/efficientnet-b0.pth") as err:
        train(cfg, loaders=_loaders(cfg), validate=False)
    assert "\n" not in str(err.value)

    from efficientnet_pytorch import EfficientNet

    torch.manual_seed(5)
    reference = EfficientNet.from_name("efficientnet-b0").state_dict()
    monkeypatch.setattr(backbone_module, "download_imagenet", lambda name: reference)
    cfg = _tiny_cfg(tmp_path / "imagenet", *B0, "model.backbone.weights=imagenet", "train.lr=1e-12")
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert "RANDOM" not in capsys.readouterr().out and "warnings" not in summary
    stem = _weights(tmp_path / "imagenet" / "run" / "last.pt")["backbone.trunk._conv_stem.weight"]
    torch.testing.assert_close(stem, reference["_conv_stem.weight"], rtol=0, atol=1e-6)


def test_the_cli_stops_a_paper_config_offline_in_one_line_before_loading_data(tmp_path, capsys, monkeypatch):
    """instagram-hdmap train configs/paper/... without internet: exit 2 and one line on how to give the
    weights as a file, before the (long) dataset setup (the dataroot here does not even exist)."""
    from instagram_hdmap.cli import main
    from instagram_hdmap.models import backbone as backbone_module

    def offline(name):
        raise OSError("[Errno -3] Temporary failure in name resolution")

    monkeypatch.setattr(backbone_module, "download_imagenet", offline)
    config = os.path.join(os.path.dirname(__file__), "..", "configs", "paper", "table1_b0_lss_128x352.yaml")
    code = main(["train", config, f"data.dataroot={tmp_path / 'absent'}", f"train.out_dir={tmp_path / 'run'}",
                 "train.device=cpu"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "model.backbone.weights=/path/to/efficientnet-b0.pth" in err and "absent" not in err


def test_validation_runs_the_model_without_autograd():
    """engine.evaluate runs under no_grad: a validation records no graph (memory, time)."""
    from instagram_hdmap import engine

    seen = []

    class Probe(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(1))

        def forward(self, batch):
            seen.append(torch.is_grad_enabled())
            return {"x": self.w * 2}

    result = engine.evaluate(Probe(), None, [{"images": torch.zeros(1, 1, 3, 4, 4)}], torch.device("cpu"))
    assert seen == [False] and result["losses"] == {}


def test_bf16_training_on_the_cpu_runs_the_convolutions_in_bf16_and_the_graph_head_in_float32(tmp_path, capsys,
                                                                                                monkeypatch):
    """train.amp=auto on a CPU with native bfloat16 trains in bf16 (and says so); under the CPU's autocast the
    BEV encoder's convolutions give bf16 and the graph network float32; the losses stay finite."""
    from instagram_hdmap import precision

    monkeypatch.setattr(precision, "cpu_flags", lambda: {"avx512f", "amx_bf16", "avx512_bf16"})
    cfg = _tiny_cfg(tmp_path, "train.epochs=2", "train.amp=auto")
    seen: dict[str, set] = {"bev": set(), "gnn": set()}
    real_build = train_module.build_model

    def build(c, **kwargs):
        model = real_build(c, **kwargs)
        model.bev_heads.stem.register_forward_hook(lambda m, i, o: seen["bev"].add(o.dtype))
        model.graph_head.gnn.register_forward_hook(lambda m, i, o: seen["gnn"].add(o.dtype))
        return model

    monkeypatch.setattr(train_module, "build_model", build)
    summary = train(cfg, loaders=_loaders(cfg), validate=False)
    assert "train.amp auto: bf16" in capsys.readouterr().out
    assert seen == {"bev": {torch.bfloat16}, "gnn": {torch.float32}}
    assert summary["step"] == 4 and math.isfinite(summary["train"]["loss_total"])


def _signal_itself_while_starting():
    import signal
    import time

    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(5)  # (not reached when the signal ends it)


def test_a_worker_signalled_as_it_starts_ends_quietly_and_the_run_still_catches_the_signal(capfd):
    """A scheduler's SIGTERM to the process group can reach a data-loader worker while it is still starting, outside
    torch's worker loop, with the training's handler inherited from the fork: it ends with exit code 0 and no
    traceback; the training process itself still turns the signal into KeyboardInterrupt."""
    import multiprocessing
    import signal

    with train_module._sigterm_as_interrupt():
        child = multiprocessing.get_context("fork").Process(target=_signal_itself_while_starting)
        child.start()
        child.join(30)
        with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):  # the handler runs at the next bytecode
                pass
    assert child.exitcode == 0
    assert "Traceback" not in capfd.readouterr().err
