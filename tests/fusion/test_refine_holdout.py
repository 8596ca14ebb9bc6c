"""The fused-map refinement's held-out check: the seeded split of the keyframes, the iterations scaled to the training
keyframes, the early stop that never serves a map worse than the vote on the held-out keyframes, the best state kept,
the report, the settings and the engine that carries the report."""

import dataclasses
import logging

import numpy as np
import pydantic
import pytest
import torch

from gausslite.config import FusionSettings
from gausslite.fusion.engine import FuseEngine
from gausslite.fusion.holdout import RefineReport, RefineValidation, scaled_iters, split_views
from gausslite.fusion import refine as refine_mod
from gausslite.fusion.refine import refine_map
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.loss import photometric_loss
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.views import keyframe_from_frame
from gausslite.metrics import psnr
from gausslite.wire.codec import GaussianArrays
from tests._scenes import plane_frame

CFG = MapperConfig(seeding={"seeds_per_frame": 800}, iters_per_frame=10, warmup_iters=0, backend="warp")


@pytest.fixture(scope="module")
def scene():
    """Four views of the textured plane, their keyframes and the map fitted to them."""
    frames = [plane_frame(i, 0.04 * i) for i in range(4)]
    m = Mapper(CFG)
    for fr in frames:
        m.map_frame(fr)
    return frames, [keyframe_from_frame(f, "cpu") for f in frames], GaussianArrays.from_any(m.gmap)


def _noisy(g: GaussianArrays, sigma: float) -> GaussianArrays:
    out = GaussianArrays.concat([g])
    out.colors = (out.colors + np.random.default_rng(0).normal(0, sigma, out.colors.shape)).astype(np.float32)
    return out


def _shifted(kfs, which, shift):
    """The keyframes, those in ``which`` with their colours raised by ``shift`` (a view the others disagree with)."""
    return [dataclasses.replace(k, rgb=(k.rgb + shift).clamp(0, 1)) if i in which else k for i, k in enumerate(kfs)]


def _render(g: GaussianArrays, kf):
    m = Mapper(CFG)
    m.load_map(g.to_gaussian_map())
    return m.render(kf.c2w, kf.K, kf.width, kf.height)


def _heldout_loss(g: GaussianArrays, kf, vote: GaussianArrays) -> float:
    """The training loss of ``g`` on keyframe ``kf``, on the pixels ``vote`` renders (as the check scores it)."""
    mask = _render(vote, kf).alpha > CFG.footprint_alpha
    return float(photometric_loss(_render(g, kf), kf, CFG.lambda_depth, CFG.lambda_ssim, mask))


def test_split_views_is_seeded_spread_over_sources_and_holds_out_one_from_two_views():
    assert split_views(0) == ([], []) and split_views(1) == ([0], [])
    assert split_views(5, fraction=0.0) == (list(range(5)), [])
    for seed in range(8):
        train, held = split_views(2, seed=seed)
        assert len(held) == 1 and sorted(train + held) == [0, 1]
        # two robots with four keyframes each: one held out from each, wherever the seed starts
        src = ["a"] * 4 + ["b"] * 4
        train, held = split_views(8, src, 0.25, seed)
        assert sorted(src[i] for i in held) == ["a", "b"] and sorted(train + held) == list(range(8))
        # two robots, two keyframes each (a live fuse): one of the four held out
        assert len(split_views(4, ["a", "a", "b", "b"], 0.25, seed)[1]) == 1
        assert split_views(8, src, 0.25, seed) == split_views(8, src, 0.25, seed)  # deterministic
    assert len({tuple(split_views(8, seed=s)[1]) for s in range(8)}) > 1  # the seed moves the held-out views
    assert len(split_views(10, fraction=0.5)[1]) == 5
    for bad in (dict(n=-1), dict(n=4, fraction=0.6), dict(n=4, fraction=-0.1), dict(n=3, sources=["a", "b"])):
        with pytest.raises(ValueError):
            split_views(**bad)


