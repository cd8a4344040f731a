"""Devices and torchrun: the device a job runs on, init from the environment, rank-aware printing,
reductions, sampler.

Works unchanged in a single process (world size 1). Under ``torchrun`` the environment variables
``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` select NCCL on GPUs and gloo on CPU.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import torch
import torch.distributed as dist
from torch.utils.data import Sampler

from .config import UserError


def resolve_device(choice: str | torch.device | None = "auto", key: str = "train.device") -> torch.device:
    """The device of a job: ``"auto"`` (or None) is CUDA when a CUDA device is available, else the CPU;
    ``"cpu"``, ``"cuda"``, ``"cuda:1"`` or a ``torch.device`` as given. Asking for CUDA on a machine
    without it is a ``UserError`` naming ``key`` (the config key or argument that asked)."""
    if choice is None or choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(choice)
    except (RuntimeError, TypeError):
        raise UserError(f"{key}={choice!r} is not a device; use auto, cpu, cuda or cuda:INDEX") from None
    if device.type not in ("cpu", "cuda"):  # torch knows mps, xpu, meta, ...: this package runs on cpu and cuda
        raise UserError(f"{key}={choice} is not supported; use auto, cpu, cuda or cuda:INDEX")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"{key}={choice} but no CUDA device is available; use {key}=cpu")
    return device


def is_dist() -> bool:
    return dist.is_available() and dist.is_initialized()


def get_rank() -> int:
    return dist.get_rank() if is_dist() else 0


def get_world_size() -> int:
    return dist.get_world_size() if is_dist() else 1


def is_main_process() -> bool:
    return get_rank() == 0


def init_distributed(device_kind: str | None = None) -> torch.device:
    """Initialise the process group if launched by torchrun; return this process's device.

    ``device_kind``: "cpu" or "cuda"; ``None`` picks CUDA when available.
    """
    kind = device_kind or ("cuda" if torch.cuda.is_available() else "cpu")
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ and not is_dist():
        missing = [v for v in ("MASTER_ADDR", "MASTER_PORT") if not os.environ.get(v)]
        if missing:  # RANK and WORLD_SIZE left in the environment (a shell, a job script), not a torchrun launch
            raise UserError(f"RANK and WORLD_SIZE are set (a torchrun launch) but {' and '.join(missing)} "
                            f"{'is' if len(missing) == 1 else 'are'} not: launch with torchrun, or unset RANK and "
                            "WORLD_SIZE for a single process")
        if kind == "cuda":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
        dist.init_process_group(backend="nccl" if kind == "cuda" else "gloo")
    return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0))) if kind == "cuda" else torch.device("cpu")


_ENDED = False  # this process destroyed its process group (a torchrun rank whose job is done)


def cleanup() -> None:
    global _ENDED
    if is_dist():
        dist.destroy_process_group()
        _ENDED = True


def group_ended() -> bool:
    """Whether ``cleanup`` destroyed this process's process group (it was a rank of a torchrun job)."""
    return _ENDED


def barrier() -> None:
    if is_dist():
        dist.barrier()


def print_main(*args, **kwargs) -> None:
    if is_main_process():
        print(*args, **kwargs)


@torch.no_grad()
def reduce_dict(values: dict[str, float | torch.Tensor], device: torch.device | None = None) -> dict[str, float]:
    """Average scalar values over all processes (for logging); returns Python floats."""
    keys = sorted(values)
    if not keys:
        return {}
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    if is_dist():
        dist.all_reduce(t)
        t /= get_world_size()
    return dict(zip(keys, t.tolist()))


def all_gather_object(obj):
    """List of ``obj`` from every rank (``[obj]`` in a single process)."""
    if not is_dist():
        return [obj]
    out = [None] * get_world_size()
    dist.all_gather_object(out, obj)
    return out


class ResumableSampler(Sampler[int]):
    """DistributedSampler-like: a seeded permutation per epoch, split over ranks, that can start
    part-way into an epoch so a resumed run sees exactly the batches it had not seen.

    Like ``DistributedSampler(drop_last=False)``, the index list is padded by wrapping around so that
    every rank gets the same number of samples.
    """

    def __init__(self, dataset_len: int, shuffle: bool = True, seed: int = 0,
                 rank: int | None = None, world_size: int | None = None):
        self.n = dataset_len
        self.shuffle = shuffle
        self.seed = seed
        self.rank = get_rank() if rank is None else rank
        self.world_size = get_world_size() if world_size is None else world_size
        self.epoch = 0
        self.start = 0  # samples of the epoch's order, over all ranks, to skip (set by the trainer on resume)
        self.num_samples = -(-self.n // self.world_size)

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Select ``epoch``'s order and skip its first ``start`` samples *over all ranks* (a resumed run:
        steps done x the batch of all ranks). Rank r's share of step k is positions ``k * B + r :: world``
        of the epoch's order, so the samples of the first k steps are its first ``k * B`` positions whatever
        the number of ranks: a run saved part-way by N processes resumes exactly under M (each sample of the
        epoch once, none skipped), as long as the batch over all ranks is the same."""
        self.epoch, self.start = epoch, start

    def indices(self) -> list[int]:
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            order = torch.randperm(self.n, generator=g).tolist()
        else:
            order = list(range(self.n))
        total = self.num_samples * self.world_size
        while len(order) < total:  # wrapping around (more than once: tiny datasets with many ranks)
            order += order[: total - len(order)]
        return order[self.start + self.rank : total : self.world_size]

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices())

    def __len__(self) -> int:
        return len(range(self.start + self.rank, self.num_samples * self.world_size, self.world_size))
