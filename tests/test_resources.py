"""A config that cannot fit the machine is refused before the work, naming the key; one that fits runs.

The memory estimate (resources.py) is checked against a step's measured peak, the refusals run the CLI as a
user would (one line, exit 2, within seconds and a small fraction of the memory the config would take), and
the data workers are fitted to the cores.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from instagram_hdmap import resources
from instagram_hdmap.cli import main
from instagram_hdmap.config import UserError, load_config

REPO = Path(__file__).resolve().parents[1]
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
    return p.returncode, lines, wall, int(peak_file.read_text())


@pytest.mark.parametrize("override, key", [
    ("model.gnn.num_vertices=100000000", "model.gnn.num_vertices"),
    ("train.batch_size=200000", "train.batch_size"),
    ("data.image_size=[8192,8192]", "data.image_size"),
    ("model.view_transform.depth_bound=[1.0,1000.0,0.01]", "model.view_transform.depth_bound"),
])
def test_an_oversized_training_is_one_line_naming_the_key(tmp_path, override, key):
    rc, lines, wall, peak = _cli(tmp_path, "train", TINY, override, f"train.out_dir={tmp_path / 'run'}")
    assert rc == 2, lines
    error = [ln for ln in lines if "error:" in ln]
    assert len(error) == 1 and not any("Traceback" in ln for ln in lines), lines
    assert f"{key}=" in error[0] and "one training step needs ~" in error[0] and "available" in error[0], error
    assert wall < 30, f"refused after {wall:.1f} s"
    assert 0 < peak < 3 * GB, f"the refusal itself took {peak / GB:.1f} GB"
    assert not (tmp_path / "run").exists(), "the run folder was made before the refusal"


def test_a_grid_too_fine_names_its_resolution(tmp_path):
    """The default resolution does not divide the tiny grid's extents: the key is found from the largest term."""
    cfg = load_config(TINY, ["grid.resolution=0.001"])
    with pytest.raises(UserError, match=r"^grid\.resolution=0\.001: one training step needs .*raise it"):
        resources.check_fits(cfg, "train")


def test_an_oversized_evaluation_batch_names_eval_batch_size(monkeypatch):
    cfg = load_config(TINY, ["eval.batch_size=100000"])
    resources.check_fits(cfg, "train")  # training does not read it
    with pytest.raises(UserError, match=r"^eval\.batch_size=100000: one inference batch needs"):
        resources.check_fits(cfg, "infer")


def test_model_summary_prints_the_estimate(capsys):
    assert main(["model-summary", str(TINY)]) == 0
    out = capsys.readouterr().out
    assert "memory of one training step (train.batch_size=" in out and "memory of one inference batch" in out
    assert "memory available:" in out


def test_more_vertices_than_cells_is_a_note(capsys):
    assert main(["model-summary", str(TINY), "model.gnn.num_vertices=1000"]) == 0
    assert "model.gnn.num_vertices=1000 is more than the grid's 128 cells" in capsys.readouterr().out


@pytest.mark.parametrize("config", ["configs/synthetic/demo.yaml", "configs/synthetic/tiny.yaml",
                                    "configs/temporal/synthetic.yaml", "configs/av2/synthetic_demo.yaml"])
def test_the_shipped_cpu_configs_fit_this_machine(config):
    """Nothing the machine can run is refused: the CPU-sized configs fit a few GB."""
    cfg = load_config(REPO / config)
    assert resources.check_fits(cfg, "train") < 3 * GB
    assert resources.check_fits(cfg, "infer") < 3 * GB


PAPER_CONFIGS = sorted(p.relative_to(REPO).as_posix() for p in (REPO / "configs").glob("*/table*.yaml"))


@pytest.mark.parametrize("config", PAPER_CONFIGS)
def test_the_paper_configs_fit_an_80_gb_gpu(monkeypatch, config):
    """The paper's batch of each Table row is not refused on one 80 GB GPU (its free memory mocked); the 128 x 352
    rows fit it outright."""
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (79 * GB, 80 * GB))
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "a mocked 80 GB GPU")
    cfg = load_config(REPO / config)
    need = resources.check_fits(cfg, "train", torch.device("cuda"))
    assert 1 * GB < need < (79 if "128x352" in config else 79 * resources.REFUSE_OVER) * GB
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (0.5 * GB, 80 * GB))
    with pytest.raises(UserError, match="a mocked 80 GB GPU has 0.5 GB available"):
        resources.check_fits(cfg, "train", torch.device("cuda"))


def test_a_cgroup_limit_is_the_memory_available(monkeypatch):
    monkeypatch.setattr(resources, "_cgroup_room", lambda: 2 * GB)
    have, what = resources.memory_available()
    held = resources.resident_bytes()
    assert what == "this process's cgroup allows" and 0 < held and abs(have - (2 * GB + held)) < 0.1 * GB
    cfg = load_config(PAPER_B4, ["train.batch_size=4"])
    with pytest.raises(UserError, match="this process's cgroup allows"):
        resources.check_fits(cfg, "train")


def test_the_estimate_is_within_a_factor_two_of_a_measured_step(tmp_path):
    """One training step of the tiny model (benchmarks/train_speed.py's step, in a fresh process: its peak RSS) against
    the estimate of the same config without data workers (the measured process has none)."""
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "train_speed.py"), "--one", str(TINY), "--batch", "4",
                        "--grad-checkpoint", "off", "--steps", "1", "--warmup", "1"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT"))
    measured = json.loads(line.split(" ", 1)[1])["peak_rss_gb"] * GB
    cfg = load_config(TINY, ["train.batch_size=4", "model.backbone.grad_checkpoint=false", "data.num_workers=0"])
    estimate = resources.estimate(cfg, "train")
    assert measured / 2 < estimate < measured * 2, (estimate / GB, measured / GB)


def test_data_workers_fit_the_cores_and_the_samples(monkeypatch, capsys):
    monkeypatch.setattr(resources, "usable_cores", lambda: 2)
    monkeypatch.setattr(resources, "_noted", set())
    assert resources.data_workers(4) == 2
    assert resources.data_workers(4, samples=100) == 2  # the same setting: noted once
    assert resources.data_workers(2, samples=1) == 1
    assert resources.data_workers(0) == 0 and resources.data_workers(1, samples=5) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == ["note: data.num_workers=4 lowered to 2: this process may use 2 CPU cores",
                   "note: data.num_workers=2 lowered to 1: the split has 1 sample(s)"], out