def test_iterations_scale_with_the_training_views():
    assert scaled_iters(300, 3) == 75 and scaled_iters(300, 12) == 300  # defaults: 25 per training view
    assert scaled_iters(300, 3, per_view_iters=0) == 300 and scaled_iters(40, 3, 10) == 30
    with pytest.raises(ValueError):
        scaled_iters(-1, 3)


def test_refine_that_overfits_disagreeing_views_is_stopped_and_serves_the_vote(scene):
    """Training views whose colours the held-out view disagrees with: fitting them spoils the held-out view, so the
    check stops the refinement and returns the vote itself; without the check the same refinement is worse there."""
    frames, kfs, vote = scene
    train, held = split_views(4, None, 0.25, seed=0)
    bad = _shifted(kfs, train, 0.1)
    rep = RefineReport()
    out = refine_map(vote, bad, iters=100, seed=0, cfg=CFG, report=rep)
    assert rep.validated and (rep.train_views, rep.heldout_views) == (3, 1)
    assert rep.rolled_back and rep.stopped_early and rep.best_iter == 0 and rep.best_loss == rep.vote_loss
    assert rep.iters_run < rep.iters_planned == 75 and rep.last_loss > rep.vote_loss
    assert out.equals(vote)
    assert _heldout_loss(out, kfs[held[0]], vote) <= _heldout_loss(vote, kfs[held[0]], vote)
    # the same training views without the check: the held-out view loses against the vote
    unchecked = refine_map(vote, [bad[i] for i in train], iters=75, seed=0, cfg=CFG, holdout_fraction=0.0)
    assert _heldout_loss(unchecked, kfs[held[0]], vote) > _heldout_loss(vote, kfs[held[0]], vote) + 0.02


def test_refine_returns_its_best_held_out_state_not_its_last(scene):
    """Fitting slightly disagreeing views first removes the vote's colour noise, then drifts: the returned map is the
    best scored state, never worse than the vote on the held-out view."""
    frames, kfs, fitted = scene
    vote = _noisy(fitted, 0.1)
    train, held = split_views(4, None, 0.25, seed=0)
    rep = RefineReport()
    out = refine_map(vote, _shifted(kfs, train, 0.05), iters=100, seed=0, cfg=CFG, check_every=5, report=rep)
    assert not rep.rolled_back and 0 < rep.best_iter <= rep.iters_run
    assert rep.best_loss < rep.vote_loss and rep.best_loss <= rep.last_loss
    got = _heldout_loss(out, kfs[held[0]], vote)
    assert got == pytest.approx(rep.best_loss, abs=1e-4) and got <= _heldout_loss(vote, kfs[held[0]], vote)


def test_refine_still_improves_the_held_out_views_of_a_consistent_scene(scene):
    frames, kfs, fitted = scene
    vote = _noisy(fitted, 0.15)
    _, held = split_views(4, None, 0.25, seed=1)
    rep = RefineReport()
    out = refine_map(vote, kfs, iters=60, seed=1, cfg=CFG, report=rep)
    assert rep.validated and not rep.rolled_back and rep.best_loss < 0.7 * rep.vote_loss
    fr = frames[held[0]]

    def score(g):
        return float(psnr(_render(g, kfs[held[0]]).color.clamp(0, 1), torch.from_numpy(fr.rgb).float() / 255))

    assert score(out) > score(vote) + 2.0


