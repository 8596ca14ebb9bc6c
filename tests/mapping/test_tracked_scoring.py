"""Scoring a live map under the protocols (gausslite.evaluation: ``sensor``, ``keyframes``, ``novel`` at the pose the
robot gives with what the map learned; ``tracked``, ``novel-tracked`` at a pose fitted to the map), the tracker those
fit each frame's pose and exposure with, and the exposure fit outside the ROI of a map without exposure records."""

import dataclasses

import numpy as np
import pytest

from gausslite.evaluation import score_live_map, score_view, track_view
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.poses import pose_delta
from tests._scenes import plane_frame

H, W = 40, 56


def _plane_map(mode: str = "uniform", roi=None) -> Mapper:
    cfg = MapperConfig(mode=mode, seeding={"seeds_per_frame": 1500}, iters_per_frame=40, warmup_iters=20,
                       backend="warp", sensor={"exposure_comp": True}, pose={"refine": True})
    cfg.densify.enabled = False
    m = Mapper(cfg)
    for i in range(4):
        m.map_frame(plane_frame(i, 0.03 * i, H, W), roi)
    return m


def _perturbed(c2w: np.ndarray, xi) -> np.ndarray:
    import torch

    return np.asarray(c2w, np.float64) @ pose_delta(torch.tensor(xi, dtype=torch.float64)).numpy()


def test_tracking_recovers_a_known_pose_and_exposure_perturbation():
    """A held-out view of the mapped plane, given 3 cm and 1° off and 25 % darker: the tracker brings the pose back
    within a fifth of the error and finds the darker response; the map does not change."""
    m = _plane_map()
    truth = plane_frame(9, 0.045, H, W)
    truth = dataclasses.replace(truth, rgb=(truth.rgb * 0.75).astype(np.uint8))
    start = _perturbed(truth.c2w, [0.0, 0.0, np.radians(1.0), 0.03, 0.0, 0.0])
    means = m.model.params["means"].detach().clone()
    tv = track_view(m.sensor, truth, start, iters=60)
    err0 = np.linalg.norm(start[:3, 3] - truth.c2w[:3, 3])
    err1 = np.linalg.norm(tv.c2w[:3, 3] - truth.c2w[:3, 3])
    assert err1 < 0.2 * err0, (err0, err1)
    assert tv.theta[:3].mean() < np.log(0.9)  # the view is darker than the map
    assert tv.iters == 60 and tv.trans_m > 0.02
    assert bool((m.model.params["means"] == means).all())  # the frozen map
    # the fitted view scores better than the given one
    at_start = score_view(m.render(start, truth.intrinsics.K, W, H), truth).psnr
    out = m.sensor.render_view(tv.c2w, truth.intrinsics.K, W, H, truth.frame_id, None)
    from gausslite.mapping.exposure import apply_exposure
    import torch

    out = dataclasses.replace(out, color=apply_exposure(out.color, torch.tensor(tv.theta)).clamp(0, 1))
    assert score_view(out, truth).psnr > at_start + 5.0


def test_tracking_does_nothing_where_the_map_is_absent():
    m = _plane_map()
    away = plane_frame(9, 0.045, H, W)
    c2w = away.c2w.copy()
    c2w[2, 3] = 10.0  # behind the plane
    tv = track_view(m.sensor, dataclasses.replace(away, c2w=c2w), c2w, iters=10)
    assert tv.iters == 0 and np.array_equal(tv.c2w, c2w)
    with pytest.raises(ValueError):
        track_view(m.sensor, away, c2w, iters=-1)


def test_protocols_score_both_modes_alike_and_tracking_never_sees_the_roi():
    roi = np.zeros((H, W), bool)
    roi[10:30, 14:42] = True
    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(8)]
    m = _plane_map("gausslite", roi)
    a = score_live_map(m, frames, lambda fr: roi, track_iters=5, track_stride=2)
    b = score_live_map(m, frames, lambda fr: np.zeros((H, W), bool), track_iters=5, track_stride=2)
    assert set(a) == {"sensor", "keyframes", "tracked"}
    assert a["sensor"]["frames_scored"] == 8 and a["tracked"]["frames_scored"] == 4
    assert a["keyframes"]["frames_scored"] == 4  # the mapped frame ids 0..3
    for p in a:  # the ROI changes what is scored, never the poses the frames are scored at
        assert a[p]["psnr"] == b[p]["psnr"] and b[p]["roi_psnr"] is None and a[p]["roi_psnr"] is not None
    with pytest.raises(ValueError, match="unknown"):
        score_live_map(m, frames, lambda fr: roi, protocols=("sensor", "oracle"))


