"""Agent pieces without servers: frame codec round trip, share rule, CLI flags → environment → settings."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.cli import build_parser
from gausslite_services.cli.cmd_sim import export_agent_env
from gausslite_services.agent.frames import FrameError, decode_frame, encode_frame
from gausslite.mission import select_shared
from gausslite_services.agent.server import settings_from_env
from tests._scenes import plane_frame


def test_frame_round_trip_png_is_exact_up_to_depth_quantisation():
    fr = plane_frame(3, shift=0.25)
    msg = encode_frame(fr, "m1")
    back = decode_frame(msg)
    assert back.frame_id == 3 and msg.mission_id == "m1"
    assert np.array_equal(back.rgb, fr.rgb)
    assert np.abs(back.depth - fr.depth).max() <= 0.5 / 6553.5 + 1e-6
    assert np.allclose(back.c2w, fr.c2w) and back.intrinsics == fr.intrinsics


def test_decode_rejects_non_rigid_pose():
    msg = encode_frame(plane_frame(0))
    msg.c2w[0] = 2.0  # scaled rotation
    with pytest.raises(FrameError, match="rotation"):
        decode_frame(msg)


def test_select_shared_active_and_kappa_rules():
    class G:
        active = torch.tensor([True, False, False, True])
        kappa = torch.tensor([5, 0, 3, 1])

    assert select_shared(G(), "active").tolist() == [True, False, False, True]
    assert select_shared(G(), "kappa", 3).tolist() == [True, False, True, False]
    with pytest.raises(ValueError):
        select_shared(G(), "everything")


def test_serve_agent_flags_reach_settings(tmp_path):
    args = build_parser().parse_args(["serve", "agent", "--port", "0", "--agent-id", "r2", "--parser", "h:1",
                                      "--fusion", "h:2", "--task", "Map the chairs", "--data-dir", str(tmp_path),
                                      "--set", "mapper.iters_per_frame=20", "--set", "agent.push.every=3"])
    env = {"GAUSSLITE_AGENT_ID": "from-env", "GAUSSLITE_AGENT_TASK_ID": "t-env"}
    export_agent_env(args, env)
    assert env["GAUSSLITE_AGENT_ID"] == "r2"  # flag wins over env
    s = settings_from_env(None, env=env, token="tok")
    assert (s.agent_id, s.parser_address, s.fusion_address, s.task, s.task_id) == ("r2", "h:1", "h:2",
                                                                                     "Map the chairs", "t-env")
    assert s.data_dir == str(tmp_path) and s.token == "tok"
    assert s.config.mapper.iters_per_frame == 20 and s.config.push.every == 3
    assert s.config.mapper.mode == "gausslite"