def test_refine_report_fields_progress_and_the_unvalidated_single_view(scene):
    frames, kfs, fitted = scene
    vote = _noisy(fitted, 0.15)
    rep, seen = RefineReport(), []
    refine_map(vote, kfs[:3], iters=200, seed=2, cfg=CFG, per_view_iters=10, check_every=5, patience=100,
               report=rep, progress=lambda f, m: seen.append((f, m)))
    assert (rep.iters_requested, rep.iters_planned, rep.iters_run) == (200, 20, 20)
    assert (rep.train_views, rep.heldout_views, rep.validated) == (2, 1, True)
    assert rep.checks == 1 + 4 and not rep.stopped_early and rep.gaussians > 0
    assert rep.best_loss <= rep.vote_loss and rep.last_loss is not None
    assert seen[-1][0] == 1.0 and "held-out" in seen[-1][1]
    assert set(rep.as_dict()) >= {"vote_loss", "best_loss", "best_iter", "iters_run", "stopped_early", "rolled_back",
                                  "train_views", "heldout_views"}
    assert "held-out loss" in rep.summary()
    one = RefineReport()
    out = refine_map(vote, kfs[:1], iters=30, seed=0, cfg=CFG, report=one)
    assert (one.train_views, one.heldout_views, one.validated, one.vote_loss, one.iters_run) == (1, 0, False, None, 25)
    assert not one.rolled_back and not out.equals(vote) and "no held-out check" in one.summary()
    # a held-out view the vote draws nothing of (the camera turned away from the plane) is trained on instead
    away = dataclasses.replace(kfs[1], c2w=torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64)))
    _, (h,) = split_views(3, None, 0.25, seed=0)
    pool = [kfs[0], kfs[2]]
    pool.insert(h, away)
    unscored = RefineReport()
    refine_map(vote, pool, iters=30, seed=0, cfg=CFG, report=unscored)
    assert (unscored.train_views, unscored.heldout_views, unscored.validated) == (3, 0, False)
    for bad in (dict(check_every=0), dict(patience=0), dict(holdout_fraction=0.6), dict(per_view_iters=-1),
                dict(sources=["a"])):
        with pytest.raises(ValueError):
            refine_map(vote, kfs[:2], iters=5, cfg=CFG, **bad)


def test_a_cancelling_progress_callback_stops_a_long_refinement_within_the_report_period(scene, monkeypatch):
    """Progress is reported at least every PROGRESS_PERIOD_S, not only every 1/20 of the iterations, so a stopping
    server's cancellation reaches a long refinement at once (here: a period of 0 s reports every iteration)."""
    frames, kfs, fitted = scene

    class Stop(Exception):
        pass

    def cancel_at_third(f, m):
        calls.append(f)
        if len(calls) == 3:
            raise Stop()

    calls, rep = [], RefineReport()
    monkeypatch.setattr(refine_mod, "PROGRESS_PERIOD_S", 0.0)
    with pytest.raises(Stop):
        refine_map(_noisy(fitted, 0.15), kfs[:3], iters=2000, seed=0, cfg=CFG, per_view_iters=0, report=rep,
                   progress=cancel_at_third)
    assert rep.iters_planned == 2000 and rep.iters_run == 3 and calls == [1 / 2000, 2 / 2000, 3 / 2000]


def test_engine_carries_logs_and_reports_the_refinement(scene, caplog):
    frames, kfs, fitted = scene
    half = len(fitted) // 2
    maps = {"a": fitted.take(slice(0, half)), "b": fitted.take(slice(half, None))}
    msgs = []
    with caplog.at_level(logging.INFO, logger="gausslite.fusion.engine"):
        out = FuseEngine({"cfg": CFG}).fuse({"a": 1, "b": 1}, maps, "concat", refine_iters=20,
                                            keyframes=lambda: {"a": kfs[:2], "b": kfs[2:]},
                                            progress=lambda s, f, m: msgs.append((s, m)))
    rep = out.refine_report
    assert out.keyframes_used == 4 and (rep.train_views, rep.heldout_views) == (3, 1)
    assert rep.iters_planned == 20 and len(out.fused) == rep.gaussians
    assert any("refinement:" in r.getMessage() for r in caplog.records)
    assert msgs[-1] == ("refine", rep.summary())
    assert FuseEngine().fuse({"a": 1}, {"a": maps["a"]}, "concat").refine_report is None


def test_settings_of_the_held_out_check():
    v = FusionSettings().refine_validation
    assert v.options() == {"holdout_fraction": 0.25, "check_every": 10, "patience": 3, "per_view_iters": 25}
    assert FusionSettings.model_validate({"refine_validation": {"patience": 5}}).refine_validation.patience == 5
    for bad in ({"holdout_fraction": 0.9}, {"check_every": 0}, {"typo": 1}):
        with pytest.raises(pydantic.ValidationError):
            RefineValidation.model_validate(bad)