def test_a_frozen_map_is_scored_under_every_protocol_at_the_poses_given_for_its_keyframes():
    """A map with no mission of its own (a fused team map, ``score_map``): ``sensor`` is the plain render at the
    sensor's pose (``evaluate_fused``'s figure), ``keyframes`` the frames whose poses are given, at those poses (a
    pose 3 cm and 1° off scores lower), none without them; ``tracked`` every stride-th frame, its pose fitted from the
    sensor's."""
    from gausslite.evaluation import evaluate_fused, score_map

    roi = np.zeros((H, W), bool)
    roi[10:30, 14:42] = True
    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(6)]
    gmap = _plane_map().gmap

    class _Ann:
        def roi_mask(self, task, depth, c2w, intr):
            return roi

    off = _perturbed(frames[2].c2w, [0.0, 0.0, np.radians(1.0), 0.03, 0.0, 0.0])
    true = score_map(gmap, frames, lambda fr: roi, track_iters=5, track_stride=3, backend="warp",
                     keyframe_poses={0: frames[0].c2w, 2: frames[2].c2w})
    moved = score_map(gmap, frames, lambda fr: roi, protocols=("keyframes",), backend="warp",
                      keyframe_poses={0: frames[0].c2w, 2: off})
    at = score_map(gmap, frames, lambda fr: roi, protocols=("keyframes",), backend="warp", keyframe_poses={2: off})
    assert at["keyframes"]["frames_scored"] == 1
    assert true["sensor"]["frames_scored"] == 6 and true["tracked"]["frames_scored"] == 2
    assert true["sensor"]["roi_psnr"] == pytest.approx(evaluate_fused(gmap, frames, _Ann(), "t", "warp"))
    assert true["keyframes"]["frames_scored"] == moved["keyframes"]["frames_scored"] == 2
    assert moved["keyframes"]["roi_psnr"] < true["keyframes"]["roi_psnr"] - 1.0, (moved, true)
    none = score_map(gmap, frames, lambda fr: roi, protocols=("keyframes",), backend="warp")
    assert none["keyframes"]["frames_scored"] == 0 and none["keyframes"]["roi_psnr"] is None
    import torch

    empty = score_map(gmap.subset(torch.zeros(len(gmap), dtype=torch.bool)), frames, lambda fr: roi)
    assert set(empty) == {"sensor", "keyframes", "tracked"}
    assert all(v["roi_psnr"] is None and v["frames_scored"] == 0 for v in empty.values())


def test_the_novel_protocol_scores_only_withheld_frames_and_refuses_a_training_view():
    from gausslite.evaluation import FrameSubset, withheld_indices

    assert withheld_indices(25, 10) == [5, 15] and withheld_indices(9, 3) == [1, 4, 7]
    with pytest.raises(ValueError):
        withheld_indices(10, 1)
    frames = [plane_frame(i, 0.03 * i, H, W) for i in range(6)]
    sub = FrameSubset(frames, [1, 4])
    assert [f.frame_id for f in sub] == [0, 2, 3, 5] and sub.withheld_ids == {1, 4}
    m = _plane_map()  # mapped frames 0..3
    roi = lambda fr: np.ones((H, W), bool)  # noqa: E731
    res = score_live_map(m, frames, roi, ("novel", "novel-tracked"), track_iters=2, novel_ids=[4, 5])
    assert res["novel"]["frames_scored"] == res["novel-tracked"]["frames_scored"] == 2
    assert set(res["novel"]["roi_psnr_per_frame"]) == {4, 5} and res["novel"]["pose"] == "predicted"
    for q in ("novel", "novel-tracked"):
        with pytest.raises(ValueError, match="training views"):
            score_live_map(m, frames, roi, (q,), track_iters=2, novel_ids=[3, 5])
        with pytest.raises(ValueError, match="novel_ids"):
            score_live_map(m, frames, roi, (q,))


