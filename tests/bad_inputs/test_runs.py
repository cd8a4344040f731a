"""Runs as processes: a training killed, interrupted or signalled and then resumed; resumes with other settings;
locks on a run folder; torchrun; data-loader workers; out of memory; the environment's thread settings.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from bad_inputs.support import (
    REPO,
    dead_pid,
    forbid,
    row,
    table,
    toy_run,
)
from instagram_hdmap.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from instagram_hdmap.config import UserError, config_to_dict


@row("best.pt is only replaced by a better validated model, across resumes")
def row_best_survives_a_resume(env):
    run = env.tmp / "run"
    # 4 samples, batch 2: 2 steps per epoch; max_steps=1 stops mid-epoch 0, then validates (0.6)
    toy_run(env, [0.6], "train.epochs=3", "train.max_steps=1")
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6
    assert load_checkpoint(run / "last.pt")["best"]["score"] == 0.6  # last.pt saved after that validation
    toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", resume=str(run / "last.pt"))
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6
    # a last.pt older than best.pt (killed between the two saves) does not lose best.pt either
    state = load_checkpoint(run / "last.pt")
    state["best"] = {"score": float("-inf")}
    state["epoch"], state["step"], state["step_in_epoch"] = 2, 4, 0
    state["clock"] = {**state["clock"], "progress": 4 / 6}  # 3 epochs of 2 steps
    save_checkpoint(state, run / "last.pt")
    toy_run(env, [0.5], "train.epochs=3", resume=str(run / "last.pt"))
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.6


@row("--force starts over: the old run's log.jsonl lines and TensorBoard events go")
def row_force_clears_the_old_log(env):
    run = env.tmp / "run"
    toy_run(env, [0.2, 0.3], "train.epochs=2")
    old_events = sorted((run / "tb").rglob("events.*"))
    assert len(old_events) == 1 and len((run / "log.jsonl").read_text().splitlines()) == 2
    toy_run(env, [0.1], "train.epochs=1", force=True)
    lines = (run / "log.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["val"]["metrics"]["mAP"] == 0.1
    events = sorted((run / "tb").rglob("events.*"))
    assert len(events) == 1 and events != old_events
    assert load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.1  # not the old run's 0.3


@row("the temporary file of an export-onnx killed mid-write (kill -9) is removed by the next export to that path")
def row_killed_export_leaves_no_temporary(env):
    pytest.importorskip("onnxruntime", reason="the [deploy] extra is not installed")
    from instagram_hdmap.deploy import export_onnx
    from instagram_hdmap.models import build_model

    out = env.tmp / "model.onnx"
    stale = out.with_name(f".model.onnx.tmp-{dead_pid()}")
    stale.write_bytes(b"half an ONNX file")
    cfg = env.cfg("model.gnn.sinkhorn_iters=3")
    torch.manual_seed(0)
    export_onnx(build_model(cfg).eval(), cfg, out)
    assert out.is_file() and not stale.exists()
    assert [p.name for p in env.tmp.iterdir() if p.name.startswith(".")] == []


@row("--resume from a weights-only checkpoint is named (was a KeyError)")
def row_resume_from_weights_only(env):
    path = env.tmp / "weights.pt"
    save_checkpoint({"model": load_checkpoint(env.ckpt)["model"]}, path)
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"weights\.pt cannot be resumed: it holds no optimizer, epoch, step, step_in_epoch, rng, config",
              "train", env.yaml, f"train.out_dir={env.tmp / 'r'}", "--resume", path)


@row("train --force --resume: refused, the checkpoint to resume is not deleted")
def row_force_and_resume(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    before = (run / "last.pt").read_bytes()
    env.error(r"--force.*--resume", "train", env.yaml, f"train.out_dir={run}", "--force", "--resume", run / "last.pt")
    assert (run / "last.pt").read_bytes() == before


@row("--resume of a finished run with more train.epochs is named, not a silent exit 0")
def row_resume_a_finished_schedule(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=1")
    with pytest.raises(UserError, match=r"last\.pt .*completed its schedule.*train\.epochs"):
        toy_run(env, [], "train.epochs=3", resume=str(run / "last.pt"))


@row("a run killed before its first checkpoint can be run again")
def row_rerun_before_first_checkpoint(env):
    run = env.tmp / "run"
    (run / "tb").mkdir(parents=True)
    (run / "config.yaml").write_text("name: killed\n")
    (run / "log.jsonl").write_text("")
    (run / "tb" / "events.out.tfevents.1.host.1.0").write_bytes(b"old")
    env.error(r"last\.pt.*(no checkpoint|before its first checkpoint).*without --resume", "train", env.yaml,
              f"train.out_dir={run}", "--resume", run / "last.pt")
    toy_run(env, [0.2], "train.epochs=1")
    assert (run / "last.pt").is_file() and not (run / "tb" / "events.out.tfevents.1.host.1.0").exists()


@row("partial checkpoints of killed saves are removed by the next run in that folder")
def row_stale_checkpoint_temporaries(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    dead, alive = dead_pid(), os.getppid()
    for name in (f".last.pt.tmp-{dead}", f".best.pt.tmp-{dead}", f".last.pt.tmp-{alive}"):
        (run / name).write_bytes(b"partial")
    toy_run(env, [0.1, 0.1], "train.epochs=2", resume=str(run / "last.pt"))
    left = sorted(p.name for p in run.iterdir() if p.name.startswith("."))
    assert left == [f".last.pt.tmp-{alive}"]  # another live process's file is not ours to remove


@row("out of memory (torch's CPU allocator, CUDA, numpy) is one line naming the sizes to lower")
def row_out_of_memory(env):
    for error in (RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                               "memory: you tried to allocate 4096000064 bytes. Error code 12"),
                  torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB.\nSee documentation"),
                  MemoryError("Unable to allocate 49.1 TiB for an array with shape (3, 3000000, 6000000)")):
        def boom(*args, error=error, **kwargs):
            raise error

        env.monkeypatch.setattr("instagram_hdmap.cli.summarize_parameters", boom)
        env.error(r"out of memory .*train\.batch_size", "model-summary", env.yaml)


@row("a second training in the folder of a running one is refused (it deleted the first one's log)")
def row_second_training_in_a_running_folder(env):
    from instagram_hdmap.files import LOCK_FILE

    run = env.tmp / "run"
    (run / "tb").mkdir(parents=True)
    (run / "log.jsonl").write_text('{"step": 1}\n')  # the first run, before its first checkpoint
    holder = subprocess.Popen(  # the first run's lock, as lock_out_dir takes it
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         f"f = open({str(run / LOCK_FILE)!r}, 'a+'); fcntl.flock(f, fcntl.LOCK_EX); f.write(str(os.getpid()))\n"
         "f.flush(); print('locked', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
        env.error(rf"another training is running in .*run \(process {holder.pid}\)", "train", env.yaml,
                  f"train.out_dir={run}")
        env.error(r"another training is running", "train", env.yaml, f"train.out_dir={run}", "--force")
        assert (run / "log.jsonl").read_text() == '{"step": 1}\n' and (run / "tb").is_dir()
    finally:
        holder.kill()
        holder.wait()


@row("a run whose last.pt save failed after best.pt (a full disk) points at best.pt, which resumes")
def row_resume_from_best_after_a_failed_save(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    (run / "last.pt").unlink()  # best.pt is saved first; the disk filled up before last.pt
    env.error(rf"already holds a run; pass --resume {re.escape(str(run / 'best.pt'))}", "train", env.yaml,
              f"train.out_dir={run}")
    env.error(rf"stopped before it saved it .*--resume {re.escape(str(run / 'best.pt'))}", "train", env.yaml,
              f"train.out_dir={run}", "--resume", run / "last.pt")
    summary = toy_run(env, [0.3, 0.1], "train.epochs=2", resume=str(run / "best.pt"))
    assert summary["step"] == 4 and load_checkpoint(run / "best.pt")["metrics"]["mAP"] == 0.3


@row("--resume of one folder's checkpoint into another folder holding a run is refused (it overwrote that "
          "run's last.pt and log)")
def row_resume_into_another_run(env):
    other, run = env.tmp / "other", env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    shutil.move(run, other)
    toy_run(env, [0.5], "train.epochs=1")
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"--resume .*other.*last\.pt continues the run of .*other, but train\.out_dir=.*run holds a run of its "
              "own", "train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "--resume", other / "last.pt")
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


@row("--resume with another train.batch_size is refused (it skipped the rest of the epoch, moved the schedule)")
def row_resume_with_another_batch_size(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")  # stopped mid-epoch
    with pytest.raises(CheckpointError, match=r"train\.batch_size: checkpoint 2 vs now 4"):
        toy_run(env, [], "train.epochs=2", "train.batch_size=4", resume=str(run / "last.pt"))


@row("--resume of a temporal run with another train.stream_frames is refused (it walked other pieces from "
          "the saved position and moved the schedule)")
def row_resume_temporal_with_other_stream_frames(env):
    run = env.tmp / "run"
    common = [env.yaml, "model.temporal.memory=bev", "train.epochs=2", f"train.out_dir={run}"]
    rc, _, err = env.cli("train", *common, "train.max_steps=1")  # stopped mid-epoch (3 steps an epoch)
    assert rc == 0, err[-3000:]
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.stream_frames: checkpoint 0 vs now 2", "train", *common, "train.stream_frames=2",
              "--resume", run / "last.pt")
    env.error(r"train\.stream_warmup: checkpoint 0\.0 vs now 0\.5", "train", *common, "train.stream_warmup=0.5",
              "--resume", run / "last.pt")


@row("--resume past train.max_steps says that nothing is left to train (printed 'done: epoch None, step None')")
def row_resume_past_max_steps(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = toy_run(env, [], "train.epochs=2", "train.max_steps=1", resume=str(run / "last.pt"))
    assert (summary["epoch"], summary["step"]) == (0, 1)
    assert "train.max_steps=1 is reached already" in env.capsys.readouterr().out


@row("RANK and WORLD_SIZE left in the environment without MASTER_ADDR (a shell, a job script; not torchrun) are "
          "one line (was torch's raw ValueError)")
def row_rank_without_torchrun(env):
    env.monkeypatch.setenv("RANK", "0")
    env.monkeypatch.setenv("WORLD_SIZE", "2")
    env.monkeypatch.delenv("MASTER_ADDR", raising=False)
    env.monkeypatch.delenv("MASTER_PORT", raising=False)
    env.error(r"RANK and WORLD_SIZE are set .* but MASTER_ADDR and MASTER_PORT are not: launch with torchrun, or "
              r"unset", "train", env.yaml, f"train.out_dir={env.tmp / 'r'}")


@row("--resume with another train.seed is refused (the saved position counted batches of the old seed's order: "
          "the rest of the epoch saw some samples twice and others never, exit 0)")
def row_resume_with_another_seed(env):
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    with pytest.raises(UserError, match=r"incompatible config \(train\.seed: checkpoint 0 vs now 7\)"):
        toy_run(env, [], "train.epochs=2", "train.seed=7", resume=str(env.tmp / "run" / "last.pt"))


@row("a training stopped by SIGTERM (a scheduler's preemption, docker stop, timeout) lost every step since its "
          "last save; it now saves last.pt as Ctrl-C does, and puts the old handler back")
def row_sigterm_saves_last_pt(env):
    import signal

    from instagram_hdmap.train import TrainingRun

    received = []

    def ours(signum, frame):  # the handler before the run (unfixed, the run kept training through the signal)
        received.append(signum)

    previous = signal.signal(signal.SIGTERM, ours)
    try:
        on_step = TrainingRun.on_step

        def step_then_term(self, info):
            on_step(self, info)
            if info.step == 2:
                os.kill(os.getpid(), signal.SIGTERM)

        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_term)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                               "train.checkpoint_every=0")
        assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
        state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
        assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
        assert not received and signal.getsignal(signal.SIGTERM) is ours  # the run's handler, then ours again
    finally:
        signal.signal(signal.SIGTERM, previous)
    # a scheduler's SIGTERM to the whole process group kills the data-loader worker too: still saved, one line
    run = env.tmp / "group"
    p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", "train", str(env.yaml), f"train.out_dir={run}",
                          "train.epochs=50", "train.batch_size=1", "data.num_workers=1", "train.checkpoint_every=0",
                          "train.val_every=100"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    try:
        for _ in range(600):
            if (run / "last.pt").exists() or p.poll() is not None:
                break
            time.sleep(0.2)
        time.sleep(1.0)  # part-way through the next epoch
        os.killpg(p.pid, signal.SIGTERM)
        out, err = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130 and "Traceback" not in err and "interrupted: saved" in out, (p.returncode, err[-2000:])


@row("a second SIGTERM during the save that the first one started (scancel or docker stop twice, a supervisor "
            "that repeats it) aborted that save: the older last.pt stayed, the steps since were lost")
def row_second_sigterm_during_the_save(env):
    import signal

    from instagram_hdmap.train import TrainingRun

    on_step, save = TrainingRun.on_step, TrainingRun.save

    def step_then_term(self, info):
        on_step(self, info)
        if info.step == 2:
            os.kill(os.getpid(), signal.SIGTERM)

    def save_under_a_second_term(self, name, metrics=None, gather=True):
        if not gather:  # the interrupt's save: the second signal arrives as it starts
            os.kill(os.getpid(), signal.SIGTERM)
        save(self, name, metrics, gather)

    previous = signal.getsignal(signal.SIGTERM)
    env.monkeypatch.setattr(TrainingRun, "on_step", step_then_term)
    env.monkeypatch.setattr(TrainingRun, "save", save_under_a_second_term)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                           "train.checkpoint_every=0")
    assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
    state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
    assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
    assert signal.getsignal(signal.SIGTERM) is previous  # the handler before the run, again


@row("a training whose terminal closed (SIGHUP: an ssh session dropped, without nohup or tmux) died without "
            "saving, losing every step since its last save; it now saves last.pt as for SIGTERM, and a SIGHUP that "
            "nohup ignores stays ignored")
def row_sighup_saves_last_pt(env):
    import signal

    if not hasattr(signal, "SIGHUP"):
        pytest.skip("no SIGHUP on this platform")
    from instagram_hdmap.train import TrainingRun

    on_step = TrainingRun.on_step

    def step_then_hup(self, info):
        on_step(self, info)
        if info.step == 2:
            os.kill(os.getpid(), signal.SIGHUP)

    previous = signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a terminal's process: the default (death)
    try:
        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_hup)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=2",
                               "train.checkpoint_every=0")
        assert rc == 130 and "interrupted: saved" in out + err, (rc, err[-2000:])
        state = torch.load(env.tmp / "run" / "last.pt", weights_only=True)
        assert (state["epoch"], state["step"]) == (0, 2), (state["epoch"], state["step"])
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # under nohup: the signal stays ignored, the run goes on
        env.monkeypatch.setattr(TrainingRun, "on_step", step_then_hup)
        rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'nohup'}", "train.epochs=1",
                               "train.checkpoint_every=0")
        assert rc == 0 and "interrupted" not in out + err, (rc, err[-2000:])
    finally:
        signal.signal(signal.SIGHUP, previous)


@row("--resume OUT/best.pt while a later last.pt sits in the folder: the run goes on from best.pt (a valid "
            "choice) and its next save replaced last.pt without a word; now a note names both steps and the "
            "--resume that continues the later one")
def row_resume_best_with_a_later_last_pt(env):
    run = env.tmp / "run"
    toy_run(env, [0.6, 0.3], "train.epochs=2")  # best.pt at step 2 (0.6), last.pt at step 4
    assert load_checkpoint(run / "best.pt")["step"] == 2 and load_checkpoint(run / "last.pt")["step"] == 4
    env.capsys.readouterr()
    toy_run(env, [0.2, 0.1], "train.epochs=3", resume=str(run / "best.pt"))
    out = env.capsys.readouterr().out
    assert re.search(rf"note: {re.escape(str(run / 'last.pt'))} is at step 4, later than .*best\.pt; this run goes "
                     rf"on from step 2 .*--resume {re.escape(str(run / 'last.pt'))}", out), out
    env.capsys.readouterr()
    toy_run(env, [], "train.epochs=3", "train.max_steps=6", resume=str(run / "last.pt"))  # its own last.pt: no note
    assert "note:" not in env.capsys.readouterr().out


@row("train --resume ANOTHER_RUN/last.pt into a new train.out_dir, of a run whose schedule was complete, "
            "printed 'nothing left to train' and ended on 'outputs in NEW_DIR' with no checkpoint there; the note "
            "says the outputs stay in the checkpoint's run and how to train on from it (train.init_from)")
def row_resume_a_finished_run_into_another_folder(env):
    first = env.tmp / "run"
    toy_run(env, [0.5], "train.epochs=1")
    env.capsys.readouterr()
    other = env.tmp / "other"
    toy_run(env, [], "train.epochs=1", f"train.out_dir={other}", resume=str(first / "last.pt"))
    out, err = env.capsys.readouterr()
    assert re.search(rf"completed its schedule: nothing left to train; its run's outputs stay in "
                     rf"{re.escape(str(first))}, train\.out_dir={re.escape(str(other))} gets no checkpoint "
                     r".*train\.init_from=", out + err)
    assert not (other / "last.pt").exists()


def _torchrun_cli(*argv) -> subprocess.CompletedProcess:
    """``torchrun --nproc_per_node 2 -m instagram_hdmap.cli ARGV`` (gloo on the CPU) on a free port."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                           str(port), "-m", "instagram_hdmap.cli", *map(str, argv)],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})


