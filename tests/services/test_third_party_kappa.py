"""κ of a robot that is not a GaussLite agent (docs/team.md#κ-for-a-robot-that-is-not-our-agent): a subset sent
without κ (every κ 0) travels as an empty κ section, the fusion server accepts it, and the vote keeps its Gaussians
only where no robot with κ > 0 contests them (per voxel; with ``contest_radius`` 1, in the 3×3×3 block around)."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.config import load_config
from gausslite.fusion.vote import voxel_vote
from gausslite.wire import GaussianArrays
from gausslite.wire.decode import decode_chunk, peek_header
from gausslite.wire.encode import encode_subset

VOXEL = 0.10


def _rows(centres, kappa) -> GaussianArrays:
    """One Gaussian per centre (metres, world frame), every κ ``kappa``."""
    c = np.asarray(centres, np.float32).reshape(-1, 3)
    n = len(c)
    return GaussianArrays(means=c, quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), np.log(0.01), np.float32), opacity_logits=np.full(n, 2.0, np.float32),
                          colors=np.full((n, 3), 0.5, np.float32), kappa=np.full(n, kappa, np.int64),
                          active=np.ones(n, bool))


def _in_voxel(ijk, k: int) -> list:
    """``k`` centres spread inside voxel ``ijk`` (δ = 0.10 m)."""
    return [(np.asarray(ijk) + 0.2 + 0.6 * (i + 0.5) / k) * VOXEL for i in range(k)]


#: ours: 2 Gaussians of κ 40 in voxel (0, 0, 0). Theirs: 5 in that voxel, 3 in voxel (10, 0, 0) a metre away
OURS = _rows(_in_voxel((0, 0, 0), 2), 40)
THEIRS = [*_in_voxel((0, 0, 0), 5), *_in_voxel((10, 0, 0), 3)]


def test_no_kappa_is_an_empty_kappa_section_on_the_wire():
    chunk = encode_subset(_rows(THEIRS, 0), "robot_x", 1)[0]
    assert peek_header(chunk).kappa_bytes == 0  # "every κ is 0": no κ bytes at all
    assert np.array_equal(decode_chunk(chunk).arrays.kappa, np.zeros(len(THEIRS), np.int64))
    with pytest.raises(KeyError):  # our client needs a κ column: "no κ" is spelled as zeros
        GaussianArrays.from_any({k: v for k, v in vars(_rows(THEIRS, 0)).items() if k != "kappa"})


def test_the_server_accepts_a_subset_without_kappa_and_the_vote_keeps_it_only_where_uncontested(tmp_path):
    from gausslite_services.common.server import ServerOptions
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve

    srv = serve(ServerOptions(port=0), load_config(None, ["fusion.team_map.enabled=false"]).fusion,
                data_dir=str(tmp_path / "fusion"))
    intr = Intrinsics(32.0, 32.0, 31.5, 23.5, 64, 48)
    try:
        with FusionClient(srv.address, timeout_s=30) as fc:
            for agent, subset in (("gausslite", OURS), ("robot_x", _rows(THEIRS, 0))):
                fc.open_session(agent, "find the chair", intr)
                assert fc.upload_subset(agent, 1, subset, full_map_gaussians=100).complete
            res = fc.fuse("vote", voxel_size=VOXEL, contest_radius=0)
        # robot_x's 5 Gaussians in the shared voxel outnumber ours 5 to 2, yet κ 0 < 2·40: it keeps only the 3 a metre
        # away, where nobody contests it
        assert res.received == {"gausslite": 2, "robot_x": 8}
        assert res.kept == {"gausslite": 2, "robot_x": 3}
    finally:
        srv.stop(0)


def test_what_kappa_a_third_party_robot_sends_decides_the_contested_voxels():
    theirs = _in_voxel((0, 0, 0), 5)
    # a constant 1 per trusted Gaussian: summed κ = their count there (5), against our 80
    assert voxel_vote({"gausslite": OURS, "robot_x": _rows(theirs, 1)}, VOXEL)[1].kept == {"gausslite": 2, "robot_x": 0}
    # a count on our scale (more than 80 in the voxel: 5 x 17 = 85) wins it
    assert voxel_vote({"gausslite": OURS, "robot_x": _rows(theirs, 17)}, VOXEL)[1].kept == {"gausslite": 0, "robot_x": 5}
    # two robots without κ: the denser one wins the voxel, and at equal counts the smaller agent id
    _, rep = voxel_vote({"robot_x": _rows(theirs, 0), "robot_y": _rows(theirs[:2], 0)}, VOXEL)
    assert rep.kept == {"robot_x": 5, "robot_y": 0}
    _, rep = voxel_vote({"robot_y": _rows(theirs[:2], 0), "robot_x": _rows(theirs[3:], 0)}, VOXEL)
    assert rep.kept == {"robot_x": 2, "robot_y": 0}


def test_with_the_neighbourhood_contest_no_kappa_also_loses_the_voxels_next_to_a_robot_with_kappa():
    # robot_x holds voxel (1, 0, 0), next to ours, and voxel (10, 0, 0); nobody else is in (1, 0, 0)
    theirs = _rows([*_in_voxel((1, 0, 0), 5), *_in_voxel((10, 0, 0), 3)], 0)
    assert voxel_vote({"gausslite": OURS, "robot_x": theirs}, VOXEL, contest_radius=0)[1].kept["robot_x"] == 8
    _, rep = voxel_vote({"gausslite": OURS, "robot_x": theirs}, VOXEL, contest_radius=1)
    assert rep.kept == {"gausslite": 2, "robot_x": 3}  # the block around (1, 0, 0) goes to κ 80: the voxel is emptied
