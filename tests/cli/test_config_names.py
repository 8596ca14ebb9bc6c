"""A configuration name means one thing across the tree: the renamed settings (``docs/reference.md#old-setting-names``:
the keyframe bounds, unique leaf names; the share and push settings, grouped under ``agent.share`` and
``agent.push``) have their old names gone from the models, ``gausslite config --show`` and ``--schema``, and every old
name still loads (YAML file, ``--set``, keyword argument) to its new key with a ``DeprecationWarning`` naming it."""

from __future__ import annotations

import json
import re
import typing
import warnings
from collections import defaultdict
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel, ValidationError

from gausslite.cli import main
from gausslite.config import FLAT_NAMES, OLD_NAMES, GaussLiteConfig, load_config, load_mapper_config
from gausslite.mapping.config import MapperConfig
from gausslite.mission.config import AgentConfig

ROOT = Path(__file__).resolve().parents[2]
#: the renamed keyframe bounds: (section, old key, new key), keys dotted within the section; each new leaf name is
#: unique in the tree
KEYFRAME_BOUNDS = [("mapper", "max_keyframes", "stored_keyframes_max"),
                   ("mapper", "keyframe_every", "store_keyframe_every"),
                   ("agent", "max_keyframes", "upload_backlog_max"),
                   ("agent", "keyframe_every", "upload_keyframe_every"),
                   ("agent", "odometry.max_keyframes", "odometry.reference_keyframes_max"),
                   ("agent", "odometry.loop.max_keyframes", "odometry.loop.keyframe_images_max")]
#: the share and push settings, grouped: old agent key → (new key, a value other than the default)
SHARE_AND_PUSH = {"share": ("share.rule", "active"), "kappa_threshold": ("share.kappa_threshold", 4),
                  "share_coverage": ("share.coverage", 0.9), "share_candidates": ("share.candidates", "active"),
                  "share_max_fraction": ("share.max_fraction", 0.5), "share_held_weight": ("share.held_weight", 2.0),
                  "share_finetune_iters": ("share.finetune_iters", 50), "share_refresh": ("share.refresh", 0.2),
                  "share_outside_alpha": ("share.outside_alpha", 1.0), "share_worker": ("share.worker", "thread"),
                  "share_worker_start": ("share.worker_start", "mission"), "push_every": ("push.every", 3),
                  "delta_push": ("push.delta", False), "delta_tolerance": ("push.delta_tolerance", 4.0),
                  "chunk_gaussians": ("push.chunk_gaussians", 1000),
                  "final_push_timeout_s": ("push.final_timeout_s", 30.0),
                  "backoff_s": ("push.backoff_s", 0.5), "max_backoff_s": ("push.max_backoff_s", 9.0),
                  "pusher_nice": ("push.nice", 5)}
#: every renamed setting: (section, old key, new key)
RENAMED = KEYFRAME_BOUNDS + [("agent", old, new) for old, (new, _) in SHARE_AND_PUSH.items()]
#: old leaf names no field of the tree has any more
OLD_LEAVES = {"max_keyframes", "keyframe_every", "share_coverage", "share_candidates", "share_max_fraction",
              "share_held_weight", "share_finetune_iters", "share_refresh", "share_outside_alpha", "share_worker",
              "share_worker_start", "push_every", "delta_push", "final_push_timeout_s", "pusher_nice"}


def _nested(key: str, value) -> dict:
    """``{"a": {"b": value}}`` of the dotted ``key`` ``a.b``."""
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def _at(tree: dict, key: str):
    for part in key.split("."):
        tree = tree[part]
    return tree