def _corrected_map(withheld: int = 2) -> Mapper:
    """The plane mapped on frames 0..4 but ``withheld``, interpolating between keyframes, with known corrections and
    exposure responses set on the keyframes (so a prediction differs from the sensor's pose and from zero)."""
    cfg = MapperConfig(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=20, warmup_iters=10,
                       backend="warp", sensor={"exposure_comp": True},
                       pose={"refine": True, "between_keyframes": "interpolate"})
    cfg.densify.enabled = False
    m = Mapper(cfg)
    for i in range(5):
        if i != withheld:
            m.map_frame(plane_frame(i, 0.03 * i, H, W))
    for k in list(m.poses.corrections):
        m.poses.corrections[k] = _perturbed(np.eye(4), [0.0, 0.01 * k, 0.0, 0.004 * k, 0.0, 0.0])
        m.sensor.exposure.params[k] = np.array([-0.05 * k, 0.0, 0.02 * k, 0.01, 0.0, -0.01 * k])
    return m


def test_novel_renders_a_withheld_frame_at_the_predicted_pose_and_fits_nothing(monkeypatch):
    """``novel`` is the ``sensor`` protocol on the withheld frames: the given pose with the correction interpolated
    between the keyframes on either side, the exposure likewise, exactly; the tracker never runs and the frame's
    images never move the view (a darker frame is scored at the same pose and exposure)."""
    import gausslite.evaluation as ev
    from gausslite.mapping.poses import interpolate_pose

    m = _corrected_map(withheld=2)
    frames = [plane_frame(i, 0.03 * i, H, W) for i in range(5)]
    used = []
    real = m.sensor.render_view

    def spy(c2w, *a, **kw):
        used.append((int(a[3]), np.array(c2w, np.float64)))  # (frame id, pose)
        return real(c2w, *a, **kw)

    def no_tracking(*a, **kw):
        raise AssertionError("novel must not fit a pose")

    monkeypatch.setattr(m.sensor, "render_view", spy)
    monkeypatch.setattr(ev, "track_view", no_tracking)
    roi = lambda fr: np.ones((H, W), bool)  # noqa: E731
    views: dict = {}
    res = ev.score_live_map(m, frames, roi, ("sensor", "novel"), novel_ids=[2], predicted=views)
    want = frames[2].c2w @ interpolate_pose(m.poses.corrections[1], m.poses.corrections[3], 0.5)
    # frame 2 rendered once, at that pose: ``sensor``'s render is ``novel``'s
    at2 = [c2w for fid, c2w in used if fid == 2]
    assert len(at2) == 1 and np.array_equal(at2[0], want) and np.array_equal(views[2].c2w, want)
    assert np.array_equal(views[2].theta, 0.5 * (m.sensor.exposure.params[1] + m.sensor.exposure.params[3]))
    assert views[2].iters == 0 and views[2].trans_m > 0.005
    # the very figure the sensor protocol gives that frame
    assert res["novel"]["psnr_per_frame"][2] == res["sensor"]["psnr_per_frame"][2]
    dark = [dataclasses.replace(f, rgb=(f.rgb * 0.5).astype(np.uint8)) if f.frame_id == 2 else f for f in frames]
    again: dict = {}
    ev.score_live_map(m, dark, roi, ("novel",), novel_ids=[2], predicted=again)
    assert np.array_equal(again[2].c2w, want) and np.array_equal(again[2].theta, views[2].theta)


