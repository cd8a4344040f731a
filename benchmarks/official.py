"""The official InstaGraM implementation, built from a local checkout, for side-by-side timings.

    python benchmarks/model_speed.py --official /path/to/InstaGraM     # forward, interleaved with ours
    python benchmarks/train_speed.py --official /path/to/InstaGraM     # training step, interleaved

The checkout is the official repository (juyebshin/InstaGraM) as it is: nothing of it is copied
here. Its LSS model (``model.get_model("LSS", ...)``, the README's training command: ``--distance_reg``,
vertex prediction, no segmentation, instance or direction heads, no refinement) is built with the
defaults of its ``train.py`` for a Table I row (``data_conf`` below) and fed the same six-camera batch
as ours. To build and run it on the CPU of a machine without its optional packages, these run-time
patches apply while it is imported and constructed (never to our code, and undone afterwards):

* ``EfficientNet.from_pretrained`` -> ``EfficientNet.from_name``: random backbone weights (no
  download), as our benchmarks use;
* ``torch.Tensor.cuda`` -> the tensor itself when CUDA is absent: the model's constructor moves a
  constant to the GPU (``InstaGraM.center``, model/base.py); its LSS forward has no other device literal;
* stand-ins for modules its imports name, when they are not installed: ``torch_scatter`` (lidar
  pillars, never called by the camera model), ``tkinter.messagebox`` and ``turtle`` (stray imports in
  model/graphmap.py and loss.py), and ``torchvision.models.resnet``: its BEV encoder takes the first
  three stages of torchvision's ResNet-18, which ``standin_resnet18`` rebuilds layer for layer. Install
  the torchvision of your torch (torch 2.13 -> torchvision 0.28) to time the real one; the tables say
  which was used.

Its training step is that of its ``train.py`` (forward; ``CEWithSoftmaxLoss`` on the vertex heatmap,
``MSEWithReluLoss`` on the distance transform, ``GraphLoss`` (match and class losses, built per sample
in Python), weighted 1 / 1 / 0.005 / 0.01; backward; gradient clipping at 5; Adam), on targets in its
formats made from the same GT polylines as ours (``official_targets``).
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import types
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from instagram_hdmap.models.bev_heads import BasicBlock

# The official train.py's defaults (LSS, 60 m x 30 m at 0.15 m, S = 8, N = 400, 7 GNN layers)
DATA_CONF = {
    "num_channels": 4, "xbound": [-30.0, 30.0, 0.15], "ybound": [-15.0, 15.0, 0.15], "zbound": [-10.0, 10.0, 20.0],
    "dbound": [4.0, 45.0, 1.0], "sample_dist": 1.5, "thickness": 5, "angle_class": 36, "dist_threshold": 10.0,
    "cell_size": 8, "num_vectors": 400, "pos_freq": 10, "feature_dim": 256, "gnn_layers": 7,
    "sinkhorn_iterations": 100, "vertex_threshold": 0.015, "match_threshold": 0.1,
}
LOSS_SCALES = {"vt": 1.0, "dt": 1.0, "match": 0.005, "seg": 0.01}  # train.py: --scale_vt, _dt, _match, _seg
MAX_GRAD_NORM = 5.0


class OfficialCodeError(RuntimeError):
    """The folder is not a checkout of the official code, or its model cannot be built here."""


def _stub(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__dict__.update(attrs)
    module.__instagram_hdmap_stub__ = True
    return module


def _missing(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return True
    return False


def standin_resnet18(pretrained: bool = False, zero_init_residual: bool = False) -> torch.nn.Module:
    """torchvision's ``resnet18`` as far as the official BEV encoder uses it (``bn1``, ``relu``,
    ``layer1..layer3``: BasicBlocks 64-64, 64-128/2, 128-256/2, the same layers and work), for a
    machine without torchvision; built from our own BasicBlock (models/bev_heads.py), whose
    ``zero_init_residual`` is always on, as the official encoder asks."""
    if pretrained:
        raise OfficialCodeError("no pretrained ResNet-18 without torchvision")
    trunk = nn.Module()
    trunk.bn1, trunk.relu = nn.BatchNorm2d(64), nn.ReLU(inplace=True)
    for i, (cin, cout, stride) in enumerate(((64, 64, 1), (64, 128, 2), (128, 256, 2)), start=1):
        setattr(trunk, f"layer{i}", nn.Sequential(BasicBlock(cin, cout, stride), BasicBlock(cout, cout)))
    return trunk


def uses_standins() -> list[str]:
    """The stand-ins the official model is built with on this machine (module docstring)."""
    return [name for name in ("torchvision.models.resnet", "torch_scatter") if _missing(name)]


@contextlib.contextmanager
def _patched(root: Path):
    """The run-time patches of the module docstring, undone on exit (the imported modules stay)."""
    from efficientnet_pytorch import EfficientNet

    saved_modules = dict(sys.modules)
    stubs = {}
    if _missing("torch_scatter"):
        stubs["torch_scatter"] = _stub("torch_scatter")
    if _missing("torchvision.models.resnet"):

        def no_resnet(*args, **kwargs):
            raise OfficialCodeError("the ResNet-50 backbone needs torchvision, which is not installed")

        resnet = _stub("torchvision.models.resnet", resnet18=standin_resnet18, resnet50=no_resnet)
        stubs.update({"torchvision": _stub("torchvision", models=_stub("torchvision.models", resnet=resnet)),
                      "torchvision.models": sys.modules.get("torchvision.models") or resnet,
                      "torchvision.models.resnet": resnet})
    for name in ("tkinter.messagebox", "turtle"):
        if _missing(name):
            stubs[name] = _stub(name, NO="no", forward=None)
    sys.modules.update(stubs)
    from_pretrained, cuda = EfficientNet.from_pretrained, torch.Tensor.cuda
    EfficientNet.from_pretrained = classmethod(lambda cls, name, *a, **k: EfficientNet.from_name(name))
    if not torch.cuda.is_available():
        torch.Tensor.cuda = lambda self, *args, **kwargs: self
    sys.path.insert(0, str(root))
    try:
        yield
    finally:
        sys.path.remove(str(root))
        EfficientNet.from_pretrained, torch.Tensor.cuda = from_pretrained, cuda
        for name in stubs:  # stand-ins leave; the official modules stay importable for the run
            if saved_modules.get(name) is None:
                sys.modules.pop(name, None)


def load_official(root: str | Path) -> types.SimpleNamespace:
    """Import the official ``model`` and ``loss`` modules from the checkout ``root``."""
    root = Path(root).resolve()
    if not (root / "model" / "lift_splat.py").is_file() or not (root / "loss.py").is_file():
        raise OfficialCodeError(f"{root} is not a checkout of the official InstaGraM code (no model/lift_splat.py "
                                "and loss.py)")
    with _patched(root):
        try:
            model = importlib.import_module("model")
            loss = importlib.import_module("loss")
        except ImportError as e:
            raise OfficialCodeError(f"cannot import the official code from {root}: {e}") from e
    return types.SimpleNamespace(root=root, model=model, loss=loss)


def build_official(code: types.SimpleNamespace, backbone: str, image_size: tuple[int, int],
                   seed: int = 0) -> torch.nn.Module:
    """The official LSS InstaGraM for ``backbone`` ("efficientnet-b0" / "-b4") and ``image_size`` (h, w),
    random weights drawn from ``seed``."""
    conf = {**DATA_CONF, "backbone": backbone, "image_size": list(image_size)}
    norm = {"1d": torch.nn.BatchNorm1d, "2d": torch.nn.BatchNorm2d}
    with _patched(code.root), torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return code.model.get_model("LSS", conf, norm, segmentation=False, instance_seg=False, embedded_dim=16,
                                    direction_pred=False, angle_class=36, distance_reg=True, vertex_pred=True,
                                    refine=False)


def official_inputs(batch: dict) -> tuple:
    """Our batch (docs/conventions.md) as the official model's positional arguments."""
    B, V = batch["images"].shape[:2]
    zeros = batch["images"].new_zeros
    return (batch["images"], batch["cam_to_ego_trans"], batch["cam_to_ego_rot"], batch["intrinsics"],
            batch["post_tran"], batch["post_rot"], zeros(B, 1, 5), zeros(B, 1), zeros(B, 3), zeros(B, 3))


