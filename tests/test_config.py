"""Config system: defaults, YAML overrides with _base_, CLI overrides, round trip, clear errors."""

from pathlib import Path

import pytest

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
    ("data.image_size=[0,352]", r"'data\.image_size\[0\]' must be >= 1"),
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
