"""A config too big for the machine is refused before the work, naming the key; one that fits runs.

The memory estimate (resources.py) is checked against a step's measured peak, the refusals run the CLI as a
user would (one line, exit 2, within seconds and a small fraction of the memory the config would take), and
the data workers are fitted to the cores.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from bad_inputs.support import row, table
from instagram_hdmap import resources
from instagram_hdmap.config import UserError, load_config

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "configs" / "synthetic" / "tiny.yaml"
PAPER_B4 = REPO / "configs" / "paper" / "table1_b4_lss_128x352.yaml"
GB = 1e9


# the CLI in this child, which writes its own peak memory (VmHWM) at exit: getrusage's figures for a child carry
# the parent's, and this test process can hold more than the 3 GB bound by itself
_CLI_WITH_PEAK = """import atexit, os, sys
from instagram_hdmap import resources
from instagram_hdmap.cli import main
atexit.register(lambda: open(os.environ["PEAK_FILE"], "w").write(str(resources.peak_resident_bytes())))
sys.argv[0] = "instagram-hdmap"
sys.exit(main())
"""


def _cli(tmp_path, *argv, timeout=60):
    """The CLI in a fresh process: (exit code, stderr lines, wall seconds, peak resident bytes of the child)."""
    peak_file = tmp_path / "peak"
    start = time.monotonic()
    p = subprocess.run([sys.executable, "-c", _CLI_WITH_PEAK, *map(str, argv)], capture_output=True, text=True,
                       timeout=timeout, cwd=tmp_path, env={**os.environ, "PEAK_FILE": str(peak_file)})
    wall = time.monotonic() - start
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert peak_file.is_file(), f"the child wrote no peak (exit {p.returncode}):\n{p.stderr[-3000:]}"
    return p.returncode, lines, wall, int(peak_file.read_text())


@row("a typo in a size (N = 10^8, a batch of 200000, 8192 x 8192 images, LSS depth bins of 1 cm) is one line "
     "naming the key, exit 2, within 30 s and 3 GB, before the run folder is made")
def row_size_typo_refused_in_seconds(env):
    for override, key in [("model.gnn.num_vertices=100000000", "model.gnn.num_vertices"),
                          ("train.batch_size=200000", "train.batch_size"),
                          ("data.image_size=[8192,8192]", "data.image_size"),
                          ("model.view_transform.depth_bound=[1.0,1000.0,0.01]", "model.view_transform.depth_bound")]:
        run = env.tmp / key
        rc, lines, wall, peak = _cli(env.tmp, "train", TINY, override, f"train.out_dir={run}")
        assert rc == 2, lines
        error = [ln for ln in lines if "error:" in ln]
        assert len(error) == 1 and not any("Traceback" in ln for ln in lines), lines
        assert f"{key}=" in error[0] and "one training step needs ~" in error[0] and "available" in error[0], error
        assert wall < 30, f"{override}: refused after {wall:.1f} s"
        assert 0 < peak < 3 * GB, f"{override}: the refusal itself took {peak / GB:.1f} GB"
        assert not run.exists(), f"{override}: the run folder was made before the refusal"


@row("a grid far too fine (grid.resolution=0.001) names grid.resolution: raise it")
def row_grid_too_fine(env):
    cfg = load_config(TINY, ["grid.resolution=0.001"])  # the key is found from the largest term
    with pytest.raises(UserError, match=r"^grid\.resolution=0\.001: one training step needs .*raise it"):
        resources.check_fits(cfg, "train")


@row("an eval.batch_size too big is named by evaluate (training does not read it)")
def row_eval_batch_too_big(env):
    cfg = load_config(TINY, ["eval.batch_size=100000"])
    resources.check_fits(cfg, "train")
    with pytest.raises(UserError, match=r"^eval\.batch_size=100000: one inference batch needs"):
        resources.check_fits(cfg, "infer")


@row("model-summary prints the memory of a training step and of an inference batch beside what is available")
def row_model_summary_prints_the_estimate(env):
    rc, out, _ = env.cli("model-summary", TINY)
    assert rc == 0
    assert "memory of one training step (train.batch_size=" in out and "memory of one inference batch" in out
    assert "memory available:" in out


@row("model.gnn.num_vertices above the grid's cells is a note")
def row_more_vertices_than_cells(env):
    rc, out, _ = env.cli("model-summary", TINY, "model.gnn.num_vertices=1000")
    assert rc == 0 and "model.gnn.num_vertices=1000 is more than the grid's 128 cells" in out


@row("the shipped CPU configs (demo, tiny, temporal, AV2 demo) are not refused: each fits a few GB")
def row_shipped_cpu_configs_fit(env):
    for config in ["configs/synthetic/demo.yaml", "configs/synthetic/tiny.yaml", "configs/temporal/synthetic.yaml",
                   "configs/av2/synthetic_demo.yaml"]:
        cfg = load_config(REPO / config)
        assert resources.check_fits(cfg, "train") < 3 * GB, config
        assert resources.check_fits(cfg, "infer") < 3 * GB, config


PAPER_CONFIGS = sorted(p.relative_to(REPO).as_posix() for p in (REPO / "configs").glob("*/table*.yaml"))


@row("every paper config at its batch is not refused on one 80 GB GPU (the 128 x 352 rows fit it outright), and is "
     "on a GPU with 0.5 GB free, naming the GPU")
def row_paper_configs_fit_an_80_gb_gpu(env):
    monkeypatch = env.monkeypatch
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "a mocked 80 GB GPU")
    for config in PAPER_CONFIGS:
        monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (79 * GB, 80 * GB))
        cfg = load_config(REPO / config)
        need = resources.check_fits(cfg, "train", torch.device("cuda"))
        assert 1 * GB < need < (79 if "128x352" in config else 79 * resources.REFUSE_OVER) * GB, config
        monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (0.5 * GB, 80 * GB))
        with pytest.raises(UserError, match="a mocked 80 GB GPU has 0.5 GB available"):
            resources.check_fits(cfg, "train", torch.device("cuda"))


@row("under a cgroup memory limit, the limit (plus what the process holds) is the memory available")
def row_cgroup_limit(env):
    env.monkeypatch.setattr(resources, "_cgroup_room", lambda: 2 * GB)
    have, what = resources.memory_available()
    held = resources.resident_bytes()
    assert what == "this process's cgroup allows" and 0 < held and abs(have - (2 * GB + held)) < 0.1 * GB
    cfg = load_config(PAPER_B4, ["train.batch_size=4"])
    with pytest.raises(UserError, match="this process's cgroup allows"):
        resources.check_fits(cfg, "train")


@row("the estimate is within a factor of two of a measured training step (benchmarks/train_speed.py's step, in a "
     "fresh process: its peak RSS; the same config without data workers)")
def row_estimate_against_a_measured_step(env):
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "train_speed.py"), "--one", str(TINY), "--batch", "4",
                        "--grad-checkpoint", "off", "--steps", "1", "--warmup", "1"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT"))
    measured = json.loads(line.split(" ", 1)[1])["peak_rss_gb"] * GB
    cfg = load_config(TINY, ["train.batch_size=4", "model.backbone.grad_checkpoint=false", "data.num_workers=0"])
    estimate = resources.estimate(cfg, "train")
    assert measured / 2 < estimate < measured * 2, (estimate / GB, measured / GB)


@row("a size beyond any sane meaning (model.gnn.heads=1000, 9000-pixel images, 100000 channels) is refused by the "
     "key's range when the config loads")
def row_size_beyond_its_range(env):
    for override, message in [("model.gnn.heads=1000", "'model.gnn.heads' must be in [1, 64], got 1000"),
                              ("data.image_size=[9000,352]", "'data.image_size[0]' must be in [1, 8192], got 9000"),
                              ("model.bev_heads.channels=100000",
                               "'model.bev_heads.channels' must be in [1, 8192], got 100000")]:
        with pytest.raises(UserError, match=re.escape(message)):
            load_config(TINY, [override])


@row("a config within the estimate's error of the memory (up to 1.3x over it) starts, with a note that it may run out "
     "of memory; beyond that it is refused")
def row_close_to_the_memory_is_a_note(env):
    cfg = load_config(TINY)
    need = resources.estimate(cfg, "train")
    for have, refused in [(need / 1.1, False), (need / 1.5, True)]:
        env.monkeypatch.setattr(resources, "memory_available", lambda device=None, have=have: (have, "mocked, with"))
        env.capsys.readouterr()
        if refused:
            with pytest.raises(UserError, match="mocked, with"):
                resources.check_fits(cfg, "train")
        else:
            assert resources.check_fits(cfg, "train") == need
            assert "it may run out of memory" in env.capsys.readouterr().out


@row("data.num_workers above the usable cores or the split's samples is lowered to them, with one note per setting")
def row_data_workers_fit_the_cores_and_the_samples(env):
    env.monkeypatch.setattr(resources, "usable_cores", lambda: 2)
    env.monkeypatch.setattr(resources, "_noted", set())
    env.capsys.readouterr()
    assert resources.data_workers(4) == 2
    assert resources.data_workers(4, samples=100) == 2  # the same setting: noted once
    assert resources.data_workers(2, samples=1) == 1
    assert resources.data_workers(0) == 0 and resources.data_workers(1, samples=5) == 1
    out = env.capsys.readouterr().out.splitlines()
    assert out == ["note: data.num_workers=4 lowered to 2: this process may use 2 CPU cores",
                   "note: data.num_workers=2 lowered to 1: the split has 1 sample(s)"], out


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_config_too_big(case, env):
    case.run(env)
