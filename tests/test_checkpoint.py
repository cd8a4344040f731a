"""Checkpoints are atomic and load safely; the resumable sampler continues an epoch exactly."""

import pytest
import torch

from instagram_hdmap import files
from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from instagram_hdmap.distributed import ResumableSampler


def _state(value: float) -> dict:
    return {"model": {"w": torch.full((4,), value)}, "epoch": 1, "step": 3, "config": {"name": "x"}}


def test_save_load_round_trip_weights_only(tmp_path):
    p = save_checkpoint(_state(2.0), tmp_path / "last.pt")
    state = load_checkpoint(p)
    assert torch.equal(state["model"]["w"], torch.full((4,), 2.0)) and state["step"] == 3


def test_interrupted_save_keeps_the_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    save_checkpoint(_state(1.0), path)

    def killed(src, dst):  # the process dies between the write and the rename
        raise KeyboardInterrupt

    monkeypatch.setattr(files, "_replace", killed)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(_state(9.0), path)
    assert torch.equal(load_checkpoint(path)["model"]["w"], torch.full((4,), 1.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]  # no temp file left behind


def test_truncated_and_missing_checkpoints_are_clear_errors(tmp_path):
    path = save_checkpoint(_state(1.0), tmp_path / "last.pt")
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"cut\.pt is truncated or corrupt"):
        load_checkpoint(tmp_path / "cut.pt")
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")


def test_rng_state_round_trip_through_a_checkpoint(tmp_path):
    import random

    import numpy as np

    torch.manual_seed(5)
    np.random.seed(5)  # noqa: NPY002
    random.seed(5)
    save_checkpoint({"model": {}, "rng": rng_state()}, tmp_path / "r.pt")
    expected = (torch.rand(3), np.random.rand(3), random.random())  # noqa: NPY002
    set_rng_state(load_checkpoint(tmp_path / "r.pt")["rng"])
    got = (torch.rand(3), np.random.rand(3), random.random())  # noqa: NPY002
    assert torch.equal(expected[0], got[0]) and np.array_equal(expected[1], got[1]) and expected[2] == got[2]


def test_sampler_is_a_function_of_seed_and_epoch_and_resumes_midway():
    s = ResumableSampler(10, seed=3)
    s.set_epoch(2)
    full = list(s)
    assert sorted(full) == list(range(10))
    s.set_epoch(2, start=4)
    assert list(s) == full[4:] and len(s) == 6
    s.set_epoch(3)
    assert list(s) != full


def test_sampler_resumes_exactly_under_another_number_of_ranks():
    # k steps of a batch of 4 over 2 ranks, then the rest of the epoch over 1 or 4 ranks: every sample of
    # the epoch's order once, in the order of one process (the samples of step k are the same set)
    n, batch, k = 23, 4, 3
    one = ResumableSampler(n, seed=7, rank=0, world_size=1)
    one.set_epoch(5)
    order = list(one)
    seen = []
    for r in range(2):
        s = ResumableSampler(n, seed=7, rank=r, world_size=2)
        s.set_epoch(5)
        seen += list(s)[: k * batch // 2]
    assert sorted(seen) == sorted(order[: k * batch])
    for world in (1, 4):
        rest = []
        for r in range(world):
            s = ResumableSampler(n, seed=7, rank=r, world_size=world)
            s.set_epoch(5, start=k * batch)
            assert len(s) == len(list(s))
            rest += list(s)
        pad = order[: (-n) % world]  # as DistributedSampler: the order wrapped round to a multiple of the ranks
        assert sorted(rest) == sorted(order[k * batch:] + pad)
        assert sorted(seen + order[k * batch:]) == list(range(n))
    s = ResumableSampler(n, seed=7, rank=1, world_size=2)
    s.set_epoch(5, start=k * batch)  # the same world: this rank's share from step k, as before
    full = ResumableSampler(n, seed=7, rank=1, world_size=2)
    full.set_epoch(5)
    assert list(s) == list(full)[k * batch // 2:]


def test_sampler_splits_over_ranks_like_distributed_sampler():
    shards = [list(ResumableSampler(7, seed=0, rank=r, world_size=2)) for r in range(2)]
    assert len(shards[0]) == len(shards[1]) == 4
    assert set(shards[0]) | set(shards[1]) == set(range(7))


def test_a_signal_during_the_save_lands_after_it(tmp_path, monkeypatch):
    """Ctrl-C (or a handler's exception) in the middle of torch.save left its zip writer half done, and the
    writer's cleanup raised "unexpected pos" in place of the KeyboardInterrupt; the save is now whole and the
    signal reaches its handler after it."""
    import signal

    real_save = torch.save
    calls = []

    def save_with_a_signal(obj, f, *args, **kwargs):
        # Ctrl-C while the checkpoint is being written (raise_signal: to this thread, handled before it returns; a
        # process-directed os.kill may be taken by another thread of the process, once lost in a loaded full suite)
        signal.raise_signal(signal.SIGINT)
        calls.append("saving")
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save_with_a_signal)
    # Python's Ctrl-C handler, whatever the suite inherited: started as a background job (`pytest &` in a script),
    # Python starts with SIGINT ignored, which signals_deferred rightly leaves alone, and the signal never came
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        state = {"model": {"w": torch.arange(1000.0)}, "step": 7}
        with pytest.raises(KeyboardInterrupt):
            save_checkpoint(state, tmp_path / "last.pt")
        assert calls == ["saving"]
        loaded = load_checkpoint(tmp_path / "last.pt")
        assert loaded["step"] == 7 and torch.equal(loaded["model"]["w"], state["model"]["w"])
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler given back
    finally:
        signal.signal(signal.SIGINT, previous)