def official_targets(batch: dict, cell_size: int = 8) -> dict:
    """The official training targets from our batch's: the vertex heatmap as a one-hot float map over
    S*S + 1 channels, our distance transform, and ``vectors_gt`` (per sample, a list of
    ``{"pts", "pts_num", "type"}`` in metres, as its dataset yields)."""
    cells = batch["gt_vertex_cells"].long()  # [B, Hc, Wc], S*S = no vertex
    vertex_gt = F.one_hot(cells, cell_size * cell_size + 1).permute(0, 3, 1, 2).float()
    vectors = [[{"pts": np.asarray(p["pts"], dtype=np.float64), "pts_num": len(p["pts"]), "type": int(p["label"])}
                for p in polylines] for polylines in batch["gt_polylines"]]
    return {"vertex_gt": vertex_gt, "distance_gt": batch["gt_distance"].float(), "vectors_gt": vectors}


class OfficialTrainer:
    """One step of the official train.py on a fixed batch: ``step()`` after construction."""

    def __init__(self, code: types.SimpleNamespace, model: torch.nn.Module, batch: dict, lr: float = 1e-3,
                 weight_decay: float = 1e-7):
        self.model = model.train()
        self.inputs = official_inputs(batch)
        self.targets = official_targets(batch, DATA_CONF["cell_size"])
        self.vt_loss = code.loss.CEWithSoftmaxLoss()
        self.dt_loss = code.loss.MSEWithReluLoss()
        self.graph_loss = code.loss.GraphLoss(DATA_CONF["xbound"], DATA_CONF["ybound"], num_classes=3)
        self.opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)

    def step(self) -> float:
        t = self.targets
        self.opt.zero_grad()
        semantic, distance, vertex, _, _, matches, positions, masks = self.model(*self.inputs)
        vt = self.vt_loss(vertex, t["vertex_gt"])
        dt = self.dt_loss(distance, t["distance_gt"])
        _, match, seg, _, _ = self.graph_loss(matches, positions, semantic, masks, t["vectors_gt"])
        loss = (seg * LOSS_SCALES["seg"] + dt * LOSS_SCALES["dt"] + vt * LOSS_SCALES["vt"]
                + match * LOSS_SCALES["match"])
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), MAX_GRAD_NORM)
        self.opt.step()
        return float(loss.detach())
