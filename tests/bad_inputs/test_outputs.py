"""Where outputs go: paths that are files, folders, below a file, inputs of the same job, symbolic links, pipes and
devices; a full disk, a read-only file system, long names; standard output and error closed, piped or in a file.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from bad_inputs.support import (
    dead_pid,
    forbid,
    row,
    submission_file,
    table,
    val_scene,
)
from instagram_hdmap.checkpoint import load_checkpoint, save_checkpoint
from instagram_hdmap.config import UserError


@row("evaluate --out that is a file: refused before the evaluation runs")
def row_evaluate_out_is_a_file(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.evaluate_split.evaluate", "the evaluation")
    env.error(r"taken", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "taken")


@row("train.out_dir that is a file: refused before training")
def row_train_out_dir_is_a_file(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"taken", "train", env.yaml, f"train.out_dir={env.tmp / 'taken'}")


@row("predict --out below a file: refused before the model runs")
def row_predict_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"taken", "predict", env.yaml, "--checkpoint", env.ckpt, "--index", "0", "--out",
              env.tmp / "taken" / "pics")


@row("export-gt --out below a file: refused before the export")
def row_export_gt_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"taken", "export-gt", env.yaml, "--out", env.tmp / "taken" / "gt.json")


@row("evaluate-json --out below a file: refused before the evaluation")
def row_evaluate_json_out_not_writable(env):
    (env.tmp / "taken").write_text("x")
    gt = env.tmp / "gt.json"
    gt.write_text(json.dumps({"results": {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}}))
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"taken", "evaluate-json", "--pred", gt, "--gt", gt, "--out", env.tmp / "taken" / "m.json")


@row("export-gt --out that is a folder: refused before the export (was an IsADirectoryError after it)")
def row_export_gt_out_is_a_folder(env):
    (env.tmp / "folder").mkdir()
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out .*folder.*is a folder", "export-gt", env.yaml, "--out", env.tmp / "folder")


@row("evaluate-json --out that is a folder: refused before the evaluation (was an IsADirectoryError)")
def row_evaluate_json_out_is_a_folder(env):
    (env.tmp / "folder").mkdir()
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    forbid(env, "instagram_hdmap.evaluation.Evaluator.compute", "the evaluation")
    env.error(r"--out .*folder.*is a folder", "evaluate-json", "--pred", gt, "--gt", gt, "--out", env.tmp / "folder")


@row("a full disk during a checkpoint save is named (and the old checkpoint kept)")
def row_full_disk(env):
    old = save_checkpoint({"model": {"w": torch.ones(3)}}, env.tmp / "last.pt")
    code = (
        "import resource, signal, torch, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))\n"
        "from instagram_hdmap.checkpoint import save_checkpoint\n"
        "from instagram_hdmap.config import UserError\n"
        "try:\n"
        f"    save_checkpoint({{'model': {{'w': torch.zeros(200_000)}}}}, {str(old)!r})\n"
        "except UserError as e:\n"
        "    print('USER', e); sys.exit(2)\n"
    )
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env_vars, timeout=120)
    assert p.returncode == 2, p.stderr[-2000:]
    assert re.search(r"USER .*last\.pt.*(disk|space|too large)", p.stdout), p.stdout
    assert torch.equal(load_checkpoint(old)["model"]["w"], torch.ones(3))
    assert sorted(x.name for x in env.tmp.iterdir()) == ["last.pt"]


@row("a full disk while writing a JSON result is named (and the old file kept)")
def row_full_disk_json(env):
    old = env.tmp / "metrics.json"
    old.write_text('{"old": 1}')
    code = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))\n"
        "from instagram_hdmap.files import write_json\n"
        "from instagram_hdmap.config import UserError\n"
        "try:\n"
        f"    write_json({{'x': 'a' * 200_000}}, {str(old)!r})\n"
        "except UserError as e:\n"
        "    print('USER', e); sys.exit(2)\n"
    )
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env_vars, timeout=120)
    assert p.returncode == 2, p.stderr[-2000:]
    assert re.search(r"USER cannot write .*metrics\.json: File too large \(the disk is full", p.stdout), p.stdout
    assert old.read_text() == '{"old": 1}' and sorted(x.name for x in env.tmp.iterdir()) == ["metrics.json"]


@row("a full disk outside the atomic writes (a training's log line) is one line, not a traceback")
def row_full_disk_in_a_log_write(env):
    import errno

    from instagram_hdmap.train import TrainingRun

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.out_dir / "log.jsonl"))

    env.monkeypatch.setattr(TrainingRun, "log", full)
    env.error(r"No space left on device writing .*log\.jsonl: the disk is full", "train", env.yaml,
              f"train.out_dir={env.tmp / 'run'}", "train.max_steps=1")


@row("temporary folders of killed world generations are removed by the next one")
def row_stale_synth_temporaries(env):
    from instagram_hdmap.data.synthetic import generate_world

    dead, alive = dead_pid(), os.getppid()
    for pid in (dead, alive):
        (env.tmp / f".w.synth-tmp-{pid}" / "samples").mkdir(parents=True)
    generate_world(env.tmp / "w", scenes_train=1, scenes_val=0, samples_per_scene=1, image_size="160x90",
                   progress=False)
    left = sorted(p.name for p in env.tmp.iterdir() if p.name.startswith("."))
    assert left == [f".w.synth-tmp-{alive}"]


@row("an output path that is one of the job's inputs is refused before the work (was overwritten)")
def row_output_is_an_input(env):
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    pred = submission_file(env.tmp / "p.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0, "confidence_level": 0.5}]},
                       False)
    before = gt.read_bytes()
    env.error(r"--out .*gt\.json is the --gt file", "evaluate-json", "--pred", pred, "--gt", gt, "--out", gt)
    assert gt.read_bytes() == before
    config = env.tmp / "cfg.yaml"
    shutil.copy(env.yaml, config)
    env.error(r"--out .*cfg\.yaml is the CONFIG file", "export-gt", config, "--out", config)
    ckpt = env.tmp / "model.pt"
    shutil.copy(env.ckpt, ckpt)
    forbid(env, "instagram_hdmap.deploy.export_onnx", "the export")
    env.error(r"--out .*model\.pt is the --checkpoint file", "export-onnx", env.yaml, "--checkpoint", ckpt,
              "--out", ckpt)
    assert ckpt.read_bytes() == env.ckpt.read_bytes()


@row("predict --video below a file, or --fps 1e9, is refused before the model runs (was a raw error after)")
def row_video_out_checked_first(env):
    (env.tmp / "taken").write_text("x")
    forbid(env, "instagram_hdmap.predict.load_predictor", "the model")
    env.error(r"--video .*taken.* is a file", "predict", env.yaml, "--checkpoint", env.ckpt, "--scene",
              val_scene(env), "--video", env.tmp / "taken" / "v.mp4")
    env.error(r"--fps 1e\+09: .*at most", "predict", env.yaml, "--checkpoint", env.ckpt, "--scene", val_scene(env),
              "--video", env.tmp / "v.mp4", "--fps", "1e9")


@row("predict --video on a full disk: named, no broken MP4 (OpenCV's writer reports nothing; was exit 0)")
def row_video_on_a_full_disk(env):
    import cv2

    real = cv2.VideoWriter

    class FullDisk:  # writes as OpenCV does, then loses the file's end as a full disk would
        def __init__(self, path, *args):
            self.path, self.writer = path, real(path, *args)

        def __getattr__(self, name):
            return getattr(self.writer, name)

        def release(self):
            self.writer.release()
            data = Path(self.path).read_bytes()
            Path(self.path).write_bytes(data[:len(data) // 2])

    env.monkeypatch.setattr("instagram_hdmap.predict.cv2.VideoWriter", FullDisk)
    video = env.tmp / "scene.mp4"
    env.error(r"cannot write --video .*scene\.mp4: the MP4 file OpenCV wrote is incomplete", "predict", env.yaml,
              "--checkpoint", env.ckpt, "--scene", val_scene(env), "--video", video)
    assert sorted(p.name for p in env.tmp.iterdir()) == []


@row("a full disk while drawing PNGs names the file and leaves no empty PNG (show-gt, predict)")
def row_png_on_a_full_disk(env):
    import errno

    from matplotlib.figure import Figure

    def full(self, path, *args, **kwargs):
        Path(path).write_bytes(b"")
        raise OSError(errno.ENOSPC, "No space left on device")

    env.monkeypatch.setattr(Figure, "savefig", full)
    env.error(r"cannot write .*bev_polylines\.png: No space left on device", "show-gt", env.yaml, "--out",
              env.tmp / "gt")
    assert list((env.tmp / "gt").iterdir()) == []


@row("evaluate --out whose metrics.json is a folder: refused before the evaluation (was after it, with a new "
          "submission.json next to the old metrics)")
def row_evaluate_metrics_path_is_a_folder(env):
    (env.tmp / "e" / "metrics.json").mkdir(parents=True)
    forbid(env, "instagram_hdmap.evaluate_split.evaluate", "the evaluation")
    env.error(r"metrics\.json: is a folder", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("train CONFIG where CONFIG is OUT/config.yaml (the experiment kept in its run folder): refused (the run "
          "started over, removing it, and wrote its resolved config there: comments and _base_ lost)")
def row_config_inside_out_dir(env):
    exp = env.tmp / "exp"
    exp.mkdir()
    config = exp / "config.yaml"
    text = f"# my experiment\n_base_: {env.yaml}\ntrain:\n  out_dir: {exp}\n"
    config.write_text(text)
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"CONFIG .*config\.yaml is .*config\.yaml, where the run writes its resolved config", "train", config)
    assert config.read_text() == text


@row("export-gt --out a table of the dataset it reads (v1.0-trainval/sample.json) is refused (it was replaced "
          "by the GT file: the dataset destroyed, exit 0)")
def row_export_gt_over_a_table(env):
    root = env.shadow_world()
    table = root / "v1.0-trainval" / "sample.json"
    before = table.read_bytes()
    for _ in range(2):  # a GT file of its own right in the dataroot is fine, and may be written again
        rc, _, err = env.cli("export-gt", env.yaml, f"data.dataroot={root}", "--out", root / "gt_val.json")
        assert rc == 0, err[-2000:]
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out .*sample\.json is a file of the dataset the export reads", "export-gt", env.yaml,
              f"data.dataroot={root}", "--out", table)
    assert table.read_bytes() == before


@row("an output path through a symbolic link that leads nowhere (a loop, an unmounted disk) is named before the "
          "work (evaluate, train, synth: raw FileExistsError / RuntimeError), and a result written at a symbolic link "
          "updates the file it points to (the link was replaced, the file left stale)")
def row_output_path_broken_symlink(env):
    dangling, loop = env.tmp / "dangling", env.tmp / "loop"
    dangling.symlink_to(env.tmp / "unmounted" / "runs")
    loop.symlink_to(env.tmp / "loop2")
    (env.tmp / "loop2").symlink_to(loop)
    forbid(env, "instagram_hdmap.evaluate_split.evaluate", "the evaluation")
    env.error(r"--out .*dangling: .*dangling is a symbolic link to .*unmounted/runs, which leads nowhere", "evaluate",
              env.yaml, "--checkpoint", env.ckpt, "--out", dangling)
    env.error(r"--out .*loop/e: .*loop is a symbolic link to .*loop2, which leads nowhere", "evaluate", env.yaml,
              "--checkpoint", env.ckpt, "--out", loop / "e")
    forbid(env, "instagram_hdmap.train.train_one_epoch", "training")
    env.error(r"train\.out_dir .*loop: .*leads nowhere", "train", env.yaml, f"train.out_dir={loop}")
    env.error(r"--out .*dangling: .*leads nowhere", "synth", "--out", dangling, "--scenes-train", "1", "--scenes-val",
              "0", "--samples-per-scene", "1", "--image-size", "160x90")
    assert not (env.tmp / "unmounted").exists()
    target, link = env.tmp / "shared_metrics.json", env.tmp / "metrics.json"
    target.write_text('{"old": 1}')
    link.symlink_to(target)
    gt = submission_file(env.tmp / "gt.json", {"a": [{"pts": [[0, 0], [1, 1]], "type": 0}]}, True)
    env.monkeypatch.undo()
    rc, _, err = env.cli("evaluate-json", "--pred", gt, "--gt", gt, "--out", link)
    assert rc == 0, err[-2000:]
    assert link.is_symlink() and json.loads(target.read_text())["protocol"] == "vector"


@row("a write whose folder is removed while the job runs (or a file system that takes no new files) is one line "
          "naming the file (was a raw FileNotFoundError)")
def row_output_folder_removed_during_the_write(env):
    from instagram_hdmap.files import OutputError, atomic_path

    target = env.tmp / "out" / "metrics.json"
    with pytest.raises(OutputError, match=r"cannot write .*out/metrics\.json: No such file or directory"):
        with atomic_path(target) as tmp:
            shutil.rmtree(target.parent)  # another process cleaning up, a network folder unmounted
            tmp.write_text("{}")


@row("an atomic write over a file with a second (hard-linked) name replaces the name written; the other name "
          "keeps the old content, as os.replace does (the promise docs/faults.md states)")
def row_atomic_write_over_a_hard_link(env):
    from instagram_hdmap.files import write_json

    old, other = env.tmp / "metrics.json", env.tmp / "backup.json"
    old.write_text('{"mAP": 0.5}')
    os.link(old, other)
    write_json({"mAP": 0.7}, old)
    assert json.loads(old.read_text()) == {"mAP": 0.7} and json.loads(other.read_text()) == {"mAP": 0.5}
    assert not old.samefile(other)


@row("synth-preview --out without a picture suffix (a name such as 'preview', or an existing file 'notes'): "
            "matplotlib's raw ValueError about the format 'tmp-PID' of the temporary file; a seed of 2**70 was "
            "refused as not 'a whole number >= 0'")
def row_synth_preview_out_without_suffix(env):
    env.error(r"--out .*preview: the picture's format comes from its suffix; .*\.png", "synth-preview", env.world,
              "--out", env.tmp / "preview")
    (env.tmp / "notes").write_text("mine")
    env.error(r"--out .*notes: the picture's format", "synth-preview", env.world, "--out", env.tmp / "notes")
    assert (env.tmp / "notes").read_text() == "mine"
    env.error(r"--seed 1180591620717411303424: .* from 0 to 2\*\*63 - 1", "synth", "--out", env.tmp / "w", "--seed",
              str(2**70), "--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1")
    rc, out, err = env.cli("synth-preview", env.world, "--out", env.tmp / "p.PNG")  # the suffix in any case
    assert rc == 0 and (env.tmp / "p.PNG").stat().st_size > 0, err[-2000:]


@row("export-onnx --out naming the CONFIG file (the YAML given first) replaced the config with the ONNX graph, "
            "exit 0 (--out naming the checkpoint was refused already)")
def row_export_onnx_out_is_the_config(env):
    pytest.importorskip("onnx", reason="the [deploy] extra is not installed")
    config = env.tmp / "exp.yaml"
    shutil.copy(env.yaml, config)
    before = config.read_bytes()
    env.error(r"--out .*exp\.yaml is the CONFIG file the job reads", "export-onnx", config, "--checkpoint", env.ckpt,
              "--out", config)
    assert config.read_bytes() == before


@row("a path option written --out=~/eval (the shell expands no ~ after '='; nor in quotes) wrote a folder "
            "named '~' under the working directory while saying 'wrote ~/eval/...'; it is the home folder, as "
            "the config's path keys read it")
def row_tilde_in_cli_paths(env):
    home = env.tmp / "home"
    home.mkdir()
    env.monkeypatch.setenv("HOME", str(home))
    rc, out, err = env.cli("export-gt", env.yaml, "--out=~/gt.json")
    assert rc == 0 and (home / "gt.json").is_file() and not (env.tmp / "~").exists(), err[-2000:]
    env.error(r"checkpoint not found: .*home/nope\.pt", "evaluate", env.yaml, "--checkpoint=~/nope.pt",
              "--out", env.tmp / "eval")


@row("an output path on a read-only file system (a read-only mount or snapshot) was 'no permission to write "
            "in DIR', which sends the user to chmod; it is named as a read-only file system")
def row_read_only_file_system_named(env):
    from types import SimpleNamespace

    from instagram_hdmap import files

    ro = env.tmp / "ro"
    ro.mkdir()
    real_access, real_statvfs = os.access, os.statvfs
    env.monkeypatch.setattr(files.os, "access", lambda p, mode, *a, **k: False if Path(p) == ro else
                            real_access(p, mode, *a, **k))
    env.monkeypatch.setattr(files.os, "statvfs", lambda p: SimpleNamespace(f_flag=os.ST_RDONLY) if Path(p) == ro
                            else real_statvfs(p))
    env.error(r"--out .*gt\.json: .*ro is on a read-only file system", "export-gt", env.yaml, "--out", ro / "gt.json")
    env.error(r"--out .*ro: is on a read-only file system", "evaluate", env.yaml, "--checkpoint", env.ckpt,
              "--out", ro)


@row("train.out_dir a folder of other files (train.out_dir=. in a project folder): refused, but told to 'pass "
            "--resume ./last.pt to continue it' (no such checkpoint: a second error); it says what to do instead")
def row_out_dir_of_other_files(env):
    out = env.tmp / "project"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    line = env.error(r"holds files that are not a run's \(notes\.txt\); choose another train\.out_dir", "train",
                     env.yaml, f"train.out_dir={out}")
    assert "--resume" not in line


@row("train.out_dir on a file system that takes no file lock (NFS without lockd, some FUSE mounts: flock fails "
            "with ENOLCK): 'another training is running in OUT (process ?)', so no training could run there at all; "
            "it trains without the lock, with a note")
def row_out_dir_without_file_locks(env):
    import errno
    import fcntl

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    env.monkeypatch.setattr(fcntl, "flock", no_locks)
    run = env.tmp / "run"
    rc, out, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.max_steps=1")
    assert rc == 0, err[-2000:]
    assert "takes no file lock (No locks available)" in out and (run / "last.pt").is_file()


@row("long file names: export-gt --out of a valid 250-byte name failed after the work with a raw ENAMETOOLONG "
            "(its temporary .NAME.tmp-PID was longer than a file name may be); a name over 255 bytes in "
            "train.out_dir or evaluate --out was a raw OSError from the first stat. The temporary's name is cut to "
            "fit, and a name too long is one line")
def row_long_file_names(env):
    name = "g" * 245 + ".json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", env.tmp / name)
    assert rc == 0 and (env.tmp / name).is_file(), err[-2000:]
    too_long = env.tmp / ("a" * 300)
    env.error(r"train\.out_dir .*: the name a+\.\.\. is 300 bytes long, more than a file name can be \(255\)", "train",
              env.yaml, f"train.out_dir={too_long}")
    env.error(r"--out .*: the name a+\.\.\. is 300 bytes long", "evaluate", env.yaml, "--checkpoint", env.ckpt,
              "--out", too_long)


@row("files.lock_folder (evaluate's --out, train.out_dir): a folder named .instagram_hdmap.lock where the lock "
            "file goes was a raw IsADirectoryError traceback (exit 1); it is one line naming it")
def row_lock_file_is_a_folder(env):
    out = env.tmp / "eval"
    (out / ".instagram_hdmap.lock").mkdir(parents=True)
    env.error(r"eval/\.instagram_hdmap\.lock \(the lock this evaluation holds on .*eval\) is a folder, not the lock "
              r"file; remove it, or choose another --out", "evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", out)
    run = env.tmp / "run"
    (run / ".instagram_hdmap.lock").mkdir(parents=True)
    env.error(r"is a folder, not the lock file; remove it, or choose another train.out_dir", "train", env.yaml,
              f"train.out_dir={run}", "train.max_steps=1")


@row("a command's output piped into a reader that stops early (`model-summary CONFIG | head -1`, export-gt's "
            "'wrote' line into `head -0`): a raw BrokenPipeError traceback, exit 1; now quiet, exit 141 as Unix "
            "tools (SIGPIPE)")
def row_output_pipe_closed_early(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    for argv in (["model-summary", str(env.yaml)], ["export-gt", str(env.yaml), "--out", str(env.tmp / "gt.json")]):
        p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, env=env_vars)
        p.stdout.close()  # the reader is gone before the first line (`| head -0`)
        err = p.stderr.read().decode()
        assert p.wait(timeout=120) == 141, err[-2000:]
        assert "Traceback" not in err and "BrokenPipe" not in err, err[-2000:]
    assert (env.tmp / "gt.json").is_file()  # the work was done; only its report had no reader


@row("export-gt --out - (stdout for Unix tools): a file named '-' written in the working directory, 'wrote -', "
            "exit 0 (show-gt --out -: a folder '-'); --out /dev/stdout still writes the JSON to the terminal")
def row_dash_as_output_path(env):
    forbid(env, "instagram_hdmap.cli.gt_submission", "the export")
    env.error(r"--out -: the output is written to a file, not to stdout", "export-gt", env.yaml, "--out", "-")
    env.error(r"--out -: the output is written to a file, not to stdout", "show-gt", env.yaml, "--out", "-")
    forbid(env, "instagram_hdmap.demo.ensure_world", "world generation")
    env.error(r"--out -: the output is written to a file", "demo", "--out", "-", "--cache", env.tmp / "cache")
    assert not Path("-").exists()  # the row runs in its own folder (monkeypatch.chdir)


@row("synth --out below a file (notes.txt/world): 'cannot write there (File exists)', naming neither the file "
            "nor the cause; now names the file that is not a folder")
def row_synth_out_below_a_file(env):
    (env.tmp / "notes.txt").write_text("x")
    env.error(r"--out .*notes\.txt/world: .*notes\.txt is a file, not a folder", "synth", "--out",
              env.tmp / "notes.txt" / "world", "--scenes-train", "1", "--scenes-val", "1", "--samples-per-scene", "1",
              "--image-size", "64x48")


@row("synth --out '' (an unset shell variable, --out \"$WORLD\") was taken for the current folder: refused "
            "there only because it was not empty (an empty one got the world). An empty --out is named")
def row_synth_out_empty_string(env):
    env.error(r"--out '': an empty path", "synth", "--out", "", "--scenes-train", "1", "--scenes-val", "1",
              "--samples-per-scene", "1", "--image-size", "64x48")
    from instagram_hdmap.data.synthetic import generate_world

    with pytest.raises(UserError, match=r"--out '': an empty path"):  # the Python API too
        generate_world("", scenes_train=1, scenes_val=1, samples_per_scene=1, image_size="64x48", progress=False)


@row("export-onnx --out runs/x/best.pt while exporting last.pt (a slip of the file name) replaced the best "
            "checkpoint with the ONNX graph, exit 0; export-gt and evaluate-json --out did the same with JSON. An "
            "existing PyTorch checkpoint as an output file is refused before the work")
def row_output_over_another_checkpoint(env):
    best = env.tmp / "best.pt"
    shutil.copy(env.ckpt, best)
    before = best.read_bytes()
    gt = env.tmp / "gt.json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err[-2000:]
    pattern = r"--out .*best\.pt is a PyTorch checkpoint; writing the result there would destroy it"
    env.error(pattern, "export-gt", env.yaml, "--out", best)
    env.error(pattern, "evaluate-json", "--gt", gt, "--pred", gt, "--out", best)
    env.error(pattern, "export-onnx", env.yaml, "--checkpoint", env.ckpt, "--out", best)
    assert best.read_bytes() == before
    rc, _, err = env.cli("evaluate-json", "--gt", gt, "--pred", gt, "--out", env.tmp / "metrics.json")  # any other file
    assert rc == 0, err[-2000:]


@row("the file's folder given for the file: evaluate-json --pred EVAL_OUT said 'cannot read ([Errno 21] Is a "
            "directory)', --pred EVAL_OUT/metrics.json 'no results key'; each now names the file that is meant "
            "(a checkpoint's run folder: checkpoints::checkpoint-given-as-a-run-folder)")
def row_folder_given_for_its_file(env):
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-2000:]
    gt = env.tmp / "gt.json"
    rc, _, err = env.cli("export-gt", env.yaml, "--out", gt)
    assert rc == 0, err[-2000:]
    env.error(r"eval: is a folder, not a submission file; the file in it: .*eval/submission\.json", "evaluate-json",
              "--gt", gt, "--pred", env.tmp / "eval")
    env.error(r"metrics\.json: no 'results' key.*this is a metrics file; evaluate writes the submission as "
              r".*eval/submission\.json", "evaluate-json", "--gt", gt, "--pred", env.tmp / "eval" / "metrics.json")


@row("demo --out a file, or a path below a file: 'cannot write there (File exists)', naming neither the file "
            "nor the cause; the demo takes the output-folder check of the other jobs")
def row_demo_out_a_file(env):
    (env.tmp / "notes.txt").write_text("mine")
    env.error(r"--out .*notes\.txt: is a file, not a folder", "demo", "--out", env.tmp / "notes.txt", "--cache",
              env.tmp / "cache")
    env.error(r"--out .*notes\.txt/run: .*notes\.txt is a file", "demo", "--out", env.tmp / "notes.txt" / "run",
              "--cache", env.tmp / "cache")
    assert (env.tmp / "notes.txt").read_text() == "mine"


def _strict_json(text: str):
    """``text`` read as standard JSON: ``NaN`` / ``Infinity`` (Python's extension) refused, as jq, JavaScript and Go
    refuse them."""
    def refuse(constant):
        raise AssertionError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


@row("metrics.json (evaluate, evaluate-json) and log.jsonl held NaN (a flicker rate with no pairs, the "
            "raster AP of a class with no GT): not JSON, jq and JavaScript refuse the file; now null. A NaN score "
            "given to write_submission is refused (null would read back as the default confidence 1.0)")
def row_json_outputs_hold_no_nan(env):
    from instagram_hdmap.evaluation.io import write_submission

    run = env.tmp / "run"
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={run}", "train.epochs=1", "train.checkpoint_every=0")
    assert rc == 0, err[-2000:]
    lines = (run / "log.jsonl").read_text().splitlines()
    assert lines and all(isinstance(_strict_json(ln), dict) for ln in lines)
    assert _strict_json(lines[-1])["val"]["consistency"]["flicker_detected_mean"] is None  # a random model: no pairs
    rc, _, err = env.cli("evaluate", env.yaml, "--checkpoint", env.ckpt, "--out", env.tmp / "eval")
    assert rc == 0, err[-2000:]
    _strict_json((env.tmp / "eval" / "submission.json").read_text())
    metrics = _strict_json((env.tmp / "eval" / "metrics.json").read_text())
    assert metrics["consistency"]["flicker_detected_mean"] is None
    line = {"pts": [[0.0, 1.0], [5.0, 1.0]], "label": 0, "score": 0.5}
    write_submission(env.tmp / "gt.json", {"a": [{"pts": line["pts"], "label": 0}]}, {"ground_truth": True})
    write_submission(env.tmp / "pred.json", {"a": [line]})
    rc, out, err = env.cli("evaluate-json", "--pred", env.tmp / "pred.json", "--gt", env.tmp / "gt.json", "--protocol",
                           "raster", "--out", env.tmp / "m.json")
    assert rc == 0 and "nan" in out, err[-2000:]  # printed as nan on the terminal
    metrics = _strict_json((env.tmp / "m.json").read_text())
    assert metrics["AP_class"]["divider"] == 1.0 and metrics["AP_class"]["boundary"] is None and metrics["mAP"] is None
    with pytest.raises(ValueError, match=r"sample 'a': a polyline's score is nan .*scores must be finite"):
        write_submission(env.tmp / "nan.json", {"a": [{**line, "score": float("nan")}]})
    assert not (env.tmp / "nan.json").exists()


@row("the reader of the output went away (`evaluate-json ... --out m.json | head -1`, `train ... 2>&1 | head`, "
            "with PYTHONUNBUFFERED=1 as in many containers): the first message after it stopped the job, exit 141 "
            "with m.json never written, a training stopped before its first step; now the job goes on, writes its "
            "files and exits 141")
def row_output_reader_gone_job_goes_on(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "PYTHONUNBUFFERED": "1"}
    gt, pred = env.tmp / "gt.json", env.tmp / "pred.json"
    line = [[0.0, 1.0], [5.0, 1.0]]
    gt.write_text(json.dumps({"meta": {"ground_truth": True}, "results": {"a": [{"pts": line, "type": 0}]}}))
    pred.write_text(json.dumps({"results": {"a": [{"pts": line, "type": 0, "confidence_level": 0.5}]}}))
    jobs = [(["evaluate-json", "--pred", pred, "--gt", gt, "--out", env.tmp / "m.json"], subprocess.PIPE),
            (["train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=1", "train.checkpoint_every=0"],
             subprocess.STDOUT)]  # 2>&1: the progress bar's stream has no reader either
    for argv, stderr in jobs:
        p = subprocess.Popen([sys.executable, "-m", "instagram_hdmap.cli", *map(str, argv)], stdout=subprocess.PIPE,
                             stderr=stderr, env=env_vars)
        p.stdout.close()  # the reader is gone before the first line (`| head -0`)
        err = p.stderr.read().decode() if p.stderr else ""
        assert p.wait(timeout=300) == 141, err[-2000:]
        assert "Traceback" not in err, err[-2000:]
    assert json.loads((env.tmp / "m.json").read_text())["mAP"] == pytest.approx(1 / 3)  # divider 1, the others 0
    assert (env.tmp / "run" / "last.pt").is_file() and (env.tmp / "run" / "log.jsonl").read_text().count("\n") == 1


@row("stderr closed at the start (`2>&-`, a launcher that closes it): the first progress bar wrote to None, a "
            "raw AttributeError nobody could see, exit 1, nothing written (export-gt, evaluate, train, synth); now "
            "the messages are dropped and the job runs")
def row_standard_error_closed(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    argv = ["export-gt", str(env.yaml), "--out", str(env.tmp / "gt.json")]
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE, env=env_vars,
                       preexec_fn=lambda: os.close(2), timeout=300)
    assert p.returncode == 0 and b"wrote" in p.stdout, p.stdout[-2000:]
    assert json.loads((env.tmp / "gt.json").read_text())["results"]


@row("train / evaluate with stderr in a file (`2> log`, nohup, not a terminal): the progress bar was drawn "
            "twice a step, each drawing a carriage-return line of ~200 bytes: megabytes a day, one `tail` line per "
            "epoch; now drawn at most once a minute off a terminal")
def row_progress_bar_in_a_log_file(env):
    rc, _, err = env.cli("train", env.yaml, f"train.out_dir={env.tmp / 'run'}", "train.epochs=1",
                         "train.checkpoint_every=0", "train.log_every=1")
    assert rc == 0, err[-2000:]
    assert err.count("epoch 0:") <= 2, err  # the bar's start and (a run longer than a minute) its refreshes


@row("a non-ASCII path on a terminal that is not UTF-8 (PYTHONIOENCODING=ascii, a Windows console): export-gt "
            "wrote the file, then its 'wrote ...' line crashed (UnicodeEncodeError traceback, exit 1); now the "
            "letter is escaped and the exit status is 0")
def row_non_ascii_path_on_an_ascii_terminal(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "PYTHONIOENCODING": "ascii"}
    out = env.tmp / "gt \u00e4.json"
    p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", "export-gt", str(env.yaml), "--out", str(out)],
                       capture_output=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and b"Traceback" not in p.stderr, p.stderr[-2000:]
    assert b"gt \\xe4.json" in p.stdout and out.is_file(), p.stdout


@row("train with stderr on a full disk (`2> log`, the log's disk full): the progress bar's next write stopped "
            "the training, exit 1, no checkpoint and no word anywhere; now stderr's messages are dropped, the "
            "training ends and a note on stdout says the messages were lost")
def row_standard_error_on_a_full_disk(env):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    argv = ["train", str(env.yaml), f"train.out_dir={env.tmp / 'run'}", "train.epochs=1", "train.checkpoint_every=0"]
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "instagram_hdmap.cli", *argv], stdout=subprocess.PIPE, stderr=full,
                           text=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and (env.tmp / "run" / "last.pt").is_file(), (p.returncode, p.stdout[-2000:])
    assert "note: the standard error could not be written from some point on (No space left on device)" in p.stdout


@row("export-gt / evaluate-json --out /dev/stdout (what the refusal of --out - advises, for `| jq`): refused "
            "('cannot write /proc/PID/fd/pipe:[N]', on a terminal 'cannot write /dev/pts/0'); --out /dev/null or "
            "another device run as root: the device node was replaced by a regular file (a temporary renamed over "
            "it); now a terminal, pipe or device is written directly, the report goes to stderr")
def row_output_to_a_pipe_or_device(env):
    env_vars = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    cli = [sys.executable, "-m", "instagram_hdmap.cli"]
    p = subprocess.run([*cli, "export-gt", str(env.yaml), "--out", "/dev/stdout"], capture_output=True, text=True,
                       env=env_vars, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    gt = json.loads(p.stdout)  # the JSON alone: "wrote ..." went to stderr
    assert gt["meta"]["ground_truth"] and gt["results"] and "wrote /dev/stdout" in p.stderr
    (env.tmp / "gt.json").write_text(p.stdout)
    p = subprocess.run([*cli, "evaluate-json", "--pred", str(env.tmp / "gt.json"), "--gt", str(env.tmp / "gt.json"),
                        "--out", "/dev/stdout"], capture_output=True, text=True, env=env_vars, timeout=300)
    assert p.returncode == 0 and "mAP" in p.stderr, p.stderr[-2000:]
    assert json.loads(p.stdout)["AP_class"]["divider"] == 1.0
    if os.geteuid() == 0:  # a device node of its own (as /dev/null is): it stays one
        import importlib.util
        import stat

        device = env.tmp / "null"
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        rc, out, err = env.cli("export-gt", env.yaml, "--out", device)
        assert rc == 0 and stat.S_ISCHR(device.stat().st_mode), (err[-2000:], device.stat())
        if importlib.util.find_spec("onnx") is not None:  # it reads its file back: a device is refused first
            env.error(r"--out .*null: a terminal, pipe or device; export-onnx reads the file back", "export-onnx",
                      env.yaml, "--checkpoint", env.ckpt, "--out", device)
            assert stat.S_ISCHR(device.stat().st_mode)


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_outputs(case, env):
    case.run(env)