@row("evaluate under torchrun with model.temporal.persist_frames: the note (and metrics.json) counted the "
            "elements kept on rank 0 only (a temporal model's scenes are spread over the ranks: 8 of 16, exit 0); "
            "the count is summed over the ranks")
def row_persisted_count_under_torchrun(env):
    from instagram_hdmap.models import build_model

    torch.manual_seed(0)
    cfg = env.cfg("model.temporal.memory=bev")
    ckpt = save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)},
                           env.tmp / "temporal.pt")
    args = ["evaluate", str(env.yaml), "--checkpoint", str(ckpt), "model.temporal.persist_frames=2",
            "model.gnn.conf_threshold=0.0", "model.gnn.match_threshold=0.01", "eval.batch_size=1",
            "data.val_split=train"]

    def kept(metrics: Path) -> int:
        notes = json.loads(metrics.read_text())["meta"]["config_notes"]
        return int(next(re.search(r"persist_frames=2: (\d+) map elements", n).group(1) for n in notes
                        if "persist_frames=2:" in n))

    rc, out, err = env.cli(*args, "--out", env.tmp / "one")
    assert rc == 0, err
    p = _torchrun_cli(*args, "--out", env.tmp / "two")
    assert p.returncode == 0, p.stderr[-3000:]
    assert kept(env.tmp / "one" / "metrics.json") > 0
    assert kept(env.tmp / "two" / "metrics.json") == kept(env.tmp / "one" / "metrics.json")


