"""Typed mapper config: paper defaults, YAML loading, overrides, validation."""

import pydantic
import pytest

from gausslite.config import load_mapper_config
from gausslite.mapping.config import MapperConfig, ablation_rows


def test_paper_defaults():
    cfg = MapperConfig()
    assert (cfg.seeding.m_roi, cfg.seeding.m_bg, cfg.seeding.init_opacity) == (0.5, 0.7, 0.5)
    assert cfg.budget.max_gaussians is None and cfg.budget.gaussians_per_pixel == 1.0  # budget scales with resolution
    assert cfg.seeding.rho == 0.4


def test_uniform_mode_turns_every_component_off():
    sw = MapperConfig(mode="uniform").effective()
    assert not any([sw.sb, sw.mvo, sw.roi, sw.sis, sw.gfd])
    sw = MapperConfig(mode="gausslite").effective()
    assert all([sw.sb, sw.mvo, sw.roi, sw.sis, sw.gfd])


def test_yaml_overrides_and_flags(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("iters_per_frame: 30\nlr:\n  means: 0.001\ncomponents:\n  gfd: false\n")
    cfg = load_mapper_config(p, ["lr.colors=0.01", "warmup_iters=5"], seed=7)
    assert cfg.iters_per_frame == 30 and cfg.lr.means == 0.001 and cfg.lr.colors == 0.01
    assert cfg.components.gfd is False and cfg.warmup_iters == 5 and cfg.seed == 7
    # keyword fields win over file and overrides; a group given as a keyword is merged key by key, None is not given
    assert load_mapper_config(p, ["iters_per_frame=50"], iters_per_frame=60).iters_per_frame == 60
    cfg = load_mapper_config(p, ["lr.colors=0.02"], lr={"means": 0.002}, seeding={"seeds_per_frame": None})
    assert (cfg.lr.means, cfg.lr.colors, cfg.seeding.seeds_per_frame) == (0.002, 0.02, 1500)


def test_invalid_values_and_unknown_keys_rejected(tmp_path):
    with pytest.raises(pydantic.ValidationError, match="rho"):
        load_mapper_config(None, ["seeding.rho=1.5"])
    with pytest.raises(pydantic.ValidationError, match="not_a_field"):
        load_mapper_config(None, ["not_a_field=1"])
    with pytest.raises(pydantic.ValidationError, match="warmup_iters"):
        load_mapper_config(None, ["iters_per_frame=10", "warmup_iters=20"])
    with pytest.raises(ValueError, match="key=value"):
        load_mapper_config(None, ["oops"])
    with pytest.raises(FileNotFoundError):
        load_mapper_config(tmp_path / "missing.yaml")


def test_ablation_rows_are_cumulative():
    rows = ablation_rows()
    assert [r[0] for r in rows] == ["none", "+SB", "+MVO", "+ROI", "+SIS", "+GFD"]
    on = [sum(vars(sw).values()) for _, sw in rows]
    assert on == [0, 1, 2, 3, 4, 5]
    assert rows[3][1].roi and rows[3][1].mvo and rows[3][1].sb and not rows[3][1].sis


def test_overrides_do_not_write_into_the_defaults_they_start_from():
    defaults = {"pose": {"refine": True}}
    assert load_mapper_config(None, ["pose.refine=false"], defaults=defaults).pose.refine is False
    assert defaults == {"pose": {"refine": True}}  # e.g. a sensor profile's mapper defaults, shared by every run
