"""``gausslite map`` on a folder without poses: poses from odometry, ``--pose-source``, ``--task`` grounded as the
agent grounds it (annotations, else ONNX, else a one-line refusal) and the trajectory written beside the map."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil

import numpy as np
import pytest

from gausslite.cli import main
from gausslite.datasets import load_dataset
from gausslite.datasets.trajectory import ate_rmse, read_tum_trajectory
from gausslite.synthetic import make_scene


@pytest.fixture(scope="module")
def bare(tmp_path_factory):
    """The synthetic scene's first robot (16 frames, 160x120) without traj.txt, with the scene's annotations; and
    its ground-truth poses."""
    root = tmp_path_factory.mktemp("scene")
    make_scene(root / "scene", frames=16, width=160, height=120, progress=False, agents=("agent_a",))
    seq = root / "bare" / "agent_a"
    shutil.copytree(root / "scene" / "agent_a", seq)
    for name in ("cam_params.json", "objects.json", "tasks.json"):
        shutil.copy(root / "scene" / name, seq.parent)
    (seq / "traj.txt").unlink()
    return seq, load_dataset(root / "scene" / "agent_a").poses


def test_map_grounds_the_task_and_writes_the_trajectory(bare, tmp_path, capsys):
    seq, gt = bare
    out = tmp_path / "run"
    rc = main(["map", "--dataset", str(seq), "--task", "find the chair", "--iters", "10", "--no-progress",
               "--set", "final_iters_per_keyframe=0", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "poses: odometry (the dataset has none)" in text
    assert "'find the chair' grounded with the scene annotations" in text and "targets ['chair']" in text
    ts, poses = read_tum_trajectory(out / "trajectory.tum")
    assert len(ts) == 16 and np.allclose(ts, np.arange(16) / 30.0, atol=1e-6)
    assert np.allclose(poses[0], np.eye(4), atol=1e-6)  # the first camera is the world frame
    assert ate_rmse(poses, gt) < 0.03
    cfg = json.loads((out / "config.json").read_text())
    assert (out / "map.ply").is_file() and cfg["mode"] == "gausslite"
    assert cfg["pose"]["refine"] is True  # estimated poses are refined with the map (off in the rendered profile)


def test_a_task_that_cannot_be_grounded_and_given_poses_that_are_missing_are_one_line(bare, tmp_path, caplog):
    seq, _ = bare
    lone = tmp_path / "lone" / "agent_a"
    shutil.copytree(seq, lone)
    shutil.copy(seq.parent / "cam_params.json", lone.parent)
    with caplog.at_level(logging.ERROR):
        assert main(["map", "--dataset", str(lone), "--task", "find the chair", "--out", str(tmp_path / "a")]) == 2
    assert "cannot ground the task 'find the chair'" in caplog.text and "--onnx-detector" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.ERROR):
        assert main(["map", "--dataset", str(seq), "--pose-source", "given", "--out", str(tmp_path / "b")]) == 2
    assert "traj.txt not found" in caplog.text and "pose_source 'odometry'" in caplog.text


def test_run_mapping_neither_maps_nor_scores_a_lost_frame(bare):
    from gausslite.config import load_mapper_config
    from gausslite.pipeline import run_mapping

    seq, _ = bare
    ds = load_dataset(seq, max_frames=6, progress=False)
    ds.track()
    ds.results[3] = dataclasses.replace(ds.results[3], ok=False)  # as a lost frame is flagged
    assert not ds[3].pose_ok and list(ds.pose_ok) == [True] * 3 + [False] + [True] * 2
    cfg = load_mapper_config(None, ["iters_per_frame=3", "warmup_iters=1", "final_iters_per_keyframe=0"])
    mapper, m = run_mapping(ds, cfg, progress=False, stride=2)
    assert m["n_frames_lost"] == 1 and m["n_frames"] == 3  # frames 0, 2, 4 mapped; 3 not scored as held out
    assert {int(s.frame_id) for s in mapper.stats} == {0, 2, 4} and m["heldout_psnr"] is not None