@row("torchrun --nproc_per_node 2 train with train.batch_size=3 (or 1): the README says it is the batch over "
            "all processes, but each rank took 3 // 2 = 1 (at least 1), so it trained with a total of 2, exit 0, no "
            "word; a batch the ranks do not divide is one 'train: error:' line per rank, exit 2, before the run folder")
def row_train_batch_not_divided_by_ranks(env):
    out = env.tmp / "run"
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={out}", "train.max_steps=1", "train.batch_size=3")
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("instagram-hdmap train: error:")]
    assert p.returncode != 0 and len(lines) == 2, p.stderr[-3000:]  # one per rank
    assert "'train.batch_size'=3 is the batch over all 2 processes of torchrun" in lines[0]
    assert not out.exists()


@row("torchrun --nproc_per_node 2 train: every rank printed 'done: epoch E, step S; outputs in OUT' (the run's "
            "other lines are rank 0's); it is printed once (and train.batch_size=2 over 2 ranks trains)")
def row_train_done_printed_once_under_torchrun(env):
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={env.tmp / 'r'}", "train.max_steps=1", "train.batch_size=2")
    assert p.returncode == 0, p.stderr[-3000:]
    assert [ln for ln in p.stdout.splitlines() if ln.startswith("done:")] == [
        f"done: epoch 0, step 1; outputs in {env.tmp / 'r'}"], p.stdout


