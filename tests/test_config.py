"""Config system: defaults, YAML overrides with _base_, CLI overrides, round trip, clear errors."""

import math
from pathlib import Path

import pytest
import torch

from instagram_hdmap.config import (
    ConfigError,
    ExperimentConfig,
    config_to_dict,
    diff_configs,
    load_config,
    parse_overrides,
    save_config,
)
from instagram_hdmap.geometry import BEVGrid

REPO = Path(__file__).resolve().parents[1]


def test_defaults_are_the_paper_main_setting():
    cfg = load_config()
    assert cfg.grid.xbound == (-30.0, 30.0) and cfg.grid.ybound == (-15.0, 15.0)
    assert cfg.grid.resolution == 0.15 and cfg.grid.cell_size == 8
    assert cfg.model.gnn.num_vertices == 400 and cfg.model.gnn.layers == 7
    assert (cfg.loss.vertex_weight, cfg.loss.distance_weight) == (1.0, 1.0)
    assert (cfg.loss.adjacency_weight, cfg.loss.class_weight) == (5e-3, 1e-2)


def test_yaml_base_and_cli_overrides(tmp_path):
    (tmp_path / "base.yaml").write_text("model:\n  gnn:\n    layers: 3\ngrid:\n  resolution: 0.3\n")
    (tmp_path / "exp.yaml").write_text("_base_: base.yaml\nmodel:\n  gnn:\n    num_vertices: 600\n")
    cfg = load_config(tmp_path / "exp.yaml", ["model.gnn.layers=9", "data.image_size=[256,704]"])
    assert cfg.model.gnn.layers == 9  # CLI beats the YAML chain
    assert cfg.model.gnn.num_vertices == 600  # the file beats its base
    assert cfg.grid.resolution == 0.3  # the base beats the defaults
    assert cfg.data.image_size == (256, 704) and isinstance(cfg.data.image_size, tuple)


def test_round_trip_save_load_is_identical(tmp_path):
    cfg = load_config(None, ["model.gnn.embedding=pe", "train.amp=bf16", "data.splits_file=s.json"])
    save_config(cfg, tmp_path / "config.yaml")
    again = load_config(tmp_path / "config.yaml")
    assert again == cfg
    assert config_to_dict(again) == config_to_dict(cfg)
    assert diff_configs(cfg, again) == []


def test_unknown_key_names_it_and_lists_valid_keys():
    with pytest.raises(ConfigError) as e:
        load_config(None, ["model.gnn.layer=9"])
    msg = str(e.value)
    assert "model.gnn.layer" in msg and "layers" in msg and "num_vertices" in msg


def test_unknown_key_in_yaml(tmp_path):
    (tmp_path / "bad.yaml").write_text("train:\n  learning_rate: 0.1\n")
    with pytest.raises(ConfigError, match=r"train\.learning_rate.*valid keys.*lr"):
        load_config(tmp_path / "bad.yaml")


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.gnn.layers=seven", "model.gnn.layers"),
        ("model.gnn.layers=7.5", "model.gnn.layers"),
        ("train.lr=fast", "train.lr"),
        ("data.augment=1", "data.augment"),
        ("data.image_size=[128]", "data.image_size"),
        ("model.view_transform.kind=bev", "model.view_transform.kind"),
    ],
)
def test_wrong_type_names_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [override])


def test_section_given_a_scalar_is_an_error():
    with pytest.raises(ConfigError, match="model.gnn"):
        load_config(None, ["model.gnn=3"])


def test_int_is_accepted_for_float_and_normalised():
    cfg = load_config(None, ["train.lr=1"])
    assert cfg.train.lr == 1.0 and isinstance(cfg.train.lr, float)


def test_cross_field_checks():
    with pytest.raises(ConfigError, match="model.gnn.num_vertices"):
        load_config(None, ["model.gnn.num_vertices=0"])
    with pytest.raises(ConfigError, match="eval.thresholds"):
        load_config(None, ["eval.thresholds=[0.5,0]"])
    with pytest.raises(ConfigError, match="grid.xbound"):
        load_config(None, ["grid.xbound=[30,-30]"])


