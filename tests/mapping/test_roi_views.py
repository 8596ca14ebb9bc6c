"""The ROI view store (gausslite.mapping.roi_views): the task region of the frames between keyframes, carried over
from the keyframes' relevance by depth, stored as bounded crops, drawn and aligned by ROI-phase iterations."""

import numpy as np
import pytest
import torch

from gausslite.mapping.config import MapperConfig
from gausslite.mapping.iterations import roi_view_draw
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.roi_views import RoiViewStore, project_roi, roi_points, roi_view_of
from gausslite.mapping.views import keyframe_from_frame
from tests._scenes import plane_frame

H, W = 40, 56


def _roi(x0=20, y0=12, x1=36, y1=28) -> np.ndarray:
    r = np.zeros((H, W), bool)
    r[y0:y1, x0:x1] = True
    return r


def _view(i: int, shift: float, roi=None):
    fr = plane_frame(i, shift, H, W)
    return roi_view_of(fr, _roi() if roi is None else roi, pad=4)


def test_a_keyframes_region_lands_on_the_same_surface_in_another_frame():
    """The ROI of a keyframe, back-projected with its depth and projected into a frame 10 cm to the side, covers the
    pixels that see the same world points (50 px/m focal at 2 m: 2.5 px per 10 cm), not the keyframe's pixels."""
    kf = keyframe_from_frame(plane_frame(0, 0.0, H, W), "cpu", _roi()).compact()
    pts = roi_points(kf, stride=1)
    assert pts.shape == (16 * 16, 3) and np.allclose(pts[:, 2], 2.0)
    other = plane_frame(1, 0.1, H, W)
    mask = project_roi(pts, other.depth, other.intrinsics.K, other.c2w, dilate_px=0)
    ys, xs = np.nonzero(mask)
    assert xs.min() == 20 - 2 or xs.min() == 20 - 3  # shifted left by 2.5 px
    assert ys.min() == 12 and ys.max() == 27


def test_a_surface_in_front_hides_the_region():
    kf = keyframe_from_frame(plane_frame(0, 0.0, H, W), "cpu", _roi()).compact()
    fr = plane_frame(1, 0.0, H, W)
    occluded = fr.depth.copy()
    occluded[:, :28] = 1.0  # a wall 1 m in front over the left half
    mask = project_roi(roi_points(kf), occluded, fr.intrinsics.K, fr.c2w)
    assert mask[:, 30:].any() and not mask[:, :28 - 3].any()  # hidden up to the dilation at its edge


def test_the_store_is_bounded_by_count_and_bytes_and_evicts_the_most_redundant_view():
    store = RoiViewStore(max_views=3)
    for i, shift in enumerate([0.0, 0.5, 0.501, 1.0]):  # views 1 and 2 are nearly the same pose
        store.add(_view(i, shift))
    assert len(store) == 3 and store.n_added == 4 and store.n_evicted == 1
    assert store.frame_ids == [0, 2, 3]  # the older of the closest pair went
    one = store[0].nbytes
    small = RoiViewStore(max_views=100, max_bytes=2 * one)
    for i in range(5):
        small.add(_view(i, 0.3 * i))
    assert len(small) == 2 and small.nbytes <= 2 * one
    with pytest.raises(ValueError):
        RoiViewStore(max_views=0)
    with pytest.raises(ValueError):
        store.add(keyframe_from_frame(plane_frame(9, 0.0, H, W), "cpu", None))


def test_views_keep_their_refined_pose_and_survive_a_checkpoint():
    store = RoiViewStore()
    store.add(_view(3, 0.2))
    new = torch.eye(4, dtype=torch.float64)
    new[0, 3] = 0.25
    assert store.set_pose(3, new) and not store.set_pose(4, new)
    again = RoiViewStore()
    again.load_state_dict(store.state_dict())
    assert again.frame_ids == [3] and float(again[0].c2w[0, 3]) == pytest.approx(0.25)
    v = again.load(0, torch.device("cpu"))
    assert v.width == 16 + 8 and v.height == 16 + 8 and v.roi_box == (4, 4, 20, 20)
    RoiViewStore().load_state_dict({})  # a checkpoint from before the store: no views


def _mapper(enabled=True, draw=1.0, mode="gausslite") -> Mapper:
    cfg = MapperConfig(mode=mode, seeding={"seeds_per_frame": 600}, iters_per_frame=6, warmup_iters=2,
                       backend="warp", sensor={"exposure_comp": True}, pose={"refine": True},
                       roi_views={"enabled": enabled, "draw": draw, "min_roi_px": 16})
    cfg.densify.enabled = False
    return Mapper(cfg)


def test_the_mapper_stores_the_frames_between_keyframes_with_their_own_pose_and_exposure_slots():
    m = _mapper()
    m.map_frame(plane_frame(0, 0.0, H, W), _roi())
    between = [plane_frame(i, 0.01 * i, H, W) for i in range(1, 4)]
    m.map_frame(plane_frame(4, 0.04, H, W), _roi(), between=between)
    assert m.roi_views.frame_ids == [1, 2, 3]
    assert all(i in m.poses.corrections for i in (1, 2, 3)) and all(i in m.sensor.exposure.params for i in (1, 2, 3))
    assert [int(s.frame_id) for s in m.stats] == [0, 4]  # views are never keyframes
    # ROI-phase draws: with draw = 1 the store's share of the ROI views is views / (views + ROI keyframes)
    drawn = [roi_view_draw(m) for _ in range(400)]
    share = np.mean([d is not None for d in drawn])
    assert 0.45 < share < 0.75  # 3 / (3 + 2) = 0.6
    m.retarget()
    assert len(m.roi_views) == 0


def test_uniform_maps_and_a_disabled_store_keep_no_view():
    for m in (_mapper(mode="uniform"), _mapper(enabled=False)):
        m.map_frame(plane_frame(0, 0.0, H, W), _roi())
        m.map_frame(plane_frame(4, 0.04, H, W), _roi(), between=[plane_frame(i, 0.01 * i, H, W) for i in (1, 2, 3)])
        assert len(m.roi_views) == 0 and roi_view_draw(m) is None


def test_a_view_drawn_by_the_roi_phase_is_aligned_and_written_back():
    """An ROI-phase iteration on a stored view steps its pose correction (pose.roi_phase) and writes the pose back
    to the store, not to the keyframes."""
    m = _mapper()
    m.map_frame(plane_frame(0, 0.0, H, W), _roi())
    m.map_frame(plane_frame(4, 0.04, H, W), _roi(), between=[plane_frame(2, 0.02, H, W)])
    before = m.roi_views[0].c2w.clone()
    view = m.roi_views.load(0, m.device)
    for _ in range(3):
        m.step(view, active_phase=True)
    assert not torch.equal(before, m.roi_views[0].c2w)
    assert 2 not in {int(k.frame_id) for k in m.keyframes}


def test_a_checkpoint_holds_the_views():
    m = _mapper()
    m.map_frame(plane_frame(0, 0.0, H, W), _roi())
    m.map_frame(plane_frame(4, 0.04, H, W), _roi(), between=[plane_frame(2, 0.02, H, W)])
    again = _mapper()
    again.load_state_dict(m.state_dict())
    assert again.roi_views.frame_ids == [2]
