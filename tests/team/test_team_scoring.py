"""The sim's scoring reads what each robot holds (gausslite.team.scoring): its own map and its keyframes, from the
files its agent wrote beside each other (``data/agents/<agent>/<mission>/``)."""

from __future__ import annotations

import logging

import numpy as np
import torch

from gausslite.team.scoring import own_keyframe_poses, own_map_files


def test_every_keyframe_a_robot_holds_is_read_from_its_checkpoint(tmp_path, caplog):
    c2w = np.eye(4)
    c2w[:3, 3] = [0.5, -0.25, 2.0]
    mission = tmp_path / "data" / "agents" / "agent_a" / "m1"
    mission.mkdir(parents=True)
    kfs = [{"frame_id": 3, "c2w": torch.as_tensor(c2w, dtype=torch.float32)},
           {"frame_id": 9, "c2w": torch.eye(4)}]
    torch.save({"mapper": {"keyframes": kfs}}, mission / "checkpoint.pt")
    (mission / "map.ply").write_bytes(b"ply\n")
    broken = tmp_path / "data" / "agents" / "agent_b" / "m2"
    broken.mkdir(parents=True)
    torch.save({"mapper": {}}, broken / "checkpoint.pt")  # a checkpoint without keyframes
    with caplog.at_level(logging.WARNING):
        poses = own_keyframe_poses(tmp_path, ["agent_a", "agent_b", "agent_c"])
    assert set(poses) == {"agent_a"} and set(poses["agent_a"]) == {3, 9}
    assert poses["agent_a"][3].dtype == np.float64 and np.allclose(poses["agent_a"][3], c2w)
    assert any("agent_b" in r.getMessage() and "uploaded" in r.getMessage() for r in caplog.records)
    assert own_map_files(tmp_path, ["agent_a", "agent_c"]) == {"agent_a": "data/agents/agent_a/m1/map.ply"}