@row("Ctrl-C (or a SIGTERM) during a training's validation: last.pt was saved with the epoch counted as "
            "done, so the resume skipped that validation; after the final epoch it said 'completed its schedule: "
            "nothing left to train', exit 0, with the run never validated and no best.pt. last.pt records the cut "
            "validation and the resume runs it first")
def row_interrupted_validation_runs_on_resume(env):
    from instagram_hdmap import train as train_module

    real, calls = train_module.evaluate, []

    def ctrl_c_in_the_first(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(train_module, "evaluate", ctrl_c_in_the_first)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}")
    assert rc == 130 and (run / "last.pt").is_file() and not (run / "best.pt").exists(), (rc, err[-2000:])
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    assert len(calls) == 2, "the interrupted validation was not run again"
    assert re.search(r"validation after step \d+ was interrupted; running it first", out), out
    assert (run / "best.pt").is_file() and not load_checkpoint(run / "last.pt")["validation_pending"]
    assert len((run / "log.jsonl").read_text().splitlines()) == 1  # the epoch's line, written once


@row("train --resume after the training split changed (a scene removed from data.splits_file, another "
            "data.dataroot): the schedule was recounted over the new split, so a run of 6 samples resumed on 3 said "
            "'done' after no step, exit 0, and the saved position skipped or repeated samples; the checkpoint keeps "
            "the split's sample count and token hash, and another split is named (the same data moved elsewhere "
            "resumes)")
def row_resume_with_another_training_split(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    splits = json.loads((env.world / "splits.json").read_text())
    fewer = env.tmp / "fewer.json"
    fewer.write_text(json.dumps({**splits, "train": splits["train"][:1]}))
    env.error(r"last\.pt was trained on another training split \(\d+ samples then, \d+ now.*train\.init_from=",
              "train", env.yaml, f"train.out_dir={run}", "train.epochs=2", f"data.splits_file={fewer}",
              "--resume", run / "last.pt")
    moved = env.tmp / "moved"
    moved.symlink_to(env.world)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                           f"data.dataroot={moved}", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]


@row("evaluate --out OLD killed between its two writes (submission.json, then metrics.json): OLD held the new "
            "checkpoint's submission beside the metrics of the evaluation before, a pair that looked whole; both are "
            "written to temporaries and renamed together, so the earlier pair stays as it was")
def row_evaluate_killed_between_its_two_files(env):
    from instagram_hdmap import evaluate_split

    out = env.tmp / "e"
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
    assert rc == 0 and (out / "metrics.json").is_file(), err[-2000:]
    before = {name: (out / name).read_bytes() for name in ("submission.json", "metrics.json")}

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    env.monkeypatch.setattr(evaluate_split, "write_json", killed)
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out, "data.val_split=train")
    assert rc == 130, err[-2000:]
    assert {name: (out / name).read_bytes() for name in before} == before  # the earlier pair, whole
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "submission.json"]  # no temporaries


@row("train --resume DIR/last.pt where DIR holds no run at all (a wrong folder): 'the run in DIR stopped before "
            "its first checkpoint ... run the same command without --resume', a run that never was; it says DIR "
            "holds no training run")
def row_resume_from_a_folder_without_a_run(env):
    empty = env.tmp / "elsewhere"
    empty.mkdir()
    env.error(r"checkpoint not found: .*elsewhere/last\.pt; .*elsewhere holds no training run", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}", "--resume", empty / "last.pt")


@row("a low limit on open files (ulimit -n 40) with data.num_workers=1: the workers pass each tensor through a "
            "file descriptor, which ran out; the run hung for good, a thread printing 'OSError: [Errno 24] Too many "
            "open files' tracebacks without end. The soft limit is raised towards the hard one, and below 4096 the "
            "tensors go through named shared memory: the run works")
