"""The mapper's parts (model, density strategy, sensor renderer, training step, keyframe store, pose refiner):
each restores its own state; the grouped configuration and its flat names; the one keyframe type."""

import dataclasses
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from gausslite.config import load_config, load_mapper_config, migrate_flat_names
from gausslite.mapping.config import FLAT_NAMES, MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.profiles import HANDHELD, with_profile
from gausslite.mapping.step import TrainStep
from gausslite.mapping.views import Keyframe, StoredKeyframe, keyframe_from_frame
from gausslite.mission.heap import trim_heap
from tests._scenes import plane_frame

H, W = 40, 56


def _roi() -> np.ndarray:
    r = np.zeros((H, W), bool)
    r[10:26, 14:34] = True
    return r


def _handheld_cfg(**kw) -> MapperConfig:
    base = dict(mode="gausslite", seeding={"seeds_per_frame": 300}, iters_per_frame=6, warmup_iters=2, window=3,
                backend="warp", pose={"refine": True}, densify={"every": 3},
                sensor={"exposure_comp": True, "motion_blur": True, "rolling_shutter_s": 0.02})
    return MapperConfig.model_validate(deep_merge(base, kw))


def _equal(a, b) -> bool:
    """Deep equality of state dicts (tensors, arrays, dicts, lists, scalars)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if torch.is_tensor(a):
        return torch.is_tensor(b) and a.shape == b.shape and bool(torch.equal(a, b))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, np.asarray(b))
    return a == b


def _mapped(**kw) -> Mapper:
    m = Mapper(_handheld_cfg(**kw))
    for i in range(4):
        m.map_frame(plane_frame(i, 0.03 * i, H, W), _roi())
    return m


@pytest.mark.parametrize("part", ["model", "strategy", "sensor", "step", "keyframes", "poses"])
def test_each_part_restores_its_own_state(part):
    m = _mapped()
    state = getattr(m, part).state_dict()
    fresh = Mapper(_handheld_cfg(seed=7))
    if part == "strategy":  # the strategy's rows follow the model's
        fresh.model.load_state_dict(m.model.state_dict())
    getattr(fresh, part).load_state_dict(state)
    assert _equal(getattr(fresh, part).state_dict(), state)


def test_the_checkpoint_is_the_union_of_the_parts_and_resumes_the_same_map():
    m = _mapped(densify={"enabled": False})  # split daughters' positions come from a generator not checkpointed
    state = m.state_dict(saved_keyframes_max=None)
    for part in ("model", "strategy", "sensor", "step"):
        for k, v in getattr(m, part).state_dict().items():
            assert _equal(state[k], v), (part, k)
    m2 = Mapper(_handheld_cfg(densify={"enabled": False}))
    m2.load_state_dict(state)
    assert _equal(m2.state_dict(saved_keyframes_max=None), state)
    # both continue alike: the same frame, the same parameters (Adam moments restart at zero in both)
    m.load_state_dict(state)
    for mm in (m, m2):
        mm.map_frame(plane_frame(4, 0.12, H, W), _roi())
    for k, p in m.model.params.items():
        assert torch.equal(p, m2.model.params[k]), k


def test_the_training_step_is_public_and_counts_kappa_in_the_roi_phase():
    m = Mapper(_handheld_cfg(pose={"refine": False},
                             sensor={"exposure_comp": False, "motion_blur": False, "rolling_shutter_s": 0.0}))
    fr = plane_frame(0, 0.0, H, W)
    m.seed_frame(fr, _roi())
    assert isinstance(m.step, TrainStep)
    kf = keyframe_from_frame(fr, m.device, _roi())
    loss = m.step(kf, active_phase=True)
    assert loss > 0 and m.step.roi_iters == 1
    act = m.model.active
    assert torch.all(m.model.kappa[act] == 1) and torch.all(m.model.kappa[~act] == 0)
    m.step(kf, footprint_only=True)  # full map, footprint loss: no κ
    assert torch.all(m.model.kappa[act] == 1)


def test_grouped_settings_and_the_migration_of_their_old_flat_names(caplog):
    cfg = MapperConfig(budget={"max_gaussians": 5000}, pose={"refine": True}, seeding={"seeds_per_frame": 300},
                       performance={"cpu_kernel": "tile"})
    assert cfg.budget.max_gaussians == 5000 and cfg.pose.refine and cfg.seeding.seeds_per_frame == 300
    assert cfg.performance.cpu_kernel == "tile"
    # every flat name names one grouped field; settings added since the groups have none (grouped names only)
    for flat, (group, name) in FLAT_NAMES.items():
        assert name in type(getattr(cfg, group)).model_fields, flat
    groups = ("seeding", "budget", "pose", "sensor", "performance")
    n_fields = sum(len(type(getattr(cfg, g)).model_fields) for g in groups)
    assert len(FLAT_NAMES) == len(set(FLAT_NAMES.values())) == 48 < n_fields
    assert ("pose", "roi_phase") not in FLAT_NAMES.values() and ("seeding", "adopt") not in FLAT_NAMES.values()
    # grouped names: no warning, no log line
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mapper_config(None, ["budget.max_gaussians=800", "pose.refine=true"], seeding={"seeds_per_frame": 9})
        load_config(None, ["mapper.budget.max_gaussians=800"])
        assert migrate_flat_names({"budget": {"cap": 3}}) == {"budget": {"cap": 3}}
    assert "old mapper setting names" not in caplog.text
    # an old flat name still loads, to its grouped setting, with a DeprecationWarning and a log line naming the new key
    with pytest.warns(DeprecationWarning, match=r"max_gaussians -> budget\.max_gaussians"):
        cfg = load_mapper_config(None, ["max_gaussians=700"], defaults={"budget": {"max_gaussians": 100, "cap": 900}})
    assert (cfg.budget.max_gaussians, cfg.budget.cap) == (700, 900)  # a flat name from a later layer wins
    assert "pose_refine -> pose.refine" not in caplog.text and "max_gaussians -> budget.max_gaussians" in caplog.text
    with pytest.warns(DeprecationWarning, match=r"pose_refine -> pose\.refine.*coverage_seeding -> seeding\.coverage"):
        tree = load_config(None, ["mapper.pose_refine=false", "mapper.coverage_seeding=false"])
    assert tree.mapper.pose.refine is False and tree.mapper.seeding.coverage is False
    assert tree.mapper.seeding.seeds_per_frame == 1500  # the deployed file's group is kept beside the migrated key
    data = {"evict": "opacity", "budget": {"cap": 5}}
    with pytest.warns(DeprecationWarning):
        assert migrate_flat_names(data) == {"budget": {"cap": 5, "evict": "opacity"}}
    assert data == {"evict": "opacity", "budget": {"cap": 5}}  # the input is not modified
    with pytest.raises(ValueError):
        MapperConfig(budget={"no_such_setting": 1})


def test_the_documented_migration_table_is_the_one_the_code_applies():
    text = (Path(__file__).resolve().parents[2] / "docs" / "mapper.md").read_text(encoding="utf-8")
    section = text.split("## Old flat names", 1)[1]
    rows = dict(re.findall(r"^\| `(\w+)` \| `(\w+\.\w+)` \|$", section, flags=re.M))
    assert rows == {flat: ".".join(key) for flat, key in FLAT_NAMES.items()}


def test_a_sensor_profile_fills_only_what_the_config_left_unset():
    explicit = MapperConfig(pose={"refine": False}, sensor={"motion_blur": False})
    out = with_profile(explicit, HANDHELD)
    assert out.pose.refine is False and out.sensor.motion_blur is False  # set explicitly: kept
    assert out.sensor.exposure_comp is True and out.sensor.rolling_shutter_s == 0.02  # the profile's
    assert out.lambda_depth == 0.3 and out.final_iters_per_keyframe == 20.0


def test_one_keyframe_type_and_its_compact_form():
    fr = plane_frame(3, 0.1, H, W)
    kf = keyframe_from_frame(fr, torch.device("cpu"), _roi())
    st = kf.compact()
    assert isinstance(st, StoredKeyframe) and st.rgb.dtype == torch.uint8 and st.depth.dtype == torch.float16
    back = st.to_keyframe(torch.device("cpu"))
    assert isinstance(back, Keyframe) and back.roi_box == kf.roi_box == (14, 10, 34, 26)
    assert float((back.rgb - kf.rgb).abs().max()) <= 0.5 / 255 + 1e-6
    assert torch.equal(back.c2w, kf.c2w) and torch.equal(back.roi, kf.roi)
    kf.ssim_stats = ("cached",)
    moved = kf.to("cpu")
    assert moved.ssim_stats is None and moved.frame_id == kf.frame_id
    bad = dataclasses.replace(fr, intrinsics=dataclasses.replace(fr.intrinsics, width=W + 1))
    with pytest.raises(ValueError, match="do not match"):
        keyframe_from_frame(bad, torch.device("cpu"))
    with pytest.raises(ValueError, match="roi"):
        keyframe_from_frame(fr, torch.device("cpu"), _roi()[:-1])


def test_trim_heap_returns_whether_memory_went_back():
    assert trim_heap() in (True, False)