def _models(annotation) -> list:
    """The pydantic model classes a field's annotation holds (itself, or inside Optional / Union / containers)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


def leaf_paths(model: type, prefix: str = "") -> dict:
    """``{leaf name: [dotted paths]}`` of every field of ``model`` and of the models nested in it."""
    out = defaultdict(list)
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        out[name].append(path)
        for sub in _models(field.annotation):
            for leaf, paths in leaf_paths(sub, path + ".").items():
                out[leaf] += paths
    return out


def _keys(tree) -> set:
    """Every key of a nested dict / list (a ``--show`` tree or a JSON schema)."""
    if isinstance(tree, dict):
        return set(tree) | {k for v in tree.values() for k in _keys(v)}
    if isinstance(tree, list):
        return {k for v in tree for k in _keys(v)}
    return set()


def test_the_renamed_settings_are_the_code_tables():
    renamed = {(s, old, new) for s, table in OLD_NAMES.items() for old, new in table.items()
               if not (s == "mapper" and old in FLAT_NAMES)}
    assert renamed == set(RENAMED)


def test_no_two_fields_of_the_tree_share_a_renamed_leaf_name():
    leaves = leaf_paths(GaussLiteConfig)
    assert "agent.mapper.seeding.seeds_per_frame" in leaves["seeds_per_frame"]  # the walk reaches nested groups
    assert not OLD_LEAVES & set(leaves), {k: leaves[k] for k in OLD_LEAVES & set(leaves)}
    for section, _, new in KEYFRAME_BOUNDS:
        leaf = new.rsplit(".", 1)[-1]
        assert leaves[leaf] == [f"agent.{new}" if section == "agent" else f"agent.mapper.{new}"], leaf
    # the other keyframe bounds keep names of their own
    assert leaves["max_keyframes_per_agent"] == ["fusion.max_keyframes_per_agent"]


def test_config_show_and_schema_print_the_new_names(capsys):
    assert main(["config", "--show"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert main(["config", "--schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    for section, _, new in RENAMED:
        assert _at(shown[section], new) is not None
        assert new.rsplit(".", 1)[-1] in _keys(schema)
    assert not OLD_LEAVES & _keys(shown) and not OLD_LEAVES & _keys(schema)


@pytest.mark.parametrize("section, old, new", RENAMED)
def test_an_old_name_loads_to_its_new_key_with_a_warning_naming_it(section, old, new, tmp_path, caplog):
    default = _at(load_config().to_yaml_dict()[section], new)
    value = SHARE_AND_PUSH[old][1] if section == "agent" and old in SHARE_AND_PUSH else default + 3
    assert value != default
    warning = re.escape(f"{old} -> {new}")
    f = tmp_path / "old.yaml"
    f.write_text(yaml.safe_dump({section: _nested(old, value)}))
    with pytest.warns(DeprecationWarning, match=warning):
        from_file = load_config(f)
    with pytest.warns(DeprecationWarning, match=warning):
        from_set = load_config(None, [f"{section}.{old}={value}"])
    for cfg in (from_file, from_set):
        given = cfg.to_yaml_dict(given_only=True)[section]
        assert _at(given, new) == value and _at(cfg.to_yaml_dict()[section], new) == value
        assert not OLD_LEAVES & _keys(given)
    assert f"{old} -> {new}" in caplog.text  # and a warning log line
    # the new key loads without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _at(load_config(None, [f"{section}.{new}={value}"]).to_yaml_dict()[section], new) == value
    # an old name from a later layer (--set over the file) wins, as for the mapper's old flat names
    f.write_text(yaml.safe_dump({section: _nested(new, value)}))
    with pytest.warns(DeprecationWarning, match=warning):
        assert _at(load_config(f, [f"{section}.{old}={default}"]).to_yaml_dict()[section], new) == default


def test_old_names_as_keyword_arguments_and_in_a_mapper_only_file(tmp_path):
    with pytest.warns(DeprecationWarning, match=r"old agent setting names.*max_keyframes -> upload_backlog_max"):
        cfg = AgentConfig(max_keyframes=5, odometry={"loop": {"max_keyframes": 9}})
    assert cfg.upload_backlog_max == 5 and cfg.odometry.loop.keyframe_images_max == 9
    assert cfg.odometry.reference_keyframes_max == 64  # only what was given moves
    with pytest.warns(DeprecationWarning, match=r"old mapper setting names.*keyframe_every -> store_keyframe_every"):
        assert MapperConfig(keyframe_every=2).store_keyframe_every == 2
    f = tmp_path / "mapper.yaml"
    f.write_text(yaml.safe_dump({"max_keyframes": 200, "max_gaussians": 5000}))
    both = r"(?=.*max_keyframes -> stored_keyframes_max)(?=.*max_gaussians -> budget\.max_gaussians)"
    with pytest.warns(DeprecationWarning, match=both):
        m = load_mapper_config(f)
    assert (m.stored_keyframes_max, m.budget.max_gaussians) == (200, 5000)


def test_old_share_and_push_names_together_load_into_their_sections(tmp_path):
    """The old spellings of one file, in any order (the flat share_* names before or after the rule given as the
    value of ``share``), land in ``agent.share`` / ``agent.push``; an old name given beside a section written with the
    new keys moves into it."""
    f = tmp_path / "old.yaml"
    f.write_text("agent:\n  share_coverage: 0.9\n  share: kappa\n  kappa_threshold: 3\n  push_every: 2\n"
                 "  pusher_nice: 0\n  share_worker: thread\n")
    with pytest.warns(DeprecationWarning, match=r"share -> share\.rule.*share_coverage -> share\.coverage"):
        agent = load_config(f).agent
    assert (agent.share.rule, agent.share.coverage, agent.share.kappa_threshold, agent.share.worker) == \
        ("kappa", 0.9, 3, "thread")
    assert (agent.push.every, agent.push.nice) == (2, 0)
    assert agent.share.max_fraction == 0.25  # what was not given keeps its default
    with pytest.warns(DeprecationWarning, match=r"share -> share\.rule, .*push_every -> push\.every"):
        cfg = AgentConfig(share="active", share_refresh=0.5, push_every=7, final_push_timeout_s=9)
    assert (cfg.share.rule, cfg.share.refresh, cfg.push.every, cfg.push.final_timeout_s) == ("active", 0.5, 7, 9)
    with pytest.warns(DeprecationWarning, match=r"share_refresh -> share\.refresh"):
        cfg = AgentConfig(share={"rule": "kappa", "coverage": 0.8}, share_refresh=0.5, push={"every": 4}, backoff_s=1)
    assert (cfg.share.rule, cfg.share.coverage, cfg.share.refresh, cfg.push.every, cfg.push.backoff_s) == \
        ("kappa", 0.8, 0.5, 4, 1.0)
    with warnings.catch_warnings():  # the new spelling alone warns about nothing
        warnings.simplefilter("error")
        assert load_config(None, ["agent.share.rule=active", "agent.push.every=3"]).agent.share.rule == "active"
    with pytest.warns(DeprecationWarning), pytest.raises(ValidationError, match="rule"):
        AgentConfig(share="everything")


def test_an_old_name_into_a_section_that_is_not_a_mapping_is_a_clear_error():
    with pytest.warns(DeprecationWarning), pytest.raises(ValidationError, match=r"mapper\.budget must be a section"):
        MapperConfig(max_gaussians=5000, budget=7)


def test_the_documented_renames_are_the_ones_the_code_applies():
    text = (ROOT / "docs" / "reference.md").read_text(encoding="utf-8")
    section = text.split("### Old setting names", 1)[1].split("\n#", 1)[0]
    rows = dict(re.findall(r"^\| `([\w.]+)` \| `([\w.]+)` \|", section, flags=re.M))
    assert rows == {f"{s}.{old}": f"{s}.{new}" for s, old, new in RENAMED}