def row_open_file_limit_with_data_workers(env):
    import resource

    def low_limit():
        resource.setrlimit(resource.RLIMIT_NOFILE, (40, 40))

    run = env.tmp / "run"
    try:
        p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "train", str(env.yaml), f"train.out_dir={run}",
                            "train.max_steps=1", "data.num_workers=1"], capture_output=True, text=True, timeout=150,
                           preexec_fn=low_limit, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path),
                                                      "OMP_NUM_THREADS": "1"})
    except subprocess.TimeoutExpired as e:
        raise AssertionError("the training hung (too many open files)") from e
    assert p.returncode == 0 and "Too many open files" not in p.stderr, p.stderr[-3000:]
    assert (run / "last.pt").is_file()


@row("a training killed after its last checkpoint (kill -9, a power cut) and resumed: the steps it had trained "
            "since were logged to TensorBoard twice, the killed run's and the resumed run's (a second curve over "
            "them, other values where the resume changed train.lr); the resumed run purges the killed one's events "
            "after its checkpoint")
def row_tensorboard_after_a_kill_and_resume(env):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from instagram_hdmap.train import TrainingRun

    class Killed(BaseException):  # not an exception the run handles: no save at the kill, as with kill -9
        pass

    on_step = TrainingRun.on_step

    def killed_after_step_3(self, info):
        on_step(self, info)
        if info.step == 3:
            raise Killed

    env.monkeypatch.setattr(TrainingRun, "on_step", killed_after_step_3)
    run = env.tmp / "run"
    args = ["train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.checkpoint_every=2",
            "train.val_every=100"]
    with pytest.raises(Killed):
        env.cli(*args)
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2
    env.monkeypatch.setattr(TrainingRun, "on_step", on_step)
    rc, _, err = env.cli(*args, "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    steps = [e.step for e in events.Scalars("train/lr")]
    assert steps == sorted(set(steps)) and 3 in steps, steps


@row("predict --out DIR over an earlier predict of another sample, killed part-way (Ctrl-C, kill -9, a full "
            "disk): DIR mixed the new sample's first pictures with the old one's last picture and prediction.json, a "
            "set that looked whole; the pictures and prediction.json are written to temporaries and renamed together")
def row_predict_killed_part_way_over_an_earlier_set(env):
    from instagram_hdmap import predict as predict_module

    out = env.tmp / "p"
    rc, _, err = env.cli("predict", env.yaml, "--checkpoint", env.ckpt, "--index", "0", "--out", out)
    assert rc == 0, err[-2000:]
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = predict_module.save_figure, []

    def killed_at_the_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(predict_module, "save_figure", killed_at_the_second)
    rc, _, err = env.cli("predict", env.yaml, "--checkpoint", env.ckpt, "--index", "2", "--out", out)
    assert rc == 130, err[-2000:]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@row("show-gt --out DIR over an earlier show-gt of another sample, killed part-way: DIR mixed both samples' "
            "pictures (only bev_polylines.png names its sample); the pictures are renamed together")
def row_show_gt_killed_part_way_over_an_earlier_set(env):
    from instagram_hdmap import visualize

    out = env.tmp / "g"
    rc, _, err = env.cli("show-gt", env.yaml, "--index", "0", "--out", out)
    assert rc == 0, err[-2000:]
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = visualize.save_figure, []

    def killed_at_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    env.monkeypatch.setattr(visualize, "save_figure", killed_at_the_third)
    rc, _, err = env.cli("show-gt", env.yaml, "--index", "1", "--out", out)
    assert rc == 130, err[-2000:]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@row("a data-loader worker killed during a training (the out-of-memory killer's choice, a kill -9): torch's "
            "'DataLoader worker (pid N) is killed by signal: Killed.' ended the run in two chained tracebacks, the "
            "steps since the last checkpoint lost; last.pt is saved at the last completed step and one line says so "
            "(evaluate: one line, nothing written)")
def row_data_worker_killed(env):
    from instagram_hdmap import evaluate_split
    from instagram_hdmap.train import TrainingRun

    on_step = TrainingRun.on_step

    def worker_killed_after_step_2(self, info):
        on_step(self, info)
        if info.step == 2:
            raise RuntimeError("DataLoader worker (pid 4242) is killed by signal: Killed. ")

    env.monkeypatch.setattr(TrainingRun, "on_step", worker_killed_after_step_2)
    run = env.tmp / "run"
    env.error(r"DataLoader worker \(pid 4242\) is killed by signal: Killed .*saved .*last\.pt at step 2: resume with "
              r"--resume", "train", env.yaml, f"train.out_dir={run}", "train.epochs=2")
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2

    def worker_died(*args, **kwargs):
        raise RuntimeError("DataLoader worker (pid(s) 4243) exited unexpectedly")

    env.monkeypatch.setattr(evaluate_split, "evaluate", worker_died)
    env.error(r"evaluate: error: DataLoader worker .*exited unexpectedly .*nothing was written", "evaluate", env.yaml,
              "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("train --resume into a run folder whose tb is a file or whose log.jsonl is a folder: a raw "
            "FileExistsError (TensorBoard's makedirs) or IsADirectoryError (open) traceback once the model and the "
            "loaders were built; one line names the entry before the work")
def row_run_files_of_the_wrong_kind(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    shutil.rmtree(run / "tb")
    (run / "tb").write_text("")
    env.error(r"tb is a file, where the run keeps its TensorBoard events in a folder", "train", env.yaml,
              f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")
    (run / "tb").unlink()
    (run / "log.jsonl").unlink()
    (run / "log.jsonl").mkdir()
    env.error(r"log\.jsonl is a folder, where the run keeps its log in a file", "train", env.yaml,
              f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")


@row("train --resume latest.pt, a symbolic link to OUT/last.pt (kept beside the runs), with train.out_dir=OUT: "
            "refused as 'continues the run of ., but OUT holds a run of its own ... set train.out_dir=.' (the link's "
            "folder, where following the advice would split the run); the checkpoint's own folder is its run")
def row_resume_through_a_symbolic_link(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    (env.tmp / "latest.pt").symlink_to(run / "last.pt")
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                         "--resume", env.tmp / "latest.pt")
    assert rc == 0, err[-2000:]
    assert torch.load(run / "last.pt", weights_only=True)["step"] == 2


@row("train --resume with another eval.protocol (or data.val_split, eval.thresholds): the run compared its "
            "raster mAP with the vector mAP best.pt was kept for, to decide whether to replace best.pt, with no word; "
            "a note names the difference")
def row_resume_with_another_validation(env):
    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=1")
    assert rc == 0 and (run / "best.pt").is_file(), err[-2000:]
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.max_steps=2",
                           "eval.protocol=raster", "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    assert re.search(r"note: the best score so far .* was measured with another validation \(eval\.protocol: "
                     r"checkpoint 'vector' vs now 'raster'\)", out), out


@row("a run saved part-way through an epoch by 2 torchrun processes and resumed by 1: the shuffled sampler "
            "skipped samples of this rank's share (computed for the old number of ranks), so part of the epoch was "
            "walked twice or not at all, no word; it goes on from the same sample of the epoch's order, and says so")
def row_resume_under_another_number_of_processes(env):
    out = env.tmp / "r"
    p = _torchrun_cli("train", env.yaml, f"train.out_dir={out}", "train.max_steps=1", "train.batch_size=2")
    assert p.returncode == 0, p.stderr[-3000:]
    rc, stdout, err = env.cli("train", env.yaml, f"train.out_dir={out}", "--resume", out / "last.pt",
                              "train.max_steps=2", "train.batch_size=2")
    assert rc == 0, err
    assert (f"note: {out / 'last.pt'} was saved by 2 process(es) at step 1 of epoch 0, resumed by 1: the epoch goes "
            "on from the same sample") in stdout
    assert load_checkpoint(out / "last.pt")["world"] == 1


@row("two evaluations into one --out at once: each wrote its pair of files at the end, so the folder could hold "
            "one's submission beside the other's metrics (a pair that looked whole); the second is refused while "
            "the first runs, and a refused or failed evaluation leaves no folder it created")
def row_two_evaluations_into_one_out(env):
    from instagram_hdmap.files import LOCK_FILE, locked_folder
    from instagram_hdmap.predict import load_model

    out = env.tmp / "eval"
    out.mkdir()
    (out / "metrics.json").write_text("{}")  # the first evaluation's earlier pair
    holder = subprocess.Popen(  # the first evaluation's lock, as files.lock_folder takes it
        [sys.executable, "-c", "import fcntl, os, sys, time\n"
         f"f = open({str(out / LOCK_FILE)!r}, 'a+'); fcntl.flock(f, fcntl.LOCK_EX); f.write(str(os.getpid()))\n"
         "f.flush(); print('locked', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        forbid(env, "instagram_hdmap.evaluate_split.load_model", "the evaluation")
        env.error(rf"another evaluation is running in .*eval \(process {holder.pid}\); wait for it to end \(or stop "
                  r"it\), or choose another --out", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
        assert (out / "metrics.json").read_text() == "{}"
    finally:
        holder.kill()
        holder.wait()
    nested = env.tmp / "new" / "eval"  # created for a job that fails before writing: removed again
    with pytest.raises(RuntimeError, match="the job failed"), locked_folder(nested, "evaluation", "choose another"):
        assert (nested / LOCK_FILE).is_file()
        raise RuntimeError("the job failed")
    assert not (env.tmp / "new").exists()
    env.monkeypatch.setattr("instagram_hdmap.evaluate_split.load_model", load_model)
    rc, out_, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", nested)
    assert rc == 0, err
    assert sorted(p.name for p in nested.iterdir()) == ["metrics.json", "submission.json"]  # the lock file gone


@row("train --resume RUN/last.pt of an unfinished run with another train.out_dir (the config's default when "
            "none is given): the run went on in that folder, its earlier checkpoints, log and events left in RUN, and "
            "only the final 'outputs in' line named it; a note says where it goes on and how to continue in RUN")
def row_resume_into_another_folder_noted(env):
    run = env.tmp / "run"
    toy_run(env, [0.6], "train.epochs=3", "train.max_steps=1")
    other = env.tmp / "elsewhere"
    toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", f"train.out_dir={other}", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert (f"note: {run / 'last.pt'} is a checkpoint of the run in {run.resolve()}; this run goes on in "
            f"train.out_dir={other}") in out and f"pass train.out_dir={run.resolve()}" in out
    assert (other / "last.pt").is_file()
    toy_run(env, [0.3, 0.4, 0.2], "train.epochs=3", resume=str(run / "last.pt"))  # its own folder: no note
    assert "is a checkpoint of the run in" not in env.capsys.readouterr().out


@row("a training killed (kill -9, a power cut) between an epoch's last.pt and its line in log.jsonl: the "
            "resume went on after that epoch and its line (losses, validation, samples/s) was never written; now the "
            "line goes first, the checkpoint counts the lines before it, and a resume drops a killed run's lines "
            "after its checkpoint (here the resume trains the epoch's end again and logs it once)")
def row_log_line_survives_a_kill_between_line_and_checkpoint(env):
    from instagram_hdmap.train import TrainingRun

    class Killed(BaseException):  # not an exception the run handles: no save at the kill, as with kill -9
        pass

    real = {name: getattr(TrainingRun, name) for name in ("train_epoch", "log", "save")}
    armed = []

    def train_epoch(self):
        stopped = real["train_epoch"](self)
        armed.append(self.position.epoch == 1)  # epoch 0 just ended
        return stopped

    def killed_after(name):
        def wrapped(self, *args, **kwargs):
            real[name](self, *args, **kwargs)
            if armed and armed[-1]:  # the first of the epoch's two writes, whichever it is
                raise Killed
        return wrapped

    env.monkeypatch.setattr(TrainingRun, "train_epoch", train_epoch)
    env.monkeypatch.setattr(TrainingRun, "log", killed_after("log"))
    env.monkeypatch.setattr(TrainingRun, "save", killed_after("save"))
    run = env.tmp / "run"
    args = ["train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "train.checkpoint_every=1",
            "train.val_every=100"]
    with pytest.raises(Killed):
        env.cli(*args)
    for name, method in real.items():
        env.monkeypatch.setattr(TrainingRun, name, method)
    rc, _, err = env.cli(*args, "--resume", run / "last.pt")
    assert rc == 0, err[-2000:]
    lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [line["epoch"] for line in lines] == [0, 1], lines
    assert load_checkpoint(run / "last.pt")["log_lines"] == 2


@row("torchrun jobs never destroyed their process group: at the interpreter's exit gloo's worker threads, still "
            "running, aborted a rank now and then (SIGABRT, 'terminate called without an active exception') and the "
            "job failed, exit 1, after all its work was done (twice in one loaded full suite); a command that ends "
            "well destroys it on every rank (here a one-process group, as torchrun --nproc_per_node 1 makes)")
def row_process_group_destroyed_at_the_end(env):
    import socket

    import torch.distributed as dist

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    for key, value in {"RANK": "0", "WORLD_SIZE": "1", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(port)}.items():
        env.monkeypatch.setenv(key, value)
    try:
        rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "e")
        assert rc == 0, err[-2000:]
        assert (env.tmp / "e" / "metrics.json").is_file()
        assert not dist.is_initialized(), "the process group outlived the command"
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


_LATE_WORKER_DEATH = """
import os, signal, sys, time
import torch
from torch.utils.data import DataLoader, Dataset
from torch.utils.data import dataloader
from instagram_hdmap import engine

class Frames(Dataset):
    def __len__(self):
        return 8

    def __getitem__(self, i):
        return {"images": torch.zeros(1, 3, 4, 4)}

class Interrupted(torch.nn.Module):
    def forward(self, batch):
        raise KeyboardInterrupt  # a SIGTERM, as a training turns it into one

real = dataloader._MultiProcessingDataLoaderIter._shutdown_workers

def signal_arrives_late(self):  # the same signal reaches the worker during the shutdown (a loaded machine)
    if not self._shutdown:
        for worker in self._workers:
            os.kill(worker.pid, signal.SIGKILL)
        time.sleep(0.3)
    return real(self)

dataloader._MultiProcessingDataLoaderIter._shutdown_workers = signal_arrives_late
try:
    engine.evaluate(Interrupted(), None, DataLoader(Frames(), batch_size=2, num_workers=1), torch.device("cpu"))
except KeyboardInterrupt:
    print("interrupted: saved", flush=True)
sys.exit(130)
"""


@row("a loop over data-loader workers cut short by a scheduler's SIGTERM to the whole process group, on a "
            "loaded machine (seen once in a full suite, in sigterm-saves-last-pt): the workers were shut down "
            "later by the iterator's __del__, where the worker's death came in as an 'Exception ignored ... "
            "DataLoader worker is killed by signal' traceback under the run's one-line message (or in the middle of "
            "the save of last.pt); the loop shuts its workers down as it ends")
def row_workers_shut_down_when_a_loop_is_cut_short(env):
    p = subprocess.run([sys.executable, "-c", _LATE_WORKER_DEATH], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(REPO / "src")})
    assert p.returncode == 130 and p.stdout.strip() == "interrupted: saved", (p.returncode, p.stdout, p.stderr)
    assert "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr[-2000:]


@row("train stopped by train.max_steps before the end of its schedule: README says the run 'ends before its "
            "final LR, and says so', but it printed only 'done: epoch 0, step 1' (log.jsonl's schedule_complete alone "
            "held it); a note says so and how to finish")
def row_max_steps_says_the_schedule_is_cut(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1", "train.epochs=2")
    assert rc == 0, err
    assert re.search(r"note: train\.max_steps=1 stopped the run before the end of its schedule \(progress 0\.\d+; "
                     r"lr .*\): resume with a larger train\.max_steps", out), out
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=2", "--resume", run / "last.pt")
    assert rc == 0 and "stopped the run before the end" not in out, out + err


@row("train --resume with another data.ped_crossing (the crossings' targets: edges or rings) or data.image_fit "
            "(the images the model learns from): the run went on with the other targets / images, mixed into one "
            "model, exit 0, no word; both are checked as the other keys that define the training targets")
def row_resume_with_another_crossing_convention_or_image_fit(env):
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1", "train.epochs=2")
    assert rc == 0, err
    for override, named in (("data.ped_crossing=each", "data.ped_crossing: checkpoint 'edges' vs now 'each'"),
                            ("data.image_fit=stretch", "data.image_fit: checkpoint 'cover' vs now 'stretch'")):
        env.error(rf"last\.pt was trained with an incompatible config \({re.escape(named)}\); resume it with the "
                  r"config it was trained with, or start a new run from its weights with train\.init_from=", "train",
                  env.yaml, f"train.out_dir={run}", "train.epochs=2", override, "--resume", run / "last.pt")
    assert load_checkpoint(run / "last.pt")["step"] == 1


@row("Ctrl-C (or a SIGTERM) in the middle of a training step saved last.pt with the step half done (the "
            "BatchNorm statistics of its forward, the optimizer's moments), which the resume did again: its weights "
            "differed from an uninterrupted run's, with no word. The signal now waits for the step's end")
def row_interrupt_mid_step_resumes_exactly(env):
    import signal

    from instagram_hdmap import engine

    real, calls = engine.optimisation_step, []

    def ctrl_c_in_the_second_step(*args, **kwargs):  # after the forward, before the optimizer's step
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kwargs)

    common = ["train.batch_size=1", "train.val_every=100"]
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'whole'}", *common)
    assert rc == 0, err[-2000:]
    env.monkeypatch.setattr(engine, "optimisation_step", ctrl_c_in_the_second_step)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", *common)
    assert rc == 130 and load_checkpoint(run / "last.pt")["step"] == 2, (rc, err[-2000:])
    env.monkeypatch.setattr(engine, "optimisation_step", real)
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "--resume", run / "last.pt", *common)
    assert rc == 0, err[-2000:]
    whole, resumed = load_checkpoint(env.tmp / "whole" / "last.pt")["model"], load_checkpoint(run / "last.pt")["model"]
    assert all(torch.equal(whole[k], resumed[k]) for k in whole), "the resumed weights differ"


@row("OMP_NUM_THREADS=0 or =abc (a laptop's shell profile): OpenMP said 'Invalid value' and took its default, "
            "and the training left the threads alone as for a value the user chose, printing '(OMP_NUM_THREADS)'; an "
            "invalid value now counts as unset (the run chooses its threads), a valid one is still left alone")
def row_invalid_omp_num_threads(env):
    from instagram_hdmap.train import cpu_threads

    cfg = env.cfg()
    for value in ("0", "abc", " "):
        env.monkeypatch.setenv("OMP_NUM_THREADS", value)
        assert isinstance(cpu_threads(cfg), int) and cpu_threads(cfg) >= 1, value
    env.monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert cpu_threads(cfg) is None


@row("train.out_dir renamed while the run wrote to it: a raw FileNotFoundError traceback from TensorBoard's "
            "writer thread (or, when the next save came first, a new folder of the old name holding a lone last.pt); "
            "now one line naming the folder, the step, and where it is now to resume")
def row_run_folder_renamed_during_training(env):
    from instagram_hdmap import train as train_module

    run, moved = env.tmp / "run", env.tmp / "run2"
    save = train_module.save_checkpoint

    def save_then_rename(state, path):  # the user's `mv run run2` right after the first epoch's checkpoint
        out = save(state, path)
        if not moved.exists() and Path(path).name == "last.pt":
            run.rename(moved)
        return out

    env.monkeypatch.setattr(train_module, "save_checkpoint", save_then_rename)
    with pytest.raises(UserError, match=rf"train.out_dir {re.escape(str(run))} was moved or removed while this run "
                                        rf"wrote to it.*stopped at step \d+; it is now {re.escape(str(moved))}: "
                                        rf"resume there with --resume {re.escape(str(moved / 'last.pt'))}"):
        toy_run(env, [0.2, 0.3], "train.epochs=2", "train.batch_size=2")
    assert not run.exists() and (moved / "last.pt").is_file()
    assert load_checkpoint(moved / "last.pt")["step"] >= 1


@row("--resume with a model key that leaves the model's computation as it is was refused as 'an incompatible "
            "config': model.backbone.grad_checkpoint (turned on after running out of memory), the decoding options "
            "(model.gnn.decoder, read at validation only); now it resumes, and a decoding option is named in the note "
            "that best.pt's score was measured with another validation")
def row_resume_with_a_memory_or_decoding_setting(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = toy_run(env, [0.3, 0.1], "train.epochs=2", "model.backbone.grad_checkpoint=false",
                       "model.gnn.decoder=mutual", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert summary["step"] == 4
    assert re.search(r"note: the best score so far .*another validation \(model\.gnn\.decoder: checkpoint 'greedy' "
                     r"vs now 'mutual'\)", out), out
    assert "grad_checkpoint" not in out  # the same model, the same scores: nothing to say


@row("--resume with another train.lr, train.schedule, train.warmup, data.augment ... went on with no word, and "
            "config.yaml was rewritten with the new values as if the whole run had been trained with them; now a note "
            "names each changed training setting and says the steps so far were trained with the checkpoint's")
def row_resume_with_other_training_settings_noted(env):
    run = env.tmp / "run"
    toy_run(env, [0.2], "train.epochs=2", "train.max_steps=1")
    env.capsys.readouterr()
    summary = toy_run(env, [0.3, 0.1], "train.epochs=2", "train.lr=0.01", "train.warmup=0.5",
                       "train.max_steps=null", resume=str(run / "last.pt"))
    out = env.capsys.readouterr().out
    assert summary["step"] == 4
    note = next((ln for ln in out.splitlines() if ln.startswith("note: resumed with training settings")), "")
    assert "train.lr: checkpoint 0.001 vs now 0.01" in note and "train.warmup: checkpoint 0.0 vs now 0.5" in note, out
    assert "the 1 step(s) so far trained with the checkpoint's" in note and "max_steps" not in note, note


@row("evaluate --out into the folder of a running training (a run folder as the evaluation's output) was "
            "refused as 'another evaluation is running in RUN': the lock named the job of the process refused, not "
            "the one holding it; now 'another training is running'")
def row_lock_names_the_job_that_holds_it(env):
    run = env.tmp / "run"
    run.mkdir()
    code = ("import time\nfrom instagram_hdmap.files import lock_folder\n"
            f"lock_folder({str(run)!r}, 'training', 'choose another train.out_dir')\n"
            "print('locked', flush=True); time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert holder.stdout.readline().strip() == "locked"
        env.error(rf"another training is running in .*run \(process {holder.pid}\); .*choose another --out",
                  "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", run)
    finally:
        holder.kill()
        holder.wait()


@row("--resume with a train.epochs whose schedule ends before the checkpoint's step (3 epochs cut to 1 at "
            "step 3 of epoch 1): 'done', exit 0, after no step, with last.pt and config.yaml still of the 3-epoch run; "
            "now refused, naming the step where the new schedule ends and the epochs that would finish it")
def row_resume_with_fewer_epochs_than_done(env):
    run = env.tmp / "run"
    toy_run(env, [0.2, 0.25], "train.epochs=3", "train.max_steps=3")  # two steps an epoch: step 3 is in epoch 1
    with pytest.raises(UserError, match=r"train\.epochs=1 ends the schedule at step 2, before checkpoint .*last\.pt's "
                                        r"step 3 \(epoch 1 of its 3\): nothing would be trained; resume with "
                                        r"train\.epochs=2 or more"):
        toy_run(env, [], "train.epochs=1", resume=str(run / "last.pt"))
    assert toy_run(env, [0.3], "train.epochs=2", resume=str(run / "last.pt"))["step"] == 4  # cut to 2: runs


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_runs(case, env):
    case.run(env)
