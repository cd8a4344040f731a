"""Training and evaluating on geographically disjoint splits (``data.split_scheme=geo``): StreamMapNet's lists as
shipped, the scenes of a dataset downloaded in parts, and the held-out road network of a synthetic world."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from instagram_hdmap.config import load_config
from instagram_hdmap.data import build_dataset
from instagram_hdmap.data.geo_split import SYNTHETIC_HELD_OUT, GeoSplitError, left_out, listed
from instagram_hdmap.data.nuscenes import geo_split_scenes

# four scenes drive the four networks (a scene's location is its index modulo 4); the fourth is a val scene
GEO_WORLD = {"scenes_train": 3, "scenes_val": 1, "samples_per_scene": 2, "seed": 3, "image_size": "320x180"}


def test_the_lists_are_streammapnets():
    """The counts of StreamMapNet's nusc_split.py and av2_{train,val}_split.txt, its converters' left-out
    scenes and logs, disjoint splits, and nuScenes names all of the devkit's trainval."""
    from nuscenes.utils import splits

    train, val = listed("nuscenes", "train"), listed("nuscenes", "val")
    assert (len(train), len(val)) == (698, 148) and not set(train) & set(val)
    assert left_out("nuscenes") == ["scene-0499", "scene-0502", "scene-0515", "scene-0517"]
    assert set(left_out("nuscenes")) <= set(train)
    assert set(train) | set(val) <= set(splits.train) | set(splits.val)
    # the point of the split: the official val scenes are spread over both
    assert set(val) & set(splits.train) and set(train) & set(splits.val)
    av2_train, av2_val = listed("av2", "train"), listed("av2", "val")
    assert (len(av2_train), len(av2_val)) == (749, 149) and not set(av2_train) & set(av2_val)
    assert len(left_out("av2")) == 6 and len(set(av2_train + av2_val)) == 898
    with pytest.raises(GeoSplitError, match="splits 'train' and 'val', not 'mini_val'"):
        listed("nuscenes", "mini_val")


def test_a_dataset_in_parts_names_the_scenes_it_lacks(tmp_path):
    val = listed("nuscenes", "val")
    there = [val[3], "scene-0499", val[0], listed("nuscenes", "train")[0]]
    nusc = SimpleNamespace(dataroot=str(tmp_path), scene=[{"name": n} for n in there])
    geo = geo_split_scenes(nusc, "v1.0-trainval", "val")
    assert geo.names == [val[3], val[0]]  # the dataroot's order
    assert geo.listed == 148 and len(geo.missing) == 146 and val[1] in geo.missing
    line = geo.line("ROOT", 80)
    assert "2 of its 148 scenes, 80 samples" in line and all(n in line for n in geo.missing)
    train = geo_split_scenes(nusc, "v1.0-trainval", "train")
    assert train.names == [there[3]] and train.listed == 694  # StreamMapNet's converter drops scene-0499 etc.
    assert "scene-0499" not in train.names and "4 left out" in train.line("ROOT", 1)
    nusc.scene = [{"name": "scene-9999"}]
    with pytest.raises(GeoSplitError, match="none of them is in .* holds 1 scene"):
        geo_split_scenes(nusc, "v1.0-trainval", "val")


@pytest.fixture(scope="module")
def geo_world(tmp_path_factory):
    from instagram_hdmap.data.synthetic import generate_world

    root = tmp_path_factory.mktemp("geo") / "nuscenes"
    generate_world(out=str(root), force=True, progress=False, **GEO_WORLD)
    return root


def _locations(ds) -> set[str]:
    return {ds._location(t) for t in ds.sample_tokens}


def test_a_synthetic_geo_split_shares_no_road_network(geo_world, capsys):
    cfg = load_config(None, [f"data.dataroot={geo_world}", "data.split_scheme=geo", "data.image_size=[64,176]"])
    train, val = build_dataset(cfg, "train"), build_dataset(cfg, "val", like=None)
    out = capsys.readouterr().out
    assert _locations(val) == {SYNTHETIC_HELD_OUT} and SYNTHETIC_HELD_OUT not in _locations(train)
    assert len(_locations(train)) == 3 and not set(train.scenes.names) & set(val.scenes.names)
    assert len(train) + len(val) == 4 * GEO_WORLD["samples_per_scene"]
    assert f"geo split 'val' of {geo_world}" in out and "1 of its 1 scenes, 2 samples" in out
    assert "3 of its 3 scenes, 6 samples" in out
    official = build_dataset(load_config(None, [f"data.dataroot={geo_world}", "data.image_size=[64,176]"]), "val")
    assert official.scenes.names == val.scenes.names  # the world's val scene drives the fourth network
    assert _locations(build_dataset(load_config(None, [f"data.dataroot={geo_world}", "data.image_size=[64,176]"]),
                                    "train")) == _locations(train)


def test_an_av2_geo_split_reads_logs_of_every_split_folder(tmp_path):
    pytest.importorskip("av2")
    from instagram_hdmap.data.synthetic.av2_writer import generate_av2_world

    root = tmp_path / "av2"
    manifest = generate_av2_world(out=root, force=True, progress=False,
                                  **{**GEO_WORLD, "scenes_train": 2, "scenes_val": 2, "image_size": "320x240"})
    over = [f"data.dataroot={root}", "data.dataset=av2", "data.split_scheme=geo", "data.image_size=[64,176]",
            "data.av2_frame_step=1", "data.splits_file=null"]
    train, val = (build_dataset(load_config(None, over), s) for s in ("train", "val"))
    networks = manifest["maps"]
    assert {networks[log] for log in val.scenes.names} == {SYNTHETIC_HELD_OUT}
    assert SYNTHETIC_HELD_OUT not in {networks[log] for log in train.scenes.names}
    # the third log was written to val/, yet it trains: a geo split draws from every folder
    assert manifest["logs"]["val"][0] in train.scenes.names
    assert len(train.gt_polylines(len(train) - 1)) > 0 and val.ego_pose(0).shape == (4, 4)
