"""The Argoverse 2 path is an optional extra: without it, asking for AV2 is a one-line error that names
the extra, and the nuScenes path never imports ``av2`` (these tests run with or without the extra)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from instagram_hdmap.cli import main
from instagram_hdmap.config import UserError, load_config


@pytest.fixture
def no_av2(monkeypatch):
    """Make ``import av2`` (and its submodules) fail as if the extra were not installed."""
    for name in [m for m in sys.modules if m == "av2" or m.startswith("av2.")] + ["av2"]:
        monkeypatch.setitem(sys.modules, name, None)


def test_missing_extra_is_a_one_line_error(no_av2, tmp_path, capsys):
    from instagram_hdmap.data import build_dataset

    cfg = load_config(None, ["data.dataset=av2", f"data.dataroot={tmp_path}"])
    with pytest.raises(UserError, match=r'data.dataset=av2 needs .*extra .av2.: pip install -e "\.\[av2\]"'):
        build_dataset(cfg, "train")
    rc = main(["synth", "--format", "av2", "--out", str(tmp_path / "w"), "--scenes-train", "1", "--scenes-val", "0"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and 'pip install -e ".[av2]"' in err
    assert not (tmp_path / "w").exists()


def test_nuscenes_path_never_imports_av2(tiny_world, world_overrides):
    overrides = [*world_overrides(tiny_world), "data.image_size=[64,176]"]
    code = (
        "import sys\n"
        "from instagram_hdmap import cli, demo, predict, train  # noqa: F401\n"
        "from instagram_hdmap.config import load_config\n"
        "from instagram_hdmap.data import build_dataset\n"
        f"cfg = load_config(None, {overrides!r})\n"
        "sample = build_dataset(cfg, 'train')[0]\n"
        "loaded = sorted(m for m in sys.modules if m == 'av2' or m.startswith('av2.'))\n"
        "assert not loaded, loaded\n"
        "print('ok', sample['sample_token'])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.startswith("ok "), out.stderr[-2000:]