def test_novel_tracked_fits_the_withheld_frames_and_a_given_prediction_is_used_as_is(monkeypatch):
    """``novel-tracked`` tracks each withheld frame against the map (the old ``novel``); ``novel_views`` (another map's
    prediction: the owner robot's, for a fused map) is rendered as given."""
    from gausslite.evaluation import TrackedView, score_live_map

    m = _corrected_map(withheld=2)
    frames = [plane_frame(i, 0.03 * i, H, W) for i in range(5)]
    roi = lambda fr: np.ones((H, W), bool)  # noqa: E731
    tracked: dict = {}
    score_live_map(m, frames, roi, ("novel-tracked",), track_iters=3, novel_ids=[2], record=tracked)
    assert tracked[2].iters == 3
    given = TrackedView(_perturbed(frames[2].c2w, [0.0, 0.0, 0.0, 0.02, 0.0, 0.0]), np.zeros(6), 0.0, 0.0, 0.0, 0)
    used: dict = {}
    score_live_map(m, frames, roi, ("novel",), novel_ids=[2], novel_views={2: given}, predicted=used)
    assert used[2] is given


def test_a_map_without_exposure_records_fits_the_exposure_outside_the_roi_only():
    """A fused map (``score_map``) keeps no exposure response: ``novel`` renders it at the sensor's pose (nothing
    fitted to the pose) and fits the affine exposure on the pixels outside the scored ROI, as NeRF-W and 3DGS's
    train_test_exp do: changing the ROI's pixels leaves the fitted exposure exactly as it was, changing the others
    moves it."""
    import torch

    from gausslite.evaluation import fit_exposure_outside_roi, render_map, score_map

    gmap = _plane_map().gmap
    fr = plane_frame(9, 0.045, H, W)
    roi = np.zeros((H, W), bool)
    roi[10:30, 14:42] = True
    out = render_map(gmap, fr, "warp")
    darker = dataclasses.replace(fr, rgb=(fr.rgb * 0.7).astype(np.uint8))
    th = fit_exposure_outside_roi(out, darker, roi)
    assert th[:3].mean() < np.log(0.85)  # the darker frame is found from the pixels outside the ROI
    inside = darker.rgb.copy()
    inside[roi] = 255 - inside[roi]
    assert np.array_equal(fit_exposure_outside_roi(out, dataclasses.replace(darker, rgb=inside), roi), th)
    outside = darker.rgb.copy()
    outside[~roi] = (outside[~roi] * 0.5).astype(np.uint8)
    assert not np.allclose(fit_exposure_outside_roi(out, dataclasses.replace(darker, rgb=outside), roi), th)
    all_roi = np.ones((H, W), bool)  # nothing outside the ROI: nothing to fit on
    assert np.array_equal(fit_exposure_outside_roi(out, darker, all_roi), np.zeros(6))
    with pytest.raises(ValueError):
        fit_exposure_outside_roi(out, darker, roi[:10])
    # through score_map: the view is the sensor's pose exactly, the exposure the fit's
    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(3)] + [darker]
    views: dict = {}
    res = score_map(gmap, frames, lambda f: roi, ("novel",), backend="warp", novel_ids=[9], predicted=views)
    assert np.array_equal(views[9].c2w, darker.c2w) and views[9].iters == 0
    assert np.allclose(views[9].theta, th) and res["novel"]["frames_scored"] == 1
    assert not torch.equal(torch.tensor(views[9].theta), torch.zeros(6))


def test_older_results_name_the_tracked_novel_figure_novel_tracked():
    from gausslite.evaluation import current_protocol_name, current_protocols

    old = {"sensor": {"roi_psnr": 20.0}, "novel": {"roi_psnr": 21.0}, "novel@own": {"t": {"roi_psnr": 1.0}}}
    assert set(current_protocols(old)) == {"sensor", "novel-tracked", "novel-tracked@own"}
    new = {"novel": {"roi_psnr": 21.0, "pose": "predicted"}, "novel-tracked": {"roi_psnr": 22.0}}
    assert current_protocols(new) == new
    assert current_protocol_name("novel", {"t": {"roi_psnr": 1.0, "pose": "predicted"}}) == "novel"


