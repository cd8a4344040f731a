"""MapTracker's consistency-aware mAP (C-mAP): ``evaluation.consistency.ConsistentAPMeter`` and the instance IDs of
``persistence.InstanceTracker`` (docs/temporal.md, "Consistency-aware mAP"). Hand-built drives with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from instagram_hdmap.config import GridConfig
from instagram_hdmap.evaluation import ConsistentAPMeter, EvaluationInputError
from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.persistence import InstanceTracker, PersistenceInputError

GRID = BEVGrid.from_config(GridConfig())  # x in [-30, 30], y in [-15, 15] m
ONE = ("divider",)


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    p, a = np.eye(4), math.radians(yaw_deg)
    p[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    p[0, 3] = x
    return p


def _drive(frames: int = 6, step: float = 1.0):
    """One scene: the ego drives along x, ``step`` m a frame, beside one straight divider at y = 2 m (world) that
    is 20 m of the view in every frame (x in [-10, 10] m of the ego frame). Perfect predictions, score 0.95 - 0.01 f
    (all distinct: no tie order)."""
    line = np.array([[-10.0, 2.0], [10.0, 2.0]])
    gts = [[{"pts": line, "label": 0}] for _ in range(frames)]
    preds = [[{"pts": line + [0.0, 0.1], "label": 0, "score": 0.95 - 0.01 * f}] for f in range(frames)]
    poses = np.stack([_pose(step * f) for f in range(frames)])
    return preds, gts, ["s"] * frames, list(range(frames)), poses


def test_a_perfect_tracker_has_c_map_equal_to_map():
    preds, gts, scenes, frames, poses = _drive()
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(preds, gts, scenes, frames, poses)  # IDs from the tracker: the divider keeps its ID
    res = meter.compute()
    assert res["mAP"] == 1.0 and res["C-mAP"] == res["mAP"] and res["switched"] == {"divider": [0, 0, 0]}
    assert res["id_switches"] == {"divider": [0, 0, 0]}
    assert res["tracks"] == {"pred": 1, "gt": 1} and res["definition"]["ids"] == "tracked"
    given = ConsistentAPMeter(GRID, classes=ONE)
    given.update(preds, gts, scenes, frames, poses, ids=[torch.tensor([7])] * 6)  # a model that tracks: one ID
    assert given.compute()["C-mAP"] == 1.0 and given.compute()["definition"]["ids"] == "given"
    # three classes, two without GT: those count 0 in both means (the vector protocol's rule), C-mAP == mAP
    three = ConsistentAPMeter(GRID, classes=("divider", "ped_crossing", "boundary"))
    three.update(preds, gts, scenes, frames, poses)
    assert three.compute()["C-mAP"] == three.compute()["mAP"] == pytest.approx(1 / 3)


def test_an_id_switch_turns_the_later_tps_into_fps():
    """MapTracker's rule (calculate_cmap.py, get_tpfp_from_scene_single): the first predicted ID matched to a GT
    track owns it; every later TP of that track with another ID is an FP, for the rest of the scene."""
    preds, gts, scenes, frames, poses = _drive()
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(preds, gts, scenes, frames, poses, ids=[[0], [0], [0], [1], [1], [1]])
    res = meter.compute()
    # 6 GT, scores descending with the frame: TP TP TP FP FP FP -> precision 1 up to recall 3/6: AP 0.5
    assert res["AP"]["divider"] == [1.0, 1.0, 1.0] and res["C-AP"]["divider"] == [0.5, 0.5, 0.5]
    assert res["switched"]["divider"] == [3, 3, 3] and res["C-mAP"] == 0.5 and res["tracks"]["pred"] == 2
    assert res["id_switches"]["divider"] == [1, 1, 1]  # one change of ID along the track (MOTA's IDSW)
    # the switched predictions ranked first: FP FP FP TP TP TP -> precision 3/6 at recall 3/6: AP 0.25
    later_first = [[dict(p[0], score=0.5 + 0.1 * f)] for f, p in enumerate(preds)]
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(later_first, gts, scenes, frames, poses, ids=[[0], [0], [0], [1], [1], [1]])
    assert meter.compute()["C-mAP"] == 0.25
    # switching back to the owner's ID makes those TPs again (the owner is the first ID, not the last)
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(preds, gts, scenes, frames, poses, ids=[[0], [0], [1], [0], [0], [0]])
    assert meter.compute()["switched"]["divider"] == [1, 1, 1]
    assert meter.compute()["id_switches"]["divider"] == [2, 2, 2]  # away and back: two switches


def test_the_tracker_gives_a_new_id_after_a_miss_and_at_a_pose_jump():
    """The tracker looks at the previous frame only: a frame without the divider breaks its track (the TPs after
    it switch), and so does a pose jump (> max_jump_m), which starts the scene anew with new IDs."""
    preds, gts, scenes, frames, poses = _drive()
    missed = [p if f != 2 else [] for f, p in enumerate(preds)]
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(missed, gts, scenes, frames, poses)
    res = meter.compute()
    assert res["switched"]["divider"] == [3, 3, 3] and res["tracks"]["pred"] == 2
    # 5 TP of 6 GT, then 3 of them FP: TP TP FP FP FP -> AP = 2/6
    assert res["AP"]["divider"][0] == pytest.approx(5 / 6) and res["C-AP"]["divider"][0] == pytest.approx(2 / 6)
    # the ego moves 1 m a frame: with max_jump_m = 0.5 every frame is a pose jump for the tracker (new IDs), while
    # the GT link (geometric, FlickerMeter's) still follows the divider: every TP after the first frame switches
    meter = ConsistentAPMeter(GRID, classes=ONE, max_jump_m=0.5)
    meter.update(preds, gts, scenes, frames, poses)
    assert meter.compute()["switched"]["divider"] == [5, 5, 5] and meter.compute()["tracks"]["gt"] == 1
    jump = poses.copy()
    jump[3:, 0, 3] += 50.0  # a teleport of 50 m between frames 2 and 3
    tracker = InstanceTracker(GRID, match_m=1.0, max_jump_m=10.0)
    ids = [tracker.step(p, "s", f, q)[0] for p, f, q in zip(preds, frames, jump)]
    assert ids == [0, 0, 0, 1, 1, 1]  # new IDs after the jump, never reused in the scene


def test_instance_ids_follow_the_ego_motion():
    """The previous frame's elements are moved by the ego poses before matching: an element fixed in the world
    keeps its ID while the ego drives and turns; one that moves in the world by more than match_m does not."""
    tracker = InstanceTracker(GRID, match_m=1.0)
    world = np.array([[0.0, 5.0], [20.0, 5.0]])
    out = []
    for f in range(4):
        pose = _pose(2.0 * f, 10.0 * f)
        inv = np.linalg.inv(pose)
        ego = world @ inv[:2, :2].T + inv[:2, 3]
        shifted = ego + [0.0, 3.0 * f]  # an element that does not stay put
        out.append(tracker([[{"pts": ego, "label": 0, "score": 0.9}, {"pts": shifted, "label": 2, "score": 0.8}]],
                           ["a"], [f], torch.tensor(pose)[None])[0])
    assert [o[0] for o in out] == [0, 0, 0, 0] and len({o[1] for o in out}) == 4
    # one to one: two elements on one previous element, the nearer one takes its ID
    t2 = InstanceTracker(GRID)
    line = np.array([[-5.0, 0.0], [5.0, 0.0]])
    t2.step([{"pts": line, "label": 0, "score": 1.0}], "b", 0, np.eye(4))
    ids = t2.step([{"pts": line + [0, 0.5], "label": 0, "score": 1.0},
                   {"pts": line + [0, 0.1], "label": 0, "score": 0.5}], "b", 1, np.eye(4))
    assert ids == [1, 0]


def test_a_single_frame_scene_and_scenes_of_their_own():
    preds, gts, scenes, frames, poses = _drive(frames=1)
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(preds, gts, scenes, frames, poses)
    res = meter.compute()
    assert res["C-mAP"] == res["mAP"] == 1.0 and res["samples"] == 1
    # the same ID in two scenes is two tracks: the owner is per scene
    p2, g2, _, f2, q2 = _drive(frames=2)
    meter = ConsistentAPMeter(GRID, classes=ONE)
    meter.update(p2 + p2, g2 + g2, ["x", "x", "y", "y"], f2 + f2, np.concatenate([q2, q2]), ids=[[0], [0], [1], [1]])
    assert meter.compute()["C-mAP"] == 1.0 and meter.compute()["tracks"] == {"pred": 2, "gt": 2}
    empty = ConsistentAPMeter(GRID, classes=ONE).compute()
    assert math.isnan(empty["C-mAP"]) and empty["samples"] == 0


def test_any_order_and_merged_meters_give_the_same_result():
    preds, gts, scenes, frames, poses = _drive(frames=8)
    preds = [p if f not in (3, 4) else [dict(p[0], pts=p[0]["pts"] + [0.0, 0.8 * (f - 2)])]
             for f, p in enumerate(preds)]  # drifts away and back: a track that breaks
    whole = ConsistentAPMeter(GRID, classes=ONE)
    whole.update(preds, gts, scenes, frames, poses)
    ref = whole.compute()
    assert 0 < ref["C-mAP"] < ref["mAP"]
    order = [5, 0, 7, 2, 1, 6, 4, 3]
    shuffled = ConsistentAPMeter(GRID, classes=ONE)
    for i in order:
        shuffled.update([preds[i]], [gts[i]], [scenes[i]], [frames[i]], poses[i:i + 1])
    assert shuffled.compute() == ref
    a, b = ConsistentAPMeter(GRID, classes=ONE), ConsistentAPMeter(GRID, classes=ONE)
    for i in order:  # every other sample to each "rank", one sample to both (padding counts once)
        (a if i % 2 else b).update([preds[i]], [gts[i]], [scenes[i]], [frames[i]], poses[i:i + 1])
    b.update([preds[5]], [gts[5]], [scenes[5]], [frames[5]], poses[5:6])
    a.merge(b.state_dict())
    assert a.compute() == ref


def test_bad_input_is_named():
    preds, gts, scenes, frames, poses = _drive(frames=2)
    meter = ConsistentAPMeter(GRID, classes=ONE)
    with pytest.raises(EvaluationInputError, match=r"ConsistentAPMeter.update: one entry per sample .*got 2 preds, "
                                                   r"1 gts"):
        meter.update(preds, gts[:1], scenes, frames, poses)
    with pytest.raises(EvaluationInputError, match=r"ConsistentAPMeter.update: sample 1 \(scene 's'\): its frame "
                                                   r"index must be an integer >= 0"):
        meter.update(preds, gts, scenes, [0, 1.5], poses)
    with pytest.raises(EvaluationInputError, match=r"scene 's', frame 0\), prediction polyline 0: unknown class id 3"):
        meter.update([[dict(preds[0][0], label=3)], []], gts, scenes, frames, poses)
    with pytest.raises(EvaluationInputError, match=r"sample \(scene 's', frame 1\): ids must be one integer per "
                                                   r"prediction \(1\)"):
        meter.update(preds, gts, scenes, frames, poses, ids=[[0], [0, 1]])
    assert meter.records == {}  # nothing of a bad batch is kept
    meter.update(preds[:1], gts[:1], scenes[:1], frames[:1], poses[:1], ids=[[0]])
    meter.update(preds[1:], gts[1:], scenes[1:], frames[1:], poses[1:])
    with pytest.raises(EvaluationInputError, match="some samples came with prediction ids and some without"):
        meter.compute()
    with pytest.raises(EvaluationInputError, match=r"pass other.state_dict\(\)"):
        meter.merge(meter)
    with pytest.raises(EvaluationInputError, match=r"the state is at thresholds \[0.5, 1.0, 1.5\], this meter at "
                                                   r"\[1.0\]"):
        ConsistentAPMeter(GRID, classes=ONE, thresholds=[1.0]).merge(meter.state_dict())
    with pytest.raises(EvaluationInputError, match="ConsistentAPMeter: thresholds must be a list"):
        ConsistentAPMeter(GRID, classes=ONE, thresholds=[0.5, 100.0])
    with pytest.raises(EvaluationInputError, match="ConsistentAPMeter: link_m must be a finite distance"):
        ConsistentAPMeter(GRID, classes=ONE, link_m=-1.0)
    with pytest.raises(EvaluationInputError, match="ConsistentAPMeter: .*match_m and max_jump_m > 0"):
        ConsistentAPMeter(GRID, classes=ONE, match_m=0.0)
    with pytest.raises(PersistenceInputError, match=r"InstanceTracker: one entry per sample"):
        InstanceTracker(GRID)(preds, scenes[:1], frames, poses)
    with pytest.raises(PersistenceInputError, match=r"InstanceTracker: sample 0 \(scene 's'\): element 0 has no "
                                                    r"'label'"):  # no score is fine: the tracker reads none (GT)
        InstanceTracker(GRID)([[{"pts": gts[0][0]["pts"], "score": 1.0}]], scenes[:1], frames[:1], poses[:1])


def test_evaluation_reports_c_map_behind_eval_cmap(tiny_world, tmp_path):
    """``eval.cmap=true``: metrics.json holds ``cmap`` (a random single-frame model: C-mAP <= mAP, the meter's
    per-frame mAP is the evaluator's); off by default."""
    import json

    from instagram_hdmap.checkpoint import save_checkpoint
    from instagram_hdmap.config import config_to_dict
    from instagram_hdmap.evaluate_split import run_evaluation
    from instagram_hdmap.models import build_model
    from test_temporal import _drive_cfg

    cfg = _drive_cfg(tiny_world, tmp_path / "run", "eval.batch_size=2", "model.gnn.conf_threshold=0.0",
                     "model.gnn.match_threshold=0.01", "model.temporal.memory=none")
    assert cfg.eval.cmap is False
    torch.manual_seed(3)
    save_checkpoint({"model": build_model(cfg).state_dict(), "config": config_to_dict(cfg)}, tmp_path / "s.pt")
    plain = run_evaluation(cfg, tmp_path / "s.pt", out=tmp_path / "plain")["metrics"]
    assert "cmap" not in plain
    metrics = run_evaluation(cfg, tmp_path / "s.pt", out=tmp_path / "c", overrides=["eval.cmap=true"])["metrics"]
    c = json.loads((tmp_path / "c" / "metrics.json").read_text())["cmap"]
    assert c["mAP"] == pytest.approx(metrics["mAP"], abs=1e-6) and c["C-mAP"] <= c["mAP"]
    assert c["samples"] == metrics["meta"]["num_samples"] == 3 and c["thresholds"] == [0.5, 1.0, 1.5]
    assert set(c["C-AP_class"]) == set(cfg.data.classes) and c["tracks"]["gt"] > 0


def _gather_worker(rank: int, world: int, init_file: str, out: str) -> None:
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    preds, gts, scenes, frames, poses = _drive(frames=8)
    preds = [p if f != 3 else [] for f, p in enumerate(preds)]
    meter = ConsistentAPMeter(GRID, classes=ONE)
    mine = [i for i in range(8) if i % world == rank]  # a single-frame model's split: no consecutive frames
    meter.update([preds[i] for i in mine], [gts[i] for i in mine], [scenes[i] for i in mine],
                 [frames[i] for i in mine], poses[mine])
    meter.gather()
    if rank == 0:
        torch.save(meter.compute(), out)
    dist.destroy_process_group()


def test_gather_over_two_gloo_ranks_tracks_over_the_whole_scene(tmp_path):
    """Under torchrun each rank of a single-frame model sees every other frame; the IDs are given after gathering,
    so the result is the single process's."""
    out = tmp_path / "out.pt"
    torch.multiprocessing.spawn(_gather_worker, args=(2, str(tmp_path / "init"), str(out)), nprocs=2)
    preds, gts, scenes, frames, poses = _drive(frames=8)
    preds = [p if f != 3 else [] for f, p in enumerate(preds)]
    single = ConsistentAPMeter(GRID, classes=ONE)
    single.update(preds, gts, scenes, frames, poses)
    got = torch.load(out, weights_only=False)
    assert got == single.compute() and got["switched"]["divider"] == [4, 4, 4]
