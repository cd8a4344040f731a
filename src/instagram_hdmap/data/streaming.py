"""Drives as data: B parallel streams, each walking whole scenes in order (docs/temporal.md).

    sampler = StreamingBatchSampler(dataset.scenes.runs, streams=4, seed=0, rank=r, world_size=R)
    loader = DataLoader(dataset, batch_sampler=sampler, collate_fn=collate_fn)
    sampler.set_epoch(epoch, start=steps_done_in_epoch * streams)

Every step yields one batch per rank of ``streams`` dataset indices: row b of every batch of an epoch
is the next frame of stream b, so a temporal model's memory row b always belongs to stream b. Scenes
are dealt to the ``world_size * streams`` streams of all ranks by longest-processing-time list
scheduling (longest scene first, each to the stream with the fewest frames so far; ties to the lowest
stream), so every scene is walked whole, in order, by one stream of one rank, once per epoch, and the
streams end as evenly as whole scenes allow. ``shuffle=True`` permutes, from (seed, epoch), the
scenes of equal length before dealing and the order in which each stream walks its scenes: the
number of steps is the same in every epoch (of the same pieces, below). All ranks compute the same
schedule from (seed, epoch) alone: no communication.

The epoch lasts as many steps as the longest stream. A shorter stream is then padded, as
``DistributedSampler`` pads its index list, so that every rank steps in lockstep with full batches:
it walks the epoch's scenes again from the first (each from its frame 0, a scene start), cut where
the epoch ends. ``schedule()`` tells which entries are padding; evaluation scores only the samples a
rank ``owned()`` (walks for real), so every sample once over all ranks.

``piece_frames`` = K > 0 walks each scene in pieces of K frames (the last one shorter) instead of
whole: the pieces are dealt as scenes are, and the sampler yields ``(index, start)`` pairs, ``start``
True on a piece's first frame, which ``MapDataset`` turns into the sample's ``scene_start`` (the
memory resets there). Training streams then change scenes every K frames, so that consecutive batches
are less alike (StreamMapNet splits its training sequences likewise, ``seq_split_num``).

StreamMapNet's training sampler (``InfiniteGroupEachSampleInBatchSampler``) also gives each batch row
its own sequence; it has no epochs (an infinite stream of shuffled sub-sequences), where this one
keeps the project's epochs and exact resume (``set_epoch(epoch, start)`` skips the steps done).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import torch
from torch.utils.data import Sampler


def deal_scenes(lengths: Sequence[int], order: Sequence[int], streams: int) -> list[list[int]]:
    """List scheduling: scene ``order[k]`` (with ``lengths[order[k]]`` frames), in turn, to the stream with
    the fewest frames so far (ties: the lowest stream). Returns the scenes of each of ``streams`` streams."""
    totals = [0] * streams
    dealt: list[list[int]] = [[] for _ in range(streams)]
    for scene in order:
        s = min(range(streams), key=lambda i: (totals[i], i))
        dealt[s].append(scene)
        totals[s] += lengths[scene]
    return dealt


class StreamingBatchSampler(Sampler[list[int]]):
    """Batches of ``streams`` indices per rank, row b walking stream b's scenes frame by frame (module doc).

    ``runs``: per scene, its dataset indices in time order (``MapDataset.scenes.runs``); ``piece_frames``:
    walk them in pieces of this many frames (0: whole), yielding ``(index, start)`` pairs;
    ``single_epochs``: the first epochs in pieces of one frame (every sample a start: shuffled single
    frames, StreamMapNet's single-frame epochs before its sequences).
    """

    def __init__(self, runs: Sequence[Sequence[int]], streams: int, *, shuffle: bool = True, seed: int = 0,
                 rank: int = 0, world_size: int = 1, piece_frames: int = 0, single_epochs: int = 0):
        if streams < 1:
            raise ValueError(f"streams must be >= 1, got {streams}")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is not in [0, {world_size})")
        if not runs or any(len(r) == 0 for r in runs):
            raise ValueError("every scene needs at least one sample")
        if piece_frames < 0 or single_epochs < 0:
            raise ValueError(f"piece_frames ({piece_frames}) and single_epochs ({single_epochs}) must be >= 0")
        self.scene_runs = [list(r) for r in runs]
        self.piece_frames, self.single_epochs = piece_frames, single_epochs
        self.pieces = piece_frames > 0 or single_epochs > 0  # yields (index, start) pairs
        self._pieces_of: tuple[int, list[list[int]]] = (0, [])  # (piece frames, pieces) last cut
        self.streams, self.shuffle, self.seed = streams, shuffle, seed
        self.rank, self.world_size = rank, world_size
        self.epoch = 0
        self.start = 0  # steps of this epoch to skip (the trainer sets it on resume)

    @property
    def runs(self) -> list[list[int]]:
        """What the streams walk this epoch: the scenes, or their pieces."""
        k = 1 if self.epoch < self.single_epochs else self.piece_frames
        if k <= 0:
            return self.scene_runs
        if self._pieces_of[0] != k:
            self._pieces_of = (k, [r[i:i + k] for r in self.scene_runs for i in range(0, len(r), k)])
        return self._pieces_of[1]

    @property
    def batch_size(self) -> int:
        """Samples per batch of this rank: the streams."""
        return self.streams

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Select ``epoch``'s schedule and skip its first ``start`` samples of this rank (whole batches:
        ``start`` is a multiple of ``streams``, as ``distributed.ResumableSampler.set_epoch``'s)."""
        if start % self.streams:
            raise ValueError(f"start={start} is not a whole number of batches of {self.streams}")
        self.epoch, self.start = epoch, start // self.streams

    def _generator(self) -> torch.Generator:
        return torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)

    def deal(self) -> list[list[int]]:
        """The scenes of each stream of every rank this epoch, in walking order (stream ``r * streams + b``
        is row b of rank r)."""
        lengths = [len(r) for r in self.runs]
        g = self._generator() if self.shuffle else None
        order = torch.randperm(len(self.runs), generator=g).tolist() if g is not None else list(range(len(self.runs)))
        order.sort(key=lambda s: -lengths[s])  # stable: equal lengths keep the shuffled order
        dealt = deal_scenes(lengths, order, self.world_size * self.streams)
        if g is not None:
            dealt = [[scenes[i] for i in torch.randperm(len(scenes), generator=g).tolist()] for scenes in dealt]
        return dealt

    def schedule(self) -> list[list[tuple[int, int, bool]]]:
        """Every stream of every rank (stream ``r * streams + b`` is row b of rank r) for this epoch:
        a list of ``(scene, frame in scene, padding)`` per step, all of the same length (``steps``)."""
        dealt = self.deal()
        order = [s for scenes in dealt for s in scenes]
        lengths = [len(r) for r in self.runs]
        steps = self.steps
        out = []
        for scenes in dealt:
            walk = [(s, f, False) for s in scenes for f in range(lengths[s])]
            k = 0
            while len(walk) < steps:  # padding: the epoch's scenes again, from the first
                s = order[k % len(order)]
                walk += [(s, f, True) for f in range(lengths[s])][: steps - len(walk)]
                k += 1
            out.append(walk)
        return out

    def owned(self) -> set[int]:
        """The dataset indices this rank walks for real (not as padding) this epoch: every sample is owned
        by exactly one rank, which scores it in a streaming evaluation."""
        mine = self.schedule()[self.rank * self.streams:(self.rank + 1) * self.streams]
        return {self.runs[s][f] for walk in mine for s, f, pad in walk if not pad}

    def _rank_batches(self) -> list[list]:
        mine = self.schedule()[self.rank * self.streams:(self.rank + 1) * self.streams]
        if self.pieces:
            return [[(self.runs[s][f], f == 0) for s, f, _ in step] for step in zip(*mine)]
        return [[self.runs[s][f] for s, f, _ in step] for step in zip(*mine)]

    @property
    def steps(self) -> int:
        """Batches in this epoch: the same on every rank, and in every epoch of the same pieces."""
        lengths = sorted((len(r) for r in self.runs), reverse=True)
        dealt = deal_scenes(lengths, range(len(lengths)), self.world_size * self.streams)
        return max(sum(lengths[s] for s in scenes) for scenes in dealt)

    def steps_of_epoch(self, epoch: int) -> int:
        """``steps`` of another epoch: the single-frame epochs (``single_epochs``) and the epochs of
        pieces walk other runs, so their lengths differ (the longest stream of pieces is at least as long)."""
        kept = self.epoch
        self.epoch = epoch
        try:
            return self.steps
        finally:
            self.epoch = kept

    @property
    def num_samples(self) -> int:
        """Samples this rank loads in one epoch, padding included (``steps * streams``)."""
        return self.steps * self.streams

    def __iter__(self) -> Iterator[list[int]]:
        return iter(self._rank_batches()[self.start:])

    def __len__(self) -> int:
        return self.steps - self.start