def test_a_frame_both_tracked_protocols_score_is_fitted_once_with_the_same_figures(monkeypatch):
    """``tracked`` (every 2nd frame: 0, 2, 4, 6) and ``novel-tracked`` (withheld 4, 5, 6, 7) share frames 4 and 6: each
    is fitted once, and both protocols get exactly the figures and views that scoring each alone gives."""
    import gausslite.evaluation as ev

    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(8)]
    m = _plane_map()  # mapped frames 0..3
    roi = lambda fr: np.ones((H, W), bool)  # noqa: E731
    calls = []
    real = ev.track_view
    monkeypatch.setattr(ev, "track_view",
                        lambda sensor, fr, *a, **k: calls.append(fr.frame_id) or real(sensor, fr, *a, **k))
    record = {}
    both = score_live_map(m, frames, roi, ("tracked", "novel-tracked"), track_iters=3, track_stride=2,
                          novel_ids=[4, 5, 6, 7], record=record)
    assert sorted(calls) == [0, 2, 4, 5, 6, 7]
    assert set(record) == {0, 2, 4, 5, 6, 7}
    for q in ("tracked", "novel-tracked"):
        alone_rec = {}
        alone = score_live_map(m, frames, roi, (q,), track_iters=3, track_stride=2, novel_ids=[4, 5, 6, 7],
                               record=alone_rec)[q]
        assert alone["psnr_per_frame"] == both[q]["psnr_per_frame"]
        assert alone["roi_psnr_per_frame"] == both[q]["roi_psnr_per_frame"] and alone["ssim"] == both[q]["ssim"]
        for fid, view in alone_rec.items():
            assert np.array_equal(view.c2w, record[fid].c2w) and np.array_equal(view.theta, record[fid].theta)


def test_a_view_that_several_protocols_render_alike_is_rendered_once(monkeypatch):
    """``sensor`` renders every frame at the pose and exposure ``keyframes`` and ``novel`` take for theirs (the refined
    keyframe pose, the predicted view): each frame is rendered and scored once, with exactly the figures and views
    that scoring each protocol alone gives. On a map without exposure records (``score_map``), a keyframe given at the
    sensor's pose shares the sensor's render and one given elsewhere does not."""
    from gausslite.evaluation import score_map
    from gausslite.mapping.sensor import SensorRenderer

    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(8)]
    m = _plane_map()  # mapped frames 0..3, exposure records and refined poses
    roi = lambda fr: np.ones((H, W), bool)  # noqa: E731
    calls = []
    real = SensorRenderer.render_view
    monkeypatch.setattr(SensorRenderer, "render_view",
                        lambda self, c2w, K, w, h, fid, *a, **k: calls.append(int(fid)) or real(self, c2w, K, w, h,
                                                                                                 fid, *a, **k))
    predicted = {}
    all3 = score_live_map(m, frames, roi, ("sensor", "keyframes", "novel"), novel_ids=[5, 7], predicted=predicted)
    assert sorted(calls) == list(range(8))
    assert all3["keyframes"]["frames_scored"] == 4 and all3["novel"]["frames_scored"] == 2
    for q in ("sensor", "keyframes", "novel"):
        alone_pred = {}
        alone = score_live_map(m, frames, roi, (q,), novel_ids=[5, 7], predicted=alone_pred)[q]
        assert alone["psnr_per_frame"] == all3[q]["psnr_per_frame"] and alone["ssim"] == all3[q]["ssim"]
        assert alone["roi_psnr_per_frame"] == all3[q]["roi_psnr_per_frame"]
        assert set(alone_pred) == ({5, 7} if q == "novel" else set())
        for fid, view in alone_pred.items():
            assert np.array_equal(view.c2w, predicted[fid].c2w) and np.array_equal(view.theta, predicted[fid].theta)
    gmap = m.gmap
    off = _perturbed(frames[2].c2w, [0.0, 0.0, np.radians(1.0), 0.03, 0.0, 0.0])
    calls.clear()
    both = score_map(gmap, frames, roi, ("sensor", "keyframes"), backend="warp",
                     keyframe_poses={0: frames[0].c2w, 2: off})
    assert sorted(calls) == sorted([*range(8), 2])  # frame 0's keyframe is the sensor's render; frame 2's is its own
    kf = score_map(gmap, frames, roi, ("keyframes",), backend="warp", keyframe_poses={0: frames[0].c2w, 2: off})
    assert kf["keyframes"]["psnr_per_frame"] == both["keyframes"]["psnr_per_frame"]
    assert both["keyframes"]["psnr_per_frame"][0] == both["sensor"]["psnr_per_frame"][0]
