"""Image backbones: per-camera image -> features at 1/16 of the input size.

Lift-Splat-style multi-scale features (as in the official InstaGraM ``CamEncode``): the stride-16
endpoint (``reduction_4``) and the stride-32 endpoint (``reduction_5``, the last MBConv block) of an
EfficientNet are fused by an :class:`Up` block (upsample x2, concatenate, two conv3x3-BN-ReLU) to
``out_channels`` channels. The classifier head of the EfficientNet (``_conv_head``, ``_bn1``,
``_fc``) is never used and is deleted, so it does not count as parameters.

The up-block goes straight to ``out_channels`` (256 for LSS, 64 for IPM / MLP), as the official
InstaGraM code does; the original Lift-Splat first fuses to 512 channels (2.6 M parameters more with
B4, which would put the LSS model 5 % above the paper's Table V).

Shapes: B' = batch x cameras, h x w the network input size (a multiple of 32).

``EfficientNetBackbone``: ``efficientnet-b0`` / ``efficientnet-b4`` from ``efficientnet_pytorch``,
randomly initialised; ``load_pretrained_backbone(backbone, weights)`` gives it ImageNet weights
(``model.backbone.weights``): ``"imagenet"`` downloads efficientnet_pytorch's release (the official
code's ``EfficientNet.from_pretrained``, ``model/base.py:167``) into torch's hub cache, a path reads a
local checkpoint in that package's state-dict format (as written by
``torch.save(EfficientNet.from_pretrained(name).state_dict())``; a DataParallel model's ``module.`` keys
and a one-key wrapper such as ``{"state_dict": ...}`` are read too; non-finite weights are refused).
``TinyBackbone``: five strided convolutions, for tests on CPU.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from efficientnet_pytorch import EfficientNet
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..config import UserError
from ..errors import one_line

# The network input must be divisible by this: both backbones reach stride 32.
IMAGE_DIVISOR = 32
FEATURE_DOWNSAMPLE = 16  # the features handed to the view transform are at 1/16 of the input
# Parts of efficientnet_pytorch's state dict that we do not build (the classifier head).
_UNUSED_PREFIXES = ("_conv_head.", "_bn1.", "_fc.")


def conv_bn_relu(cin: int, cout: int, kernel: int = 3, stride: int = 1) -> nn.Sequential:
    """conv (no bias) -> BatchNorm -> ReLU; padding keeps ``size / stride`` for odd kernels."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class Up(nn.Module):
    """Upsample the coarse input to the size of the skip input, concatenate [skip, coarse], and apply
    two conv3x3-BN-ReLU: [B, c_skip, h, w], [B, c_coarse, h', w'] -> [B, cout, h, w]."""

    def __init__(self, c_skip: int, c_coarse: int, cout: int):
        super().__init__()
        self.conv = nn.Sequential(conv_bn_relu(c_skip + c_coarse, cout), conv_bn_relu(cout, cout))

    def forward(self, skip: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
        coarse = F.interpolate(coarse, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.conv(torch.cat([skip, coarse], dim=1))


class _RecomputeOnce:
    """``block(x, drop_connect_rate)`` for ``torch.utils.checkpoint``: the first call is the forward,
    later calls are the recomputation in backward, which must not update the BatchNorm running
    statistics a second time: their buffers are restored after it (bit-exact, unlike momentum 0)."""

    def __init__(self, block: nn.Module, drop_connect_rate: float):
        self.block, self.rate, self.calls = block, drop_connect_rate, 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        if self.calls == 1:
            return self.block(x, drop_connect_rate=self.rate)
        stats = [b for m in self.block.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
                 for b in (m.running_mean, m.running_var, m.num_batches_tracked) if b is not None]
        saved = [b.clone() for b in stats]
        try:  # checkpoint may stop the recomputation early (by raising) once it has what backward needs
            return self.block(x, drop_connect_rate=self.rate)
        finally:
            with torch.no_grad():
                for b, old in zip(stats, saved):
                    b.copy_(old)


class EfficientNetBackbone(nn.Module):
    """EfficientNet trunk up to its last MBConv block, reduction_4 + reduction_5 fused by ``Up``.

    forward: images [B', 3, h, w] -> features [B', out_channels, h/16, w/16].
    """

    def __init__(self, name: str, out_channels: int, image_size: tuple[int, int], grad_checkpoint: bool = False):
        super().__init__()
        self.grad_checkpoint = grad_checkpoint
        # image_size sets the static "same" padding of efficientnet_pytorch's convolutions.
        trunk = EfficientNet.from_name(name, image_size=list(image_size))
        for unused in ("_conv_head", "_bn1", "_avg_pooling", "_dropout", "_fc"):
            delattr(trunk, unused)
        self.trunk, self.name, self.out_channels = trunk, name, out_channels
        # The last block at stride 16 ends reduction_4; the last block overall is reduction_5.
        stride, self._r4_index = 2, -1  # the stem has stride 2
        for i, block in enumerate(trunk._blocks):
            s = block._depthwise_conv.stride
            stride *= s[0] if isinstance(s, (tuple, list)) else s
            if stride == 16:
                self._r4_index = i
        c4 = trunk._blocks[self._r4_index]._block_args.output_filters
        c5 = trunk._blocks[-1]._block_args.output_filters
        self.up = Up(c4, c5, out_channels)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        t = self.trunk
        x = t._swish(t._bn0(t._conv_stem(images)))
        rate = t._global_params.drop_connect_rate or 0.0
        n = len(t._blocks)
        reduction_4 = x
        checkpointing = self.grad_checkpoint and self.training and torch.is_grad_enabled()
        for i, block in enumerate(t._blocks):
            r = rate * i / n  # linearly scaled, as efficientnet_pytorch
            if checkpointing:
                x = checkpoint(_RecomputeOnce(block, r), x, use_reentrant=False)  # same drop-connect mask
            else:
                x = block(x, drop_connect_rate=r)
            if i == self._r4_index:
                reduction_4 = x
        return self.up(reduction_4, x)

    def load_imagenet_weights(self, path: str | Path) -> None:
        """Load an ImageNet checkpoint in efficientnet_pytorch's state-dict format from a local file.

        The classifier head's entries (``_conv_head``, ``_bn1``, ``_fc``) are ignored; every other key
        must be present with the right shape. Raises :class:`~instagram_hdmap.config.UserError`.
        """
        key = "model.backbone.weights"
        path = Path(path)
        if not path.is_file():
            # a folder, a URL or the release's name (efficientnet_pytorch's from_pretrained takes one) were "weight
            # file not found" alone
            named = str(path).lower().startswith(("http:", "https:", "imagenet", "efficientnet")) or "://" in str(path)
            hint = (" (it is a folder: give the .pth file in it)" if path.is_dir() else
                    f" (to download {self.name}'s ImageNet release, give model.backbone.weights=imagenet)" if named
                    else "")
            raise UserError(f"{key}: weight file not found: {path}{hint}")
        device = self.trunk._conv_stem.weight.device
        try:
            state = torch.load(path, map_location=device, weights_only=True)
        except Exception as e:  # any unreadable file is a user error
            raise UserError(f"{key}: cannot read {path} as a torch checkpoint: {one_line(e)}") from None
        self.load_imagenet_state(state, str(path))

    def load_imagenet_state(self, state: object, source: str) -> None:
        """Load an ImageNet state dict in efficientnet_pytorch's format (``source`` names it in errors)."""
        key, path = "model.backbone.weights", source
        if isinstance(state, dict) and len(state) == 1 and isinstance(next(iter(state.values())), dict):
            state = next(iter(state.values()))  # a wrapper: {"state_dict": ...}, {"model": ...}
        if isinstance(state, dict) and state and all(isinstance(k, str) and k.startswith("module.") for k in state):
            state = {k[len("module."):]: v for k, v in state.items()}  # saved from a DataParallel / DDP wrapper
        if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
            raise UserError(f"{key}: {path} is not a state dict of tensors; save one with "
                            f"torch.save(EfficientNet.from_pretrained('{self.name}').state_dict(), path)")
        state = {k: v for k, v in state.items() if not k.startswith(_UNUSED_PREFIXES)}
        own = self.trunk.state_dict()
        missing = sorted(set(own) - set(state))
        unexpected = sorted(set(state) - set(own))
        wrong_shape = [k for k in own if k in state and state[k].shape != own[k].shape]
        if missing or unexpected or wrong_shape:
            details = [f"{len(keys)} {label} (e.g. {', '.join(keys[:3])})" for label, keys in
                       (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong_shape)) if keys]
            raise UserError(f"{key}: {path} does not match {self.name} in efficientnet_pytorch's format: "
                            f"{'; '.join(details)}. Is it a checkpoint of another EfficientNet variant?")
        bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
        if bad:  # loaded silently, then every loss NaN from the first step
            more = f" (and {len(bad) - 1} more tensors)" if len(bad) > 1 else ""
            raise UserError(f"{key}: {path}: the weights {bad[0]}{more} hold NaN or infinite values; the file is "
                            "damaged: fetch it again")
        self.trunk.load_state_dict(state)


def download_imagenet(name: str) -> dict:
    """efficientnet_pytorch's ImageNet state dict of ``name``, through torch's hub cache (downloaded
    once, read from the cache afterwards, also offline). Raises what the download raises."""
    from efficientnet_pytorch.utils import url_map

    return torch.hub.load_state_dict_from_url(url_map[name], progress=False)  # host tensors, as released


def imagenet_state(name: str, download=None) -> dict:
    """The ImageNet state dict of EfficientNet ``name`` through ``download(name)`` (``download_imagenet``
    by default: once over the network, then from torch's hub cache). A failed download is one
    ``UserError`` saying how to give the file instead."""
    try:
        return (download or download_imagenet)(name)
    except Exception as e:  # no network, a proxy, a full disk: the user gives the file instead
        from efficientnet_pytorch.utils import url_map

        reason = " ".join(str(e).split()) or type(e).__name__
        raise UserError(
            f"model.backbone.weights=imagenet: cannot download the ImageNet weights of {name} ({reason}). "
            f"Where there is internet, fetch {url_map[name]} (or run python -c \"import torch; "
            f"from efficientnet_pytorch import EfficientNet; torch.save(EfficientNet.from_pretrained("
            f"'{name}').state_dict(), '{name}.pth')\"), copy the file here and pass "
            f"model.backbone.weights=/path/to/{name}.pth, or put it in torch's hub cache as "
            f"{Path(torch.hub.get_dir()) / 'checkpoints' / url_map[name].rsplit('/', 1)[-1]}"
        ) from None


def load_pretrained_backbone(backbone: EfficientNetBackbone, weights: str, download=None) -> None:
    """Give ``backbone`` the ImageNet weights of ``model.backbone.weights``: ``"imagenet"``
    (``imagenet_state``) or a local file."""
    if weights != "imagenet":
        backbone.load_imagenet_weights(weights)
        return
    state = imagenet_state(backbone.name, download)
    backbone.load_imagenet_state(state, f"the downloaded ImageNet weights of {backbone.name}")


class TinyBackbone(nn.Module):
    """Five strided conv-BN-ReLU (stride 32 in total) and the same ``Up`` fusion; for tests.

    forward: images [B', 3, h, w] -> features [B', out_channels, h/16, w/16].
    """

    def __init__(self, out_channels: int, widths: tuple[int, ...] = (8, 16, 24, 32, 48)):
        super().__init__()
        chans = (3, *widths)
        self.stages = nn.ModuleList(conv_bn_relu(a, b, stride=2) for a, b in zip(chans[:-1], chans[1:]))
        self.up = Up(widths[3], widths[4], out_channels)
        self.out_channels = out_channels

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images
        for stage in self.stages[:4]:
            x = stage(x)
        return self.up(x, self.stages[4](x))
