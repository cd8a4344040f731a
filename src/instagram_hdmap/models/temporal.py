"""Streaming temporal fusion: the previous frame's BEV features, warped into the current ego frame by
the relative ego pose, fused with the current BEV features (docs/temporal.md).

Shapes: B batch, C channels, h x w a BEV feature map covering the whole grid extent (any resolution;
in the model the half-resolution grid of F_bev's first stage, H/2 x W/2).

What the memory holds (``model.temporal.memory``): ``bev`` the fused BEV features of the previous frame
(StreamMapNet's BEV memory); ``graph`` the previous frame's predicted map graph (its vertices with their
scores, its edges with their classes: the graph head's output) rendered as a raster of K + 1 channels
(``render_graph``), the InstaGraM-specific memory; ``bev+graph`` both. Either is warped the same way and
fed to the same fusion.

The memory (``InstaGraM.forward(batch, memory)`` in and ``outputs["memory"]`` out) is a dict of
tensors, ``MEMORY_KEYS``:

* ``bev`` [B, M, h, w]: the previous frame's BEV memory map, detached (no gradient crosses a step, as
  StreamMapNet): its fused features (C channels, ``bev``), then its graph raster (K + 1 channels,
  ``graph``), M = ``BEVMemoryFusion.memory_channels``;
* ``ego_pose`` [B, 4, 4]: that frame's ego -> global pose;
* ``valid`` [B] bool: the row holds a frame (False: empty memory, ``initial_memory``);
* ``frame_index`` [B] int64: that frame's index in its scene.

Which samples fuse (``memory_status``, one code per sample, ``STATUS_NAMES``): a sample fuses its
memory (``FUSED``) unless the memory row is empty or the batch flags a scene start (``NO_MEMORY``),
the ego moved more than ``max_jump_m`` or turned more than ``max_turn_deg`` since the memory's frame
(``POSE_JUMP``: the real AV2 log of ../shared/av2_real turns at most 14.6 degrees per half second, the
nuScenes keyframe interval, the synthetic worlds up to 35; a spin of 60 or more is a pose in the wrong
unit or frame), the frame does not follow the memory's frame (``frame_index`` not one more:
``MISSING_FRAME``), or, in training, the memory was dropped at random (``DROPPED``). A batch row flagged
``replaced`` (``data.on_bad_sample=skip`` put another sample in place of a bad frame) is a missing frame:
``MISSING_FRAME``, never fused, and the memory it leaves is empty (the next frame starts anew, ``NO_MEMORY``).
A sample that does not fuse uses its own features only
(the fusion still runs, with an all-invalid history, so every parameter always gets a gradient) and
starts a new memory. A frame index at or below the memory's one, without a scene start, is frames out
of order: ``FrameOrderError`` naming the scene (eager mode; an exported graph or a captured CUDA graph
cannot raise, nor wait for the host to look).

The warp (StreamMapNet's ``update_bev_feature``, here batched): every current BEV cell centre
(x, y, 0) in metres is mapped into the previous ego frame by ``prev_pose^-1 @ cur_pose`` and the
memory is sampled there bilinearly (``grid_sample``, ``align_corners=False``, geometry.py's
normalised convention); cells whose centre falls outside the previous grid have no history and are
masked (``valid`` channel 0).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..config import UserError
from ..geometry import BEVGrid

MEMORY_KEYS = ("bev", "ego_pose", "valid", "frame_index")
FUSED, NO_MEMORY, POSE_JUMP, MISSING_FRAME, DROPPED = 0, 1, 2, 3, 4
STATUS_NAMES = ("fused", "no_memory", "pose_jump", "missing_frame", "dropped")


class FrameOrderError(UserError):
    """Frames of one scene given out of order to a temporal model."""


# --- geometry (plain functions) ---------------------------------------------------------------------


def rigid_inverse(pose: torch.Tensor) -> torch.Tensor:
    """[..., 4, 4] rigid transforms -> their inverses (R^T, -R^T t), in plain ops (ONNX has no inverse)."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    trans = -(rot_t @ pose[..., :3, 3:4])
    bottom = pose[..., 3:4, :]
    return torch.cat([torch.cat([rot_t, trans], -1), bottom], -2)


