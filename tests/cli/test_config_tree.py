"""One typed configuration tree (gausslite.config) and ``gausslite config``."""

from __future__ import annotations

import json

import pytest
import yaml
from pydantic import ValidationError

from gausslite.cli import main
from gausslite.config import DEFAULT_CONFIG_PATH, GaussLiteConfig, load_config


def test_the_defaults_are_the_measured_settings_and_overrides_reach_every_section():
    cfg = load_config()
    assert cfg.mapper is cfg.agent.mapper and cfg.mapper.mode == "gausslite"
    # the measured settings (docs/results.md): task sharing bounded at 25 %, the ROI phase fitting what the ROI draws,
    # the team map kept refined, the novel-view protocol scored
    assert (cfg.agent.share.rule, cfg.agent.share.candidates, cfg.agent.share.max_fraction) == ("task", "rendered", 0.25)
    assert (cfg.mapper.roi_update, cfg.mapper.iters_per_frame, cfg.mapper.seeding.seeds_per_frame) == ("visible", 30, 1500)
    assert cfg.fusion.team_map.enabled and "novel" in cfg.agent.scoring.protocols
    assert cfg.sim.fuse.voxel_size == 0.10 and cfg.sim.tasks["synthetic"] == ["synth-pick-object", "synth-find-chair"]
    # the shipped site file changes none of them
    assert load_config(DEFAULT_CONFIG_PATH).to_yaml_dict() == cfg.to_yaml_dict()
    cfg = load_config(None, ["mapper.iters_per_frame=12", "agent.push.every=3", "sim.fuse.refine_iters=100",
                             "fusion.max_keyframes_per_agent=8"])
    assert (cfg.mapper.iters_per_frame, cfg.agent.push.every, cfg.sim.fuse.refine_iters,
            cfg.fusion.max_keyframes_per_agent) == (12, 3, 100, 8)


def test_typos_fail_before_anything_starts(tmp_path):
    with pytest.raises(ValidationError, match="pushevery"):
        load_config(None, ["agent.pushevery=3"])
    with pytest.raises(ValidationError):
        load_config(None, ["sim.fuse.contest_radius=-1"])
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump({"agent": {}, "mappper": {}}))
    with pytest.raises(ValidationError, match="mappper"):
        load_config(f)


def test_show_prints_the_effective_tree_and_schema_its_json_schema(capsys, tmp_path):
    assert main(["config", "--show", "--set", "mapper.iters_per_frame=11"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert set(shown) == {"agent", "mapper", "sim", "fusion"} and shown["mapper"]["iters_per_frame"] == 11
    f = tmp_path / "again.yaml"
    f.write_text(yaml.safe_dump(shown))
    assert load_config(f).to_yaml_dict() == shown  # the printed tree loads back to itself
    assert main(["config", "--schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert {"agent", "mapper", "sim", "fusion"} <= set(schema["properties"])
    assert main(["config", "--show", "--set", "agent.nope=1"]) == 2


def test_fusion_server_reads_the_fusion_section(tmp_path):
    from gausslite_services.fusion_server.server import FusionConfig

    f = tmp_path / "g.yaml"
    f.write_text(yaml.safe_dump({"fusion": {"max_keyframes_per_agent": 9}}))
    assert FusionConfig.from_file(str(f)).max_keyframes_per_agent == 9
    j = tmp_path / "f.json"
    j.write_text(json.dumps({"max_keyframs_per_agent": 9}))
    with pytest.raises(ValueError, match="max_keyframs_per_agent"):
        FusionConfig.from_file(str(j))
    assert isinstance(GaussLiteConfig().fusion.refine_options, dict)


def test_the_tree_handed_to_an_agent_leaves_the_dataset_profile_its_defaults():
    """``to_yaml_dict(given_only=True)`` (what ``gausslite sim`` writes for its agents) keeps only the settings given,
    so a replayed TUM sequence still gets the hand-held profile (depth weight 0.3, exposure compensation, a final
    pass); the effective tree, with every default written out, would set them back to the generic defaults."""
    from gausslite.mapping.profiles import profile_for_layout, with_profile

    cfg = load_config(None, ["mapper.iters_per_frame=17"])
    given = cfg.to_yaml_dict(given_only=True)
    assert given["mapper"]["iters_per_frame"] == 17 and "lambda_depth" not in given["mapper"]
    handheld = profile_for_layout("tum")
    m = with_profile(GaussLiteConfig.model_validate(given).agent.mapper, handheld)
    assert (m.lambda_depth, m.sensor.exposure_comp, m.final_iters_per_keyframe, m.iters_per_frame) == (0.3, True,
                                                                                                        20.0, 17)
    full = with_profile(GaussLiteConfig.model_validate(cfg.to_yaml_dict()).agent.mapper, handheld)
    assert (full.lambda_depth, full.sensor.exposure_comp) == (1.0, False)  # why the agents get the given settings
    # both forms load back to the same effective settings
    assert GaussLiteConfig.model_validate(given).to_yaml_dict() == cfg.to_yaml_dict()
