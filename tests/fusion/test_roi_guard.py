"""ROI guard after the vote and the ROI cover diagnosis (gausslite.fusion.guard, gausslite.fusion.diagnose;
docs/sharing.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.fusion.diagnose import RoiView, cover_image, roi_cover
from gausslite.fusion.guard import roi_guard, roi_weights
from gausslite.fusion.vote import voxel_vote
from gausslite.wire.codec import GaussianArrays

K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])


def _arrays(means, scales, opacity=0.95, kappa=5) -> GaussianArrays:
    n = len(means)
    return GaussianArrays(
        means=np.asarray(means, np.float32), quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        log_scales=np.log(np.repeat(np.asarray(scales, np.float32)[:, None], 3, 1)),
        opacity_logits=np.full(n, np.log(opacity / (1 - opacity)), np.float32),
        colors=np.full((n, 3), 0.5, np.float32), kappa=np.full(n, kappa, np.int64), active=np.ones(n, bool))


def _view(box, tx=0.0) -> RoiView:
    """A 64x48 view from (tx, 0, 0) looking down +z; ROI = box (x0, y0, x1, y1); depth 2 m everywhere."""
    roi = np.zeros((48, 64), bool)
    x0, y0, x1, y1 = box
    roi[y0:y1, x0:x1] = True
    c2w = np.eye(4)
    c2w[0, 3] = tx
    return RoiView(K, 64, 48, c2w, roi, np.full((48, 64), 2.0, np.float32))


def _team():
    """agent_a: small Gaussians on its ROI (the image's left part at 2 m). agent_b: small Gaussians on its own ROI
    (right part), plus one large splat centred beside a's region, in front of it, that spreads over a's ROI."""
    a = _arrays([[-0.4, 0.0, 2.0], [-0.3, 0.0, 2.0], [-0.4, 0.1, 2.0]], [0.05, 0.05, 0.05])
    b = _arrays([[0.4, 0.0, 2.0], [0.3, 0.0, 2.0], [-0.05, 0.0, 1.6]], [0.05, 0.05, 0.25])
    views = {"agent_a": [_view((2, 10, 26, 38))], "agent_b": [_view((40, 10, 62, 38))]}
    return {"agent_a": a, "agent_b": b}, views


def test_guard_drops_a_foreign_splat_over_an_roi_and_keeps_every_owner_row():
    subsets, views = _team()
    fused, rep = voxel_vote(subsets, 0.10)
    assert len(fused) == 6  # nothing contested: the vote keeps the large splat
    w_a = roi_weights(fused, views["agent_a"])
    big = int(np.nonzero((rep.source_agent == 1) & (rep.source_row == 2))[0][0])
    assert w_a[big] > 1.0  # it draws more than a pixel of a's ROI
    keep, gr = roi_guard(fused, rep.source_agent, rep.agents, views)
    assert not keep[big] and keep.sum() == 5
    assert gr.dropped == {"agent_a": 0, "agent_b": 1} and gr.views == {"agent_a": 1, "agent_b": 1}


def test_guard_keeps_a_gaussian_that_serves_its_own_robot_more():
    subsets, views = _team()
    # agent_b's ROI now also covers the splat's centre: it draws b's ROI more than a's
    views["agent_b"] = [_view((28, 10, 62, 38))]
    fused, rep = voxel_vote(subsets, 0.10)
    keep, gr = roi_guard(fused, rep.source_agent, rep.agents, views)
    assert keep.all() and gr.dropped == {"agent_a": 0, "agent_b": 0}
    # an agent without ROI views is not guarded and its rows serve nothing: b's splat goes again
    keep, _ = roi_guard(fused, rep.source_agent, rep.agents, {"agent_a": views["agent_a"]})
    assert keep.sum() == 5


def test_guard_rejects_bad_inputs():
    subsets, views = _team()
    fused, rep = voxel_vote(subsets, 0.10)
    with pytest.raises(ValueError):
        roi_guard(fused, rep.source_agent[:-1], rep.agents, views)
    with pytest.raises(ValueError):
        roi_guard(fused, rep.source_agent + 5, rep.agents, views)
    with pytest.raises(ValueError):
        roi_guard(fused, rep.source_agent, rep.agents, views, max_views=0)


def test_roi_cover_lists_the_foreign_splat_and_the_missing_own_rows():
    subsets, views = _team()
    fused, rep = voxel_vote(subsets, 0.10)
    cov = roi_cover(subsets, fused, rep.source_agent, rep.source_row, views)
    ca = cov["agent_a"]
    m = ca["mass"]
    assert m["foreign_task"] + m["foreign_context"] > 0.05 and m["own"] > 0.01
    assert sum(m.values()) == pytest.approx(1.0, abs=1e-6)
    top = ca["top_foreign"][0]
    assert top["agent"] == "agent_b" and top["row"] == 2 and top["extent_m"] == pytest.approx(0.75, rel=1e-4)
    assert top["depth_vs_roi_m"] < -0.3  # 40 cm in front of a's ROI surface
    assert ca["foreign"]["weight_in_front"] > 0.9
    assert ca["own_missing"] == {"rows": 0, "of": 3, "weight_share": 0.0}
    # after the guard a's ROI is its own; rows the vote dropped are listed as missing with their weight
    keep, _ = roi_guard(fused, rep.source_agent, rep.agents, views)
    clean = roi_cover(subsets, fused.take(keep), rep.source_agent[keep], rep.source_row[keep], views)["agent_a"]
    assert clean["mass"]["foreign_task"] + clean["mass"]["foreign_context"] < 1e-6
    drop_a = (rep.source_agent == 0) & (rep.source_row == 0)
    gone = roi_cover(subsets, fused.take(~drop_a), rep.source_agent[~drop_a], rep.source_row[~drop_a], views)
    assert gone["agent_a"]["own_missing"]["rows"] == 1 and gone["agent_a"]["own_missing"]["weight_share"] > 0.1
    img = cover_image(fused, rep.source_agent != 0, views["agent_a"][0])
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    # the foreign splat shows in red over a's ROI
    assert (img[24, 14, 2] > img[24, 14, 1])
    with pytest.raises(ValueError):
        roi_cover(subsets, fused, rep.source_agent[:-1], rep.source_row, views)


def test_team_map_for_a_robot_keeps_its_roi_whatever_another_robot_shares():
    """The timeline check: another robot's subset arriving leaves the robot's ROI, in the team map made for it, as it
    was (its whole subset, nothing of the other's over its ROI), while the team vote map changes."""
    from gausslite.fusion.guard import for_robot
    from gausslite.render import rasterize

    subsets, views = _team()
    # agent_b also holds a row in a voxel of agent_a's (κ 50: it wins that voxel in the team vote)
    b = GaussianArrays.concat([subsets["agent_b"], _arrays([[-0.4, 0.0, 2.02]], [0.05], kappa=50)])
    v = views["agent_a"][0]
    roi = torch.from_numpy(v.roi)

    def roi_render(g):
        out = rasterize(*(torch.from_numpy(x) for x in (g.means, g.quats, g.log_scales, g.opacity_logits, g.colors)),
                        K=v.K, width=v.width, height=v.height, c2w=v.c2w, background=torch.zeros(3))
        return out.color[roi]

    alone, rep1 = voxel_vote({"agent_a": subsets["agent_a"]}, 0.10, contest_radius=1)
    before, _ = for_robot(alone, rep1.source_agent, rep1.agents, "agent_a", subsets["agent_a"], views["agent_a"])
    team, rep2 = voxel_vote({"agent_a": subsets["agent_a"], "agent_b": b}, 0.10, contest_radius=1)
    assert rep2.dropped["agent_a"] > 0  # the team vote took rows of agent_a's region
    after, st = for_robot(team, rep2.source_agent, rep2.agents, "agent_a", subsets["agent_a"], views["agent_a"])
    assert st["own"] == len(subsets["agent_a"]) and st["others_dropped"] >= 2
    assert float((roi_render(after) - roi_render(before)).abs().max()) < 1e-3
    assert float((roi_render(team) - roi_render(before)).abs().max()) > 0.05
    with pytest.raises(ValueError):
        for_robot(team, rep2.source_agent, rep2.agents, "agent_z", subsets["agent_a"], views["agent_a"])


def test_the_team_map_made_on_board_holds_the_robots_whole_map_and_culls_what_covers_its_roi():
    """``with_own_map``: the vote's rows of robot a are replaced by a's whole map (more than it shared); b's splat over
    a's ROI goes, b's region stays; provenance that does not fit the map is refused."""
    from gausslite.fusion.guard import provenance_rows, with_own_map

    subsets, views = _team()
    fused, rep = voxel_vote(subsets, 0.10)
    order = [rep.agents[i] for i in rep.source_agent]
    first_row = {a: order.index(a) for a in rep.agents}
    kept = {a: order.count(a) for a in rep.agents}
    assert order == sorted(order)  # rows grouped by agent, as a downloaded vote is
    agents, src = provenance_rows(first_row, kept, len(fused))
    assert agents == ["agent_a", "agent_b"] and np.array_equal(src, rep.source_agent)
    own = GaussianArrays.concat([subsets["agent_a"], _arrays([[-0.8, 0.3, 3.0]], [0.05])])  # a row it never shared
    out, st = with_own_map(fused, first_row, kept, "agent_a", own, views["agent_a"])
    assert st["own"] == len(own) == 4 and out.take(np.arange(4)).equals(own)
    assert st["others_dropped"] == 1 and st["others_kept"] == 2  # the large splat only
    rest = out.take(np.arange(4, len(out)))
    assert np.allclose(np.sort(rest.means[:, 0]), [0.3, 0.4])
    with pytest.raises(ValueError, match="does not fit"):
        provenance_rows({"agent_a": 0, "agent_b": 2}, kept, len(fused))
    with pytest.raises(ValueError, match="no provenance"):
        provenance_rows({"agent_a": 0}, {"agent_a": 3}, len(fused))
    with pytest.raises(ValueError, match="no rows of robot"):
        with_own_map(fused, first_row, kept, "agent_c", own, views["agent_a"])