@pytest.mark.parametrize("overrides, message", [
    (["model.gnn.decoder=hungarian"], r"model\.gnn\.decoder.*'greedy', 'mutual'"),
    (["model.gnn.match_threshold=0"], r"match_threshold.*\(0, 1\)"),
    (["model.gnn.match_threshold=1.5"], r"match_threshold.*\(0, 1\)"),
    (["model.gnn.max_edge_m=0"], r"max_edge_m.*> 0"),
    (["model.gnn.decoder=mutual", "model.gnn.max_edge_m=2.5"], r"max_edge_m.*greedy and classwise decoders"),
    (["model.gnn.class_min_prob=1"], r"class_min_prob.*\[0, 1\)"),
    (["model.gnn.min_vertices=1"], r"min_vertices.*>= 2"),
])
def test_decoder_settings_are_checked(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, overrides)


def test_override_syntax_error():
    with pytest.raises(ConfigError, match="key.sub=value"):
        parse_overrides(["model.gnn.layers"])


def test_missing_file_and_cycle(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    (tmp_path / "a.yaml").write_text("_base_: b.yaml\n")
    (tmp_path / "b.yaml").write_text("_base_: a.yaml\n")
    with pytest.raises(ConfigError, match="includes itself"):
        load_config(tmp_path / "a.yaml")


def test_every_shipped_config_loads():
    files = sorted((REPO / "configs").rglob("*.yaml"))
    for f in files:
        cfg = load_config(f)
        BEVGrid.from_config(cfg.grid)  # the grid is consistent
    assert isinstance(ExperimentConfig(), ExperimentConfig)


def test_exponent_floats_on_the_command_line():
    assert load_config(None, ["train.lr=3e-3"]).train.lr == 0.003
    with pytest.raises(ConfigError, match="train.amp"):
        load_config(None, ["train.amp=1e3"])  # a number is still not one of the choices


def _numeric_fields(obj, prefix=""):
    import dataclasses
    import typing

    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numeric_fields(value, f"{prefix}{f.name}.")
        elif any(t in (int, float) for t in (hints[f.name], *typing.get_args(hints[f.name]),
                                              *[a for arg in typing.get_args(hints[f.name])
                                                for a in typing.get_args(arg)])):
            yield f"{prefix}{f.name}", f


def test_every_numeric_key_declares_its_range():
    """A numeric key is defined with config.bounded(default, ge=..., gt=..., le=..., lt=...), so that
    validate_config checks its range: a new key gets the check by declaring it, never by a list."""
    fields = dict(_numeric_fields(ExperimentConfig()))
    assert "train.lr" in fields and "grid.xbound" in fields and "model.gnn.max_edge_m" in fields
    undeclared = [k for k, f in fields.items() if "range" not in f.metadata]
    assert not undeclared, f"declare the valid range of {undeclared} with config.bounded(...)"


@pytest.mark.parametrize("override, message", [
    ("train.lr=.nan", r"'train\.lr': expected a finite number"),
    ("train.lr=.inf", r"'train\.lr': expected a finite number"),
    ("model.gnn.max_edge_m=.nan", r"'model\.gnn\.max_edge_m': expected a finite number"),
    ("data.aug_scale=[1.0,.nan]", r"'data\.aug_scale\[1\]': expected a finite number"),
    ("train.lr=0", r"'train\.lr' must be > 0, got 0\.0"),
    ("train.seed=-1", r"'train\.seed' must be in \[0, 4294967296\)"),
    ("data.image_size=[0,352]", r"'data\.image_size\[0\]' must be in \[1, 8192\], got 0"),
    ("model.gnn.conf_threshold=1", r"'model\.gnn\.conf_threshold' must be in \[0, 1\)"),
    ("data.aug_scale=[1.1,0.9]", r"data\.aug_scale.*low <= high"),
    ("data.classes=[boundary,ped_crossing,divider]", r"data\.classes.*order"),
])
def test_ranges_and_finiteness_name_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_a_key_written_twice_in_a_yaml_mapping_is_an_error(tmp_path):
    (tmp_path / "twice.yaml").write_text("train:\n  lr: 0.1\n  epochs: 3\n  lr: 0.2\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: key 'lr' is written twice .*lines 2 and 4"):
        load_config(tmp_path / "twice.yaml")
    (tmp_path / "merge.yaml").write_text("a: &a {lr: 0.1}\ntrain:\n  <<: *a\n  lr: 0.2\n")  # a merge key may repeat
    with pytest.raises(ConfigError, match=r"unknown config key 'a'"):  # (and then 'a' is unknown)
        load_config(tmp_path / "merge.yaml")


def test_yaml_reads_exponent_floats_and_base_must_be_a_path(tmp_path):
    (tmp_path / "e.yaml").write_text("train:\n  lr: 1e-3\n  weight_decay: 1E-7\n")
    cfg = load_config(tmp_path / "e.yaml")
    assert (cfg.train.lr, cfg.train.weight_decay) == (1e-3, 1e-7)  # YAML 1.1 would read strings
    (tmp_path / "b.yaml").write_text("_base_: [e.yaml]\n")
    with pytest.raises(ConfigError, match=r"'_base_' must name one YAML file"):
        load_config(tmp_path / "b.yaml")


PAPER = sorted((REPO / "configs" / "paper").glob("*.yaml"))


def test_every_paper_config_carries_the_official_settings():
    """configs/paper/*: the official code's values where our defaults differ (benchmarks/README.md,
    "The paper configs against the official code")."""
    for f in PAPER:
        cfg = load_config(f)
        name = f.name
        assert cfg.eval.protocol == "raster" and cfg.eval.also_protocols == ("vector",), name
        assert cfg.eval.thresholds == (0.5, 1.0, 1.5) and cfg.eval.rank_by == "ascending", name
        assert cfg.model.backbone.weights == "imagenet" and not cfg.model.backbone.from_scratch, name
        assert cfg.model.gnn.nms == "superpoint" and cfg.model.gnn.nms_radius == cfg.grid.cell_size // 2, name
        assert cfg.model.gnn.decoder == "official" and cfg.model.gnn.match_threshold == 0.1, name
        assert (cfg.loss.match_space, cfg.loss.class_targets, cfg.loss.match_dist) == ("patch", "nearest", 1.5), name
        assert cfg.data.image_fit == "stretch" and cfg.data.sample_dist == 1.5 and not cfg.data.augment, name
        assert cfg.model.view_transform.bev_downsample == 1, name
        assert (cfg.train.epochs, cfg.train.lr, cfg.train.lr_step, cfg.train.lr_gamma) == (30, 1e-3, 10, 0.1), name
        assert (cfg.train.weight_decay, cfg.train.grad_clip, cfg.data.dt_clip) == (1e-7, 5.0, 10.0), name
        vd = name.startswith("fig7_vd")
        assert cfg.model.bev_heads.distance_head is not vd, name  # the official VD variant has no DT head
        assert (cfg.model.gnn.embedding, cfg.model.gnn.vd_sampling) == (("pe+vd", "cell") if vd else
                                                                       (cfg.model.gnn.embedding, "vertex")), name


def _farthest_seen_depth(cfg) -> float:
    """Over the BEV cell centres a nuScenes camera sees (inside its 1600 x 900 image, in front of it), the
    largest distance along the optical axis to the nearest camera that sees it (LSS's depth)."""
    from instagram_hdmap.benchmark import nuscenes_like_rig

    rig = nuscenes_like_rig((128, 352))
    grid = BEVGrid.from_config(cfg.grid)
    centres = torch.from_numpy(grid.cell_centres_m().reshape(-1, 2)).float()
    pts = torch.cat([centres, torch.zeros(len(centres), 1)], 1)
    best = torch.full((len(pts),), float("inf"))
    for K, R, t in zip(rig["intrinsics"], rig["cam_to_ego_rot"], rig["cam_to_ego_trans"]):
        cam = (pts - t) @ R
        uv = cam @ K.T
        u, v = uv[:, 0] / cam[:, 2], uv[:, 1] / cam[:, 2]
        seen = (cam[:, 2] > 0) & (u >= 0) & (u < 1600) & (v >= 0) & (v < 900)
        best = torch.where(seen, torch.minimum(best, cam[:, 2]), best)
    return float(best[torch.isfinite(best)].max())


def test_lss_depth_bins_reach_every_bev_cell_the_cameras_see():
    """No BEV cell beyond the LSS depth range: for every paper config with LSS, each cell a camera of a
    nuScenes rig sees lies within the last depth bin of it (the 100 m x 100 m range of Table II needs
    bins to ~73 m, the official default stops at 44 m)."""
    checked = 0
    for f in PAPER:
        cfg = load_config(f)
        if cfg.model.view_transform.kind != "lss":
            continue
        start, stop, step = cfg.model.view_transform.depth_bound
        last_bin = start + step * (math.ceil((stop - start) / step) - 1)
        assert _farthest_seen_depth(cfg) <= last_bin, f.name
        checked += 1
    assert checked >= 20
    long_range = load_config(REPO / "configs/paper/table2_range100x100.yaml",
                             ["model.view_transform.depth_bound=[4,45,1]"])
    assert _farthest_seen_depth(long_range) > 44  # the official default leaves the far cells without features


GEO = sorted((REPO / "configs" / "geo").glob("*.yaml"))


def test_geo_configs_are_their_bases_on_the_geo_split():
    """Every configs/geo file is a shipped row on StreamMapNet's split: the geo scheme and, for the 100 x 50 m
    rows, the long-range grid, a vertex budget scaled with the area and depth bins that reach the grid."""
    from instagram_hdmap.config import config_to_dict, diff_configs

    assert len(GEO) == 9
    for f in GEO:
        cfg = load_config(f)
        assert cfg.data.split_scheme == "geo" and cfg.data.splits_file is None, f.name
        base = load_config(REPO / "configs" / ("av2" if f.name.startswith("av2") else "paper") /
                           f.name.removeprefix("av2_").removeprefix("nuscenes_")) if "table1" in f.name else None
        if base is not None:
            assert set(diff_configs(base, cfg)) == {"name", "data.split_scheme"}, f.name
            continue
        grid = BEVGrid.from_config(cfg.grid)
        assert (cfg.grid.xbound, cfg.grid.ybound) == ((-50.0, 50.0), (-25.0, 25.0))  # 100 m along, 50 m across
        assert (grid.H, grid.W) == (200, 400) and grid.H % cfg.grid.cell_size == grid.W % cfg.grid.cell_size == 0
        assert cfg.model.gnn.num_vertices == round(400 * (100 * 50) / (60 * 30)) <= (grid.H * grid.W) // 64
        start, stop, step = cfg.model.view_transform.depth_bound
        assert _farthest_seen_depth(cfg) <= start + step * (math.ceil((stop - start) / step) - 1), f.name
        assert config_to_dict(cfg)["data"]["dataset"] == ("av2" if f.name.startswith("av2") else "nuscenes")


def test_also_protocols_are_checked():
    assert load_config(None, ["eval.also_protocols=[raster]"]).eval.also_protocols == ("raster",)
    for bad in ("[vector]", "[raster,raster]", "[lidar]"):
        with pytest.raises(ConfigError, match="eval.also_protocols"):
            load_config(None, [f"eval.also_protocols={bad}"])


def test_no_shipped_config_trains_an_efficientnet_from_random_weights_by_accident():
    """Paper and AV2 configs ask for ImageNet weights, the CPU demo / tiny configs use the tiny backbone,
    configs/synthetic/full.yaml trains from scratch on purpose: none warns. A paper config with its
    weights removed does."""
    from instagram_hdmap.models import random_init_warning

    for f in sorted((REPO / "configs").rglob("*.yaml")):
        cfg = load_config(f)
        assert random_init_warning(cfg) is None, f
        assert (cfg.model.backbone.weights == "imagenet") != (cfg.model.backbone.name == "tiny"
                                                             or cfg.model.backbone.from_scratch), f
    warning = random_init_warning(load_config(PAPER[0], ["model.backbone.weights=null"]))
    assert "RANDOM" in warning and "model.backbone.from_scratch=true" in warning


def test_the_configs_nuscenes_camera_count_is_the_rigs():
    """config.py checks the MLP view transform's camera count without importing the data layer (which sits
    above it), so it keeps the nuScenes rig's size as a number: it must be data/rig.py's CAMERAS."""
    from instagram_hdmap.config import NUSCENES_CAMERA_COUNT
    from instagram_hdmap.data.rig import CAMERAS

    assert NUSCENES_CAMERA_COUNT == len(CAMERAS)
