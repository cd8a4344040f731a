"""What a job needs of the machine, known before it starts: memory and data workers.

``estimate(cfg, job)`` is the peak memory of one training step (``job="train"``) or one inference
batch (``"infer"``) of a config, in bytes, from the config's shapes alone: nothing of that size is
allocated (the parameters are counted on a model built on the meta device). It is the sum of named
terms, each a shape product times the bytes a sample keeps of it, the factors fitted to peaks measured
on this package's models (benchmarks/memory_estimate.py prints estimate against measured peak):

- ``base``: the Python process with torch and the libraries loaded (host memory only);
- ``params``: weights, and for training their gradients and Adam's two moments (4 copies);
- ``images``: the batch's camera images, B x V x 3 x H x W;
- ``backbone``: the image encoder's activations kept for backward, per input pixel and camera
  (``BACKBONE_BYTES_PER_PIXEL``: fewer with ``model.backbone.grad_checkpoint``, which recomputes them);
- ``lift``: LSS's frustum, B x V x D x C x H/16 x W/16;
- ``bev``: the BEV encoder and heads over the grid's cells, B x cells x their width;
- ``graph``: the attentional GNN's N x N attention in each layer, the (N+1)^2 score matrix and
  Sinkhorn (its 100 iterations kept with ``sinkhorn_grad=unrolled``), the N x D vertex features.

``check_fits(cfg, job, device)`` compares the estimate with the memory the process may use
(``memory_available``: a cgroup's limit, else the kernel's MemAvailable; on a GPU its free memory) and
raises one ``UserError`` naming the key whose size dominates, before any data worker starts.
``data_workers(requested, samples)`` lowers ``data.num_workers`` to the usable cores and the samples.
``cpu_flags`` / ``cpu_capability`` read the CPU's extensions; ``reuse_freed_memory`` has glibc keep the large blocks
an inference forward frees for the next one.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import torch

from . import distributed as du
from .config import ExperimentConfig, config_to_dict, flatten, load_config, set_key
from .errors import UserError
from .models import build_model

GB = 1e9
BASE_BYTES = 0.38 * GB  # python + torch + numpy/cv2/shapely imported: a tiny model's step peaks at 0.39 GB
# bytes kept per input pixel of one camera image in a training step: (no recomputation, grad_checkpoint)
BACKBONE_BYTES_PER_PIXEL = {"efficientnet-b0": (2500.0, 700.0), "efficientnet-b4": (6800.0, 1600.0),
                            "tiny": (600.0, 300.0)}
BEV_FLOATS_PER_CHANNEL = 5.0  # floats kept per BEV cell and channel of the widest BEV layer in a training step
INFER_SHARE = 0.35  # an inference batch keeps no activations for backward: this share of a training sample's
# the estimate runs up to ~1.3x over the peaks measured (benchmarks/memory_estimate.py): a config is refused only when
# it exceeds the memory by more than that, and noted when it comes close
REFUSE_OVER = 1.3
NOTE_OVER = 0.8
# a GPU step's max allocated memory against the terms fitted to CPU peaks (which hold the allocator's caches too):
# B0 / B4 LSS 128x352, batch 8, fp32 (benchmarks/README.md, train_speed.py --device cuda) 8.16 / 14.69 GB allocated
GPU_SHARE = 0.75
WORKER_BYTES = 0.1 * GB  # a data-loader worker's own pages (the rest is shared with the parent)
# the keys whose size the terms read: the one whose reset to its default lowers the estimate most is named
SIZE_KEYS = ("model.gnn.num_vertices", "train.batch_size", "eval.batch_size", "data.image_size", "grid.resolution",
             "grid.xbound", "grid.ybound", "model.bev_heads.channels", "model.bev_heads.stage_channels",
             "model.bev_heads.head_channels", "model.backbone.out_channels", "model.backbone.name",
             "model.backbone.grad_checkpoint", "model.gnn.dim", "model.gnn.layers", "model.gnn.heads",
             "model.gnn.sinkhorn_iters", "model.gnn.sinkhorn_grad", "model.view_transform.depth_bound",
             "data.av2_cameras", "data.num_workers")
# the key named for a term when no key's reset lowers the estimate (every size key at its default, or defaults that do
# not fit the rest of the config: a grid resolution that does not divide its extents)
TERM_KEYS = {"images": "data.image_size", "backbone": "data.image_size", "lift": "model.view_transform.depth_bound",
             "bev": "grid.resolution", "graph": "model.gnn.num_vertices", "params": "model.bev_heads.channels",
             "base": "train.batch_size", "workers": "data.num_workers"}
_MODEL_SECTIONS = ("model.", "data.image_size", "grid.", "data.av2_cameras", "data.dataset")


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; all cores where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def num_cameras(cfg: ExperimentConfig) -> int:
    """The cameras of a sample: AV2's chosen ring cameras, else the MLP view transform's count (the rig's)."""
    return len(cfg.data.av2_cameras) if cfg.data.dataset == "av2" else cfg.model.view_transform.num_cameras


def count_parameters(cfg: ExperimentConfig) -> int:
    """The model's parameter count, built on the meta device (no weight is allocated)."""
    with torch.device("meta"), torch.random.fork_rng(devices=[]):
        model = build_model(cfg, pretrained=False)
    return sum(p.numel() for p in model.parameters())


def terms(cfg: ExperimentConfig, job: str = "train", *, host: bool = True, params: int | None = None,
          batch: int | None = None) -> dict:
    """The estimate's named terms in bytes (module docstring); ``job``: train | infer; ``host``: with the
    process's own base and its data workers (CPU), or the device's share only (GPU); ``batch``: samples per
    process (default: ``train.batch_size`` over the processes, ``eval.batch_size`` for inference)."""
    training = job == "train"
    b = max(cfg.train.batch_size // du.get_world_size(), 1) if training else cfg.eval.batch_size
    b = b if batch is None else batch
    V, (h, w) = num_cameras(cfg), cfg.data.image_size
    mb, g, gnn = cfg.model.backbone, cfg.grid, cfg.model.gnn
    off, on = BACKBONE_BYTES_PER_PIXEL.get(mb.name, BACKBONE_BYTES_PER_PIXEL["efficientnet-b4"])
    cells = (g.xbound[1] - g.xbound[0]) * (g.ybound[1] - g.ybound[0]) / g.resolution**2
    heads = cfg.model.bev_heads
    width = max(heads.channels, heads.head_channels, *heads.stage_channels, mb.out_channels)
    vt = cfg.model.view_transform
    depths = max(math.ceil((vt.depth_bound[1] - vt.depth_bound[0]) / vt.depth_bound[2]), 1)
    n = gnn.num_vertices
    iters = gnn.sinkhorn_iters if gnn.sinkhorn_grad == "unrolled" and training else 4
    per_sample = {
        "images": V * 3 * h * w * 4 * 3,
        "backbone": V * h * w * (on if mb.grad_checkpoint else off),
        "lift": V * depths * mb.out_channels * (h // 16) * (w // 16) * 4 * 2 if vt.kind == "lss" else 0,
        "bev": cells * width * 4 * BEV_FLOATS_PER_CHANNEL * (1.5 if cfg.model.temporal.memory != "none" else 1),
        "graph": ((gnn.layers + 1) * gnn.heads * n * n * 12 + (n + 1) ** 2 * 4 * (4 + 2 * iters)
                  + n * gnn.dim * 4 * 8 * max(gnn.layers, 1)),
    }
    share = (1.0 if training else INFER_SHARE) * (1.0 if host else GPU_SHARE)
    out = {k: v * b * share for k, v in per_sample.items()}
    out["params"] = (count_parameters(cfg) if params is None else params) * 4 * (4 if training else 1)
    if host:
        out["base"] = BASE_BYTES
        out["workers"] = min(cfg.data.num_workers, usable_cores()) * WORKER_BYTES
    return out


def estimate(cfg: ExperimentConfig, job: str = "train", *, host: bool = True, batch: int | None = None) -> float:
    """Peak bytes of one training step / inference batch of ``cfg`` (the sum of ``terms``)."""
    return sum(terms(cfg, job, host=host, batch=batch).values())


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def _cgroup_room() -> float | None:
    """Bytes this process's cgroup still allows (v2 memory.max - memory.current, or v1's), None without a limit."""
    own = (_read("/proc/self/cgroup") or "").splitlines()
    v2 = next((line.split("::", 1)[1] for line in own if line.startswith("0::")), None)
    own_dir = f"/sys/fs/cgroup{v2.rstrip('/')}" if v2 else None
    pairs = [(f"{own_dir}/memory.max", f"{own_dir}/memory.current")] if own_dir else []
    pairs += [("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
              ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")]
    for limit_path, usage_path in pairs:
        limit, usage = _read(limit_path), _read(usage_path)
        if limit and limit.isdigit() and int(limit) < 2**60:  # v1 writes "no limit" as a huge number
            return float(int(limit) - int(usage or 0))
    return None


def memory_available(device: torch.device | None = None) -> tuple[float, str]:
    """(bytes the job may still use, where that figure comes from): a GPU's free memory, else the smaller of the
    kernel's MemAvailable and a cgroup's room, plus what this process holds already (its base is in the estimate)."""
    if device is not None and device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return float(free), f"{torch.cuda.get_device_name(device)} has"
    meminfo = dict(line.split(":", 1) for line in (_read("/proc/meminfo") or "").splitlines() if ":" in line)
    avail = float(meminfo["MemAvailable"].split()[0]) * 1024 if "MemAvailable" in meminfo else math.inf
    room = _cgroup_room()
    what = "this machine has"
    if room is not None and room < avail:
        avail, what = room, "this process's cgroup allows"
    return avail + resident_bytes(), what


def _status_bytes(field: str) -> int | None:
    """A memory field of /proc/self/status (kB there) in bytes; None off Linux."""
    for line in (_read("/proc/self/status") or "").splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return None


def resident_bytes() -> int:
    """The memory this process holds now (its resident set)."""
    return _status_bytes("VmRSS") or 0


def peak_resident_bytes() -> int:
    """The most memory this program has held since it started (VmHWM). Not ``getrusage``'s ``ru_maxrss``: Linux
    carries that across ``exec`` from the process that spawned this one, so a child of a 2 GB parent reports 2 GB."""
    peak = _status_bytes("VmHWM")
    if peak is not None:
        return peak
    import resource  # not on Windows; macOS reports bytes, Linux kB
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss if sys.platform == "darwin" else rss * 1024


def human(n: float) -> str:
    """Bytes as people read them: 1.2 TB, 22 GB, 0.46 GB."""
    for unit, size in (("EB", 1e18), ("PB", 1e15), ("TB", 1e12)):
        if n >= size:
            return f"{n / size:.2g} {unit}" if n < 10 * size else f"{n / size:.0f} {unit}"
    return f"{n / GB:.2g} GB" if n < 10 * GB else f"{n / GB:.0f} GB"


def dominant_key(cfg: ExperimentConfig, job: str, host: bool, batch: int | None = None) -> str:
    """The size key whose reset to its default lowers the estimate most (else ``TERM_KEYS`` of the largest term, or
    the batch)."""
    default, now = flatten(config_to_dict(ExperimentConfig())), flatten(config_to_dict(cfg))
    params = count_parameters(cfg)
    parts = terms(cfg, job, host=host, params=params, batch=batch)
    # if no reset helps: the largest term's key where it is not its default, else the batch (the first lever)
    best, best_key = sum(parts.values()), TERM_KEYS[max(parts, key=parts.get)]
    if now[best_key] == default[best_key]:
        best_key = "train.batch_size" if job == "train" else "eval.batch_size"
    for key in SIZE_KEYS:
        if key not in now or now[key] == default[key]:
            continue
        values = config_to_dict(cfg)
        set_key(values, key, default[key])  # the same config with this one key at its default
        reuse = None if any(key.startswith(s) for s in _MODEL_SECTIONS) else params
        try:
            size = sum(terms(load_config(values), job, host=host, params=reuse, batch=batch).values())
        except (UserError, ValueError):  # its default does not fit the rest (a grid, heads vs dim): not this key
            continue
        if size < best:
            best, best_key = size, key
    return best_key


def _override_value(value) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(map(str, value)) + "]"
    return "null" if value is None else str(value)


def check_fits(cfg: ExperimentConfig, job: str = "train", device: torch.device | None = None,
               batch: int | None = None) -> float:
    """Raise one ``UserError`` when ``estimate(cfg, job)`` exceeds ``memory_available(device)`` by more than the
    estimate's error (``REFUSE_OVER``; a note when it comes close), naming the key that dominates, e.g.
    "model.gnn.num_vertices=100000000: one training step needs ~61 EB, this machine has 22 GB available"; return
    the estimate otherwise."""
    host = device is None or device.type != "cuda"
    need = estimate(cfg, job, host=host, batch=batch)
    have, what = memory_available(device)
    step = "one training step" if job == "train" else "one inference batch"
    if NOTE_OVER * have < need <= REFUSE_OVER * have:
        du.print_main(f"note: {step} may need ~{human(need)} and {what} {human(have)} available: it may run out of "
                      "memory")
    if need > REFUSE_OVER * have:
        key = dominant_key(cfg, job, host, batch)
        value = flatten(config_to_dict(cfg))[key]
        change = {"grid.resolution": "raise it", "grid.xbound": "narrow it", "grid.ybound": "narrow it",
                  "model.backbone.grad_checkpoint": "set it to true", "model.backbone.name": "choose a smaller one",
                  "model.gnn.sinkhorn_grad": "set it to implicit"}.get(key, "lower it")
        raise UserError(f"{key}={_override_value(value)}: {step} needs ~{human(need)}, {what} {human(have)} "
                        f"available; {change} (the estimate per part: instagram-hdmap model-summary CONFIG)")
    return need


_noted: set[tuple[int, int]] = set()


def data_workers(requested: int, samples: int | None = None) -> int:
    """``data.num_workers`` lowered to the usable cores (and to the loader's samples): more workers than cores only
    wait for each other (a thousand take minutes to start for one batch), and torch warns of them. One note per
    setting and process."""
    fitted = min(requested, usable_cores(), requested if samples is None else max(samples, 1))
    if fitted < requested and (requested, fitted) not in _noted:
        _noted.add((requested, fitted))
        why = (f"this process may use {fitted} CPU cores" if fitted == usable_cores()
               else f"the split has {samples} sample(s)")
        du.print_main(f"note: data.num_workers={requested} lowered to {fitted}: {why}")
    return fitted


def size_notes(cfg: ExperimentConfig) -> list[str]:
    """Notes on sizes that run, but not as they read: more vertices than the grid has cells (the top-N takes at most
    one vertex per cell; the rest is padding)."""
    g = cfg.grid
    cells = round((g.xbound[1] - g.xbound[0]) / g.resolution / g.cell_size) * round(
        (g.ybound[1] - g.ybound[0]) / g.resolution / g.cell_size)
    n = cfg.model.gnn.num_vertices
    if n > cells:
        return [f"note: model.gnn.num_vertices={n} is more than the grid's {cells} cells of "
                f"grid.cell_size={g.cell_size}: at most {cells} vertices are found (one per cell), the other "
                f"{n - cells} rows are padding"]
    return []


def summary_lines(cfg: ExperimentConfig) -> list[str]:
    """``model-summary``'s memory lines: the estimate of a training step and of an inference batch, per term."""
    lines = []
    for job, what in (("train", f"training step (train.batch_size={cfg.train.batch_size})"),
                      ("infer", f"inference batch (eval.batch_size={cfg.eval.batch_size})")):
        parts = terms(cfg, job)
        big = sorted((kv for kv in parts.items() if kv[1] >= 0.005 * GB), key=lambda kv: -kv[1])
        detail = ", ".join(f"{k} {human(v)}" for k, v in big)
        lines.append(f"memory of one {what}: ~{human(sum(parts.values()))} ({detail})")
    have, where = memory_available()
    lines.append(f"memory available: {where} {human(have)} (CPU; a GPU's free memory is checked on it)")
    return lines


# /proc/cpuinfo flags of the instruction sets that decide a convolution's speed here, in the order they build on
# each other: AVX2, AVX-512, AVX-512 with bf16 dot products, AMX tiles for bf16 and int8 matrix products
# (int8 convolutions run on the VNNI dot products where a CPU has them, bf16 on AVX512-BF16 or AMX)
CPU_FLAGS = (("avx2", "AVX2"), ("avx512f", "AVX512"), ("avx_vnni", "AVX-VNNI"), ("avx512_vnni", "AVX512-VNNI"),
             ("avx512_bf16", "AVX512-BF16"), ("amx_bf16", "AMX-BF16"), ("amx_int8", "AMX-INT8"))


def cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> set[str]:
    """The flags of the first processor in ``cpuinfo`` (empty where there is no such file: macOS, Windows)."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith(("flags", "Features")):  # x86, ARM
            return set(line.split(":", 1)[1].split())
    return set()


def cpu_capability(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """What a CPU figure was measured on: the CPU's vector and matrix extensions and the level torch's kernels
    dispatch to, e.g. ``AVX2 AVX512 AVX512-BF16 AMX-BF16 AMX-INT8; torch kernels: AVX2``. A CPU may have none of
    them (bf16 is then emulated, and slow): this is read from the machine, never assumed."""
    flags = cpu_flags(cpuinfo)
    have = " ".join(name for flag, name in CPU_FLAGS if flag in flags) or "none of AVX2 / AVX512 / AMX"
    try:
        level = torch.backends.cpu.get_cpu_capability()
    except (AttributeError, RuntimeError):  # a torch without it
        level = "unknown"
    return f"{have}; torch kernels: {level}"


# glibc's mallopt parameters (malloc.h) and the values inference sets: blocks up to 1 GiB come from the heap, and up
# to 2 GiB of free heap top is kept (mallopt takes a C int)
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
REUSED_MEMORY = {M_MMAP_THRESHOLD: 1 << 30, M_TRIM_THRESHOLD: (1 << 31) - 1, M_TOP_PAD: 64 << 20}


def reuse_freed_memory() -> bool:
    """Have glibc's malloc keep the large blocks a forward frees, for the next forward to reuse: True where it
    did (Linux with glibc), False elsewhere (another C library: nothing is changed).

    By default glibc maps every block over 32 MiB afresh from the kernel and returns it when freed, so each
    forward of a paper config faults in its BEV tensors (B4 at 200 x 400 cells: 80 MB each) page by page again:
    10-20 % of a bf16 / int8 forward on the CPU (``benchmarks/model_speed.py``). With this, such blocks come
    from the heap and stay there once freed. Process-wide, as the environment variables ``MALLOC_MMAP_THRESHOLD_``
    / ``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_TOP_PAD_`` would set it: the process keeps the memory of its largest
    forward instead of handing it back between forwards. Inference (``Mapper``, predict, evaluate, benchmark)
    and training call it on the CPU (a training step frees and takes again its activations, smaller blocks that
    glibc's trimming handed back all the same)."""
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return all(mallopt(param, value) == 1 for param, value in REUSED_MEMORY.items())


def out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says that memory ran out: Python's (numpy's) ``MemoryError``, torch's CUDA
    ``OutOfMemoryError``, or the RuntimeError of torch's CPU allocator."""
    if isinstance(e, MemoryError) or type(e).__name__ == "OutOfMemoryError":
        return True
    return isinstance(e, RuntimeError) and ("can't allocate memory" in str(e) or "out of memory" in str(e).lower())