def relative_pose(prev_pose: torch.Tensor, cur_pose: torch.Tensor) -> torch.Tensor:
    """[B, 4, 4] ego -> global poses of two frames -> [B, 4, 4] current ego frame -> previous ego frame."""
    return rigid_inverse(prev_pose.float()) @ cur_pose.float()


def bev_plane_m(grid: BEVGrid, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """[h * w, 4] homogeneous metre coordinates (x, y, 0, 1) of the cell centres of an h x w map over
    the grid's extent, row-major (rows along y, columns along x)."""
    x = grid.xmin + (torch.arange(w, device=like.device, dtype=torch.float32) + 0.5) * ((grid.xmax - grid.xmin) / w)
    y = grid.ymin + (torch.arange(h, device=like.device, dtype=torch.float32) + 0.5) * ((grid.ymax - grid.ymin) / h)
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    zeros = torch.zeros_like(xx)
    return torch.stack([xx, yy, zeros, zeros + 1], -1).reshape(h * w, 4)


def warp_bev(features: torch.Tensor, cur_to_prev: torch.Tensor, grid: BEVGrid,
             plane: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A BEV map of the previous frame seen from the current one.

    features [B, C, h, w] over the grid's extent in the previous ego frame, cur_to_prev [B, 4, 4]
    (``relative_pose``) -> (warped [B, C, h, w] in the current ego frame, ``inside`` [B, 1, h, w] bool:
    cells the previous map covered; elsewhere the warped values are the border's and meaningless)."""
    h, w = features.shape[-2:]
    if plane is None:
        plane = bev_plane_m(grid, h, w, features)
    prev = torch.einsum("bij,pj->bpi", cur_to_prev.float(), plane)  # [B, h*w, 4] the cells in the previous frame
    gx = (prev[..., 0] - grid.xmin) * (2.0 / (grid.xmax - grid.xmin)) - 1.0  # grid_sample's (x, y) order
    gy = (prev[..., 1] - grid.ymin) * (2.0 / (grid.ymax - grid.ymin)) - 1.0
    norm = torch.stack([gx, gy], -1).reshape(-1, h, w, 2)
    inside = (gx > -1) & (gx < 1) & (gy > -1) & (gy < 1)
    warped = F.grid_sample(features, norm.to(features.dtype), mode="bilinear", padding_mode="border",
                           align_corners=False)
    return warped, inside.reshape(-1, 1, h, w)


# --- the graph memory: the previous frame's map graph as a raster --------------------------------------


def render_graph(graph: dict[str, torch.Tensor], grid: BEVGrid, h: int, w: int, samples: int = 8) -> torch.Tensor:
    """The predicted map graph of a frame, drawn on an h x w map over the grid (no gradient).

    ``graph``: the graph head's outputs (``pred_vertices_px`` [B, N, 2] BEV pixels, ``pred_vertex_mask``
    [B, N], ``pred_vertex_scores`` [B, N], ``pred_class_log_probs`` [B, N, K], ``pred_log_assignment``
    [B, N+1, N+1]) -> [B, K + 1, h, w] in [0, 1]:

    * channel k < K: the edges of class k. Each real vertex i is joined to its most likely successor
      j = argmax_j P[i, j] (P = exp(log assignment) without the dustbin, the matrix the decoders follow);
      ``samples`` points along the edge each add P[i, j] times the mean class probability of i and j to
      the cell they fall in;
    * channel K: the vertices, each adding its score to its cell.

    Sums are clipped at 1 (a presence map). Only tensor ops (scatter-add, gather), so the graph exports to
    ONNX with the rest of the model.
    """
    with torch.no_grad():
        px = graph["pred_vertices_px"].float()  # [B, N, 2] (u, v), pixel centres at integers
        mask = graph["pred_vertex_mask"].bool()
        B, N = mask.shape
        scores = graph["pred_vertex_scores"].float() * mask
        probs = graph["pred_class_log_probs"].float().exp()  # [B, N, K]
        K = probs.shape[-1]
        adjacency = graph["pred_log_assignment"][:, :N, :N].float().exp()  # [B, N, N], row i -> column j
        weight, successor = adjacency.max(-1)  # [B, N]
        succ_mask = mask.gather(1, successor)
        weight = weight * (mask & succ_mask)
        succ_px = px.gather(1, successor[..., None].expand(B, N, 2))
        succ_probs = probs.gather(1, successor[..., None].expand(B, N, K))
        t = torch.linspace(0.0, 1.0, samples, device=px.device)[None, None, :, None]  # [1, 1, T, 1]
        points = px[:, :, None] + t * (succ_px - px)[:, :, None]  # [B, N, T, 2]
        value = weight[..., None] * 0.5 * (probs + succ_probs)  # [B, N, K]

        def cell(uv: torch.Tensor) -> torch.Tensor:  # BEV pixels -> flat index of the h x w cell
            col = torch.floor((uv[..., 0] + 0.5) * (w / grid.W)).clamp(0, w - 1)
            row = torch.floor((uv[..., 1] + 0.5) * (h / grid.H)).clamp(0, h - 1)
            return (row * w + col).long()

        edge_cells = cell(points)  # [B, N, T]
        channel = torch.arange(K, device=px.device) * (h * w)  # [K]
        index = (edge_cells[..., None] + channel).reshape(B, -1)  # [B, N*T*K]
        edge_value = value[:, :, None, :].expand(B, N, samples, K).reshape(B, -1)
        edges = px.new_zeros(B, K * h * w).scatter_add(1, index, edge_value).reshape(B, K, h, w)
        vertices = px.new_zeros(B, h * w).scatter_add(1, cell(px), scores).reshape(B, 1, h, w)
        return torch.cat([edges, vertices], 1).clamp(max=1.0)


# --- which samples fuse --------------------------------------------------------------------------


def memory_status(batch: dict, memory: dict[str, torch.Tensor], max_jump_m: float,
                  drop: torch.Tensor | None = None, max_turn_deg: float = 180.0) -> torch.Tensor:
    """[B] int64 status codes (module docstring) of a batch against its memory. ``drop`` [B] bool:
    memories dropped on purpose (training). Raises ``FrameOrderError`` (eager only) for frames out of
    order inside a scene."""
    valid = memory["valid"].bool()
    B = valid.shape[0]
    start = batch.get("scene_start")
    start = valid.new_zeros(B) if start is None else start.bool().reshape(B)
    rel = batch["ego_pose"][:, :2, 3].float() - memory["ego_pose"][:, :2, 3].float()
    jump = (rel * rel).sum(-1) > max_jump_m * max_jump_m
    if max_turn_deg < 180:  # the angle of the relative rotation: cos = (trace(R_prev^T R_cur) - 1) / 2
        turn = (memory["ego_pose"][:, :3, :3].float() * batch["ego_pose"][:, :3, :3].float()).sum((-1, -2))
        jump = jump | ((turn - 1) * 0.5 < math.cos(math.radians(max_turn_deg)))
    frame = batch.get("frame_index")
    replaced = _replaced(batch, B, valid)
    if frame is not None:
        gap = frame.reshape(B).long() - memory["frame_index"].long()
        missing = gap != 1
        _check_order(batch, valid & ~start & ~replaced & (gap <= 0), frame, memory["frame_index"])
    else:
        missing = valid.new_zeros(B)
    status = torch.full_like(memory["frame_index"].long(), FUSED)
    status = torch.where(missing, torch.full_like(status, MISSING_FRAME), status)
    status = torch.where(jump, torch.full_like(status, POSE_JUMP), status)
    if drop is not None:
        status = torch.where(drop, torch.full_like(status, DROPPED), status)
    status = torch.where(~valid | start, torch.full_like(status, NO_MEMORY), status)
    return torch.where(replaced, torch.full_like(status, MISSING_FRAME), status)


def _replaced(batch: dict, B: int, like: torch.Tensor) -> torch.Tensor:
    """[B] bool: rows standing in for a bad frame (``replaced``; none without the key)."""
    flag = batch.get("replaced")
    return like.new_zeros(B) if flag is None else flag.bool().reshape(B).to(like.device)


def _check_order(batch: dict, backwards: torch.Tensor, frame: torch.Tensor, previous: torch.Tensor) -> None:
    capturing = backwards.is_cuda and torch.cuda.is_current_stream_capturing()
    if torch.compiler.is_compiling() or torch.jit.is_tracing() or capturing or not bool(backwards.any()):
        return
    b = int(backwards.nonzero()[0, 0])
    scenes = batch.get("scene")
    scene = f"scene '{scenes[b]}'" if isinstance(scenes, (list, tuple)) else f"the scene of batch row {b}"
    raise FrameOrderError(
        f"{scene}: frame {int(frame.reshape(-1)[b])} follows frame {int(previous[b])} in the stream; a temporal "
        "model needs each scene's frames in order (flag a new pass over a scene with scene_start, or reset the memory)")


# --- the fusion module -----------------------------------------------------------------------------


MEMORIES = ("bev", "graph", "bev+graph")


class BEVMemoryFusion(nn.Module):
    """Current BEV features + warped memory -> fused features, the new memory and the status.

    ``memory``: what the memory map holds (module docstring); ``num_classes`` K (the graph raster's K + 1
    channels), ``edge_samples`` (``render_graph``).
    ``fusion="gated"``: ``[g, d] = conv([x, m * warped, m])``, ``fused = x + sigmoid(g) * d`` with the last
    convolution zero-initialised, so an untrained fusion is the identity (the single-frame model).
    ``fusion="gru"``: StreamMapNet's ConvGRU (``necks/gru.py``): ``z, r = sigmoid(conv([h, x, m]))``,
    ``q = conv([r * h, x])``, ``fused = LayerNorm((1 - z) h + z q)`` over channels, with the history
    ``h = m * warped + (1 - m) * x`` (a cell without history starts from its current features); with a
    graph raster (``bev+graph``) the warped raster joins the gates' and the candidate's inputs. ``graph``
    alone has no features to carry: the gated fusion only.
    """

    def __init__(self, channels: int, grid: BEVGrid, size: tuple[int, int], fusion: str = "gated",
                 kernel: int = 1, drop_prob: float = 0.0, max_jump_m: float = 10.0, memory: str = "bev",
                 num_classes: int = 0, edge_samples: int = 8, max_turn_deg: float = 180.0):
        super().__init__()
        if memory not in MEMORIES:
            raise ValueError(f"memory must be one of {MEMORIES}, got {memory!r}")
        if memory == "graph" and fusion != "gated":
            raise ValueError("a graph memory alone is fused by the gated fusion (the GRU carries BEV features)")
        self.channels, self.grid, self.size = channels, grid, tuple(size)
        self.fusion, self.drop_prob, self.max_jump_m = fusion, drop_prob, max_jump_m
        self.memory, self.edge_samples, self.max_turn_deg = memory, edge_samples, max_turn_deg
        self.bev_channels = channels if memory in ("bev", "bev+graph") else 0
        self.graph_channels = num_classes + 1 if memory in ("graph", "bev+graph") else 0
        self.memory_channels = self.bev_channels + self.graph_channels
        pad = kernel // 2
        c, g = channels, self.graph_channels
        if fusion == "gated":
            self.mix = nn.Sequential(nn.Conv2d(c + self.memory_channels + 1, c, kernel, padding=pad),
                                     nn.ReLU(inplace=True))
            self.out = nn.Conv2d(c, 2 * c, 1)
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)
        else:
            self.gates = nn.Conv2d(2 * c + g + 1, 2 * c, kernel, padding=pad)
            self.candidate = nn.Conv2d(2 * c + g, c, kernel, padding=pad)
            self.norm = nn.LayerNorm(c)
        h, w = self.size
        self.register_buffer("plane", bev_plane_m(grid, h, w, torch.zeros(())), persistent=False)

    def initial_memory(self, batch_size: int, like: torch.Tensor) -> dict[str, torch.Tensor]:
        """An empty memory of ``batch_size`` rows (``valid`` all False) on ``like``'s device."""
        h, w = self.size
        return {
            "bev": like.new_zeros(batch_size, self.memory_channels, h, w, dtype=torch.float32),
            "ego_pose": torch.eye(4, device=like.device).expand(batch_size, 4, 4).contiguous(),
            "valid": torch.zeros(batch_size, dtype=torch.bool, device=like.device),
            "frame_index": torch.zeros(batch_size, dtype=torch.long, device=like.device),
        }

    def forward(self, x: torch.Tensor, batch: dict, memory: dict[str, torch.Tensor] | None
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        """x [B, C, h, w] -> (fused [B, C, h, w], new memory, status [B] int64)."""
        B = x.shape[0]
        if memory is None:
            memory = self.initial_memory(B, x)
        missing = [k for k in MEMORY_KEYS if k not in memory]
        if missing:
            raise KeyError(f"the memory lacks {missing}: pass back outputs['memory'] of the previous frame")
        if memory["bev"].shape[0] != B:
            raise ValueError(f"the memory holds {memory['bev'].shape[0]} rows for a batch of {B}: one memory row "
                             "per stream, in the same order every step")
        if memory["bev"].shape[1] != self.memory_channels:
            raise ValueError(f"the memory map has {memory['bev'].shape[1]} channels, this model's "
                             f"(model.temporal.memory={self.memory}) has {self.memory_channels}: pass back "
                             "outputs['memory'] of this model, or None to start anew")
        if tuple(memory["bev"].shape[-2:]) != self.size:  # a model of another grid or BEV size
            raise ValueError(f"the memory map is {memory['bev'].shape[-2]} x {memory['bev'].shape[-1]} cells, this "
                             f"model's {self.size[0]} x {self.size[1]} (another grid): pass back outputs['memory'] of "
                             "this model, or None to start anew")
        drop = None
        if self.training and self.drop_prob > 0:
            drop = torch.rand(B, device=x.device) < self.drop_prob
        status = memory_status(batch, memory, self.max_jump_m, drop, self.max_turn_deg)
        use = status == FUSED  # [B]
        cur_to_prev = relative_pose(memory["ego_pose"], batch["ego_pose"])
        warped, inside = warp_bev(memory["bev"].to(x.dtype), cur_to_prev, self.grid, self.plane)
        m = (inside & use[:, None, None, None]).to(x.dtype)  # [B, 1, h, w] cells with history
        fused = self._fuse(x, warped * m, m)
        frame = batch.get("frame_index")
        frame = memory["frame_index"] + 1 if frame is None else frame.reshape(B).long()
        new_memory = {
            "bev": fused.detach().float() if self.bev_channels else None,  # the graph raster: ``remember_graph``
            "ego_pose": batch["ego_pose"].detach().float(),
            "valid": ~_replaced(batch, B, memory["valid"]),
            "frame_index": frame.detach(),
        }
        return fused, new_memory, status

    def remember_graph(self, memory: dict[str, torch.Tensor], graph: dict[str, torch.Tensor]) -> dict:
        """The new memory of ``forward`` completed with this frame's predicted graph (``render_graph``, the
        graph head's outputs) where the memory holds one; the memory map is then whole."""
        if not self.graph_channels:
            return memory
        h, w = self.size
        raster = render_graph(graph, self.grid, h, w, self.edge_samples)
        bev = raster if memory["bev"] is None else torch.cat([memory["bev"], raster], 1)
        return {**memory, "bev": bev}

    def _fuse(self, x: torch.Tensor, history: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        if self.fusion == "gated":
            gate_logits, delta = self.out(self.mix(torch.cat([x, history, m], 1))).chunk(2, 1)
            return x + torch.sigmoid(gate_logits) * delta
        graph = [history[:, self.channels:]] if self.graph_channels else []  # the warped graph raster
        h = history[:, :self.channels] + (1 - m) * x
        z, r = torch.sigmoid(self.gates(torch.cat([h, x, *graph, m], 1))).chunk(2, 1)
        q = self.candidate(torch.cat([r * h, x, *graph], 1))
        out = (1 - z) * h + z * q
        return self.norm(out.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
