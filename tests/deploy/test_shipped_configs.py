"""Every YAML file shipped in the repository (outside ``tests/``) parses, and every GaussLite configuration among them
(and among the YAML examples of the docs) loads into the typed tree with warnings turned into errors: no old setting
name (an old flat mapper name, ``docs/mapper.md#old-flat-names``, or the old name of a renamed setting,
``docs/reference.md#old-setting-names``) and no other deprecation."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
import yaml

from gausslite.config import OLD_NAMES, GaussLiteConfig, load_config, load_mapper_config
from gausslite.mapping.config import MapperConfig

ROOT = Path(__file__).resolve().parents[2]
#: the sections of a GaussLite YAML (``mapper`` is one of them: the tree holds it as ``agent.mapper``)
SECTIONS = set(GaussLiteConfig().to_yaml_dict())
SKIP_DIRS = {"tests", "runs", "node_modules", "__pycache__"}


def shipped_yaml() -> list:
    """The repository's YAML files, outside ``tests/``, hidden folders and run outputs."""
    out = []
    for path in sorted(ROOT.rglob("*")):
        rel = path.relative_to(ROOT)
        if path.suffix not in (".yaml", ".yml") or not path.is_file():
            continue
        if any(p.startswith(".") or p in SKIP_DIRS for p in rel.parts[:-1]):
            continue
        out.append(rel)
    return out


def _kind(doc) -> str | None:
    """``tree`` for a GaussLite YAML (:data:`SECTIONS`), ``mapper`` for a mapper-only file (fields
    of :class:`MapperConfig`, old names included), None for anything else (compose, Kubernetes, tokens)."""
    if not isinstance(doc, dict) or not doc:
        return None
    if set(doc) <= SECTIONS:
        return "tree"
    if set(doc) <= set(MapperConfig.model_fields) | set(OLD_NAMES["mapper"]):
        return "mapper"
    return None


def _embedded(doc) -> list:
    """GaussLite configurations carried as text inside a YAML document (a Kubernetes ConfigMap's ``data``)."""
    if not isinstance(doc, dict) or doc.get("kind") != "ConfigMap":
        return []
    return [yaml.safe_load(v) for v in (doc.get("data") or {}).values() if isinstance(v, str)]


def load_strictly(data: dict, kind: str) -> None:
    """Validate ``data`` as a configuration of ``kind`` with every warning an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if kind == "tree":
            GaussLiteConfig.model_validate(data)
        else:
            MapperConfig.model_validate(data)


def test_every_shipped_config_loads_without_a_warning():
    """Each configuration of the shipped YAML files, of ConfigMaps in them and of the docs' YAML examples."""
    files = shipped_yaml()
    assert Path("deploy/gausslite.yaml") in files and Path("deploy/docker-compose.yml") in files
    loaded = []
    for rel in files:
        docs = list(yaml.safe_load_all((ROOT / rel).read_text(encoding="utf-8")))  # every file parses
        for doc in docs + [d for doc in docs for d in _embedded(doc)]:
            kind = _kind(doc)
            if kind is not None:
                load_strictly(doc, kind)
                loaded.append(str(rel))
    # the YAML examples of the docs that are configurations
    for md in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "deploy").rglob("*.md"))]:
        for block in re.findall(r"```ya?ml\n(.*?)```", md.read_text(encoding="utf-8"), flags=re.S):
            doc = yaml.safe_load(block)
            if _kind(doc) is not None:
                load_strictly(doc, _kind(doc))
                loaded.append(md.name)
    # the site file sets nothing (the models' defaults are the measured settings) and its commented example loads
    site = ROOT / "deploy" / "gausslite.yaml"
    assert yaml.safe_load(site.read_text(encoding="utf-8")) == {}
    example_doc = yaml.safe_load(_commented_example(site.read_text(encoding="utf-8")))
    assert set(example_doc) == {"agent", "fusion"}
    load_strictly(example_doc, "tree")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_config(site)
        load_config()


def _commented_example(text: str) -> str:
    """The YAML example of a commented-out file: the ``# `` lines from the first ``section:`` line to the next prose
    line (a comment line that is not indented YAML and not a ``key:`` line)."""
    out, inside = [], False
    for line in text.splitlines():
        if not line.startswith("#"):
            continue
        body = line[2:] if line.startswith("# ") else line[1:]
        if re.match(r"^[a-z_]+:\s*$", body):
            inside = True
        elif inside and not body.startswith(" "):
            break
        if inside:
            out.append(body)
    return "\n".join(out)


def test_the_check_fails_on_an_old_name(tmp_path):
    flat = {"mapper": {"max_gaussians": 5000, "budget": {"cap": 9000}}}
    assert _kind(flat) == "tree" and _kind(flat["mapper"]) == "mapper"
    with pytest.raises(DeprecationWarning, match=r"max_gaussians -> budget\.max_gaussians"):
        load_strictly(flat, "tree")
    with pytest.raises(DeprecationWarning):
        load_strictly({"pose_refine": True}, "mapper")
    # and on the old name of a renamed setting, in any section
    with pytest.raises(DeprecationWarning, match=r"max_keyframes -> upload_backlog_max"):
        load_strictly({"agent": {"max_keyframes": 128}}, "tree")
    with pytest.raises(DeprecationWarning, match=r"loop\.max_keyframes -> odometry\.loop\.keyframe_images_max"):
        load_strictly({"agent": {"odometry": {"loop": {"max_keyframes": 500}}}}, "tree")
    assert _kind({"max_keyframes": 200}) == "mapper"
    with pytest.raises(DeprecationWarning, match=r"max_keyframes -> stored_keyframes_max"):
        load_strictly({"max_keyframes": 200}, "mapper")
    f = tmp_path / "mapper.yaml"
    f.write_text(yaml.safe_dump({"budget": {"max_gaussians": 5000}}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mapper_config(f).budget.max_gaussians == 5000
    assert _kind({"services": {"fusion": {}}}) is None  # a compose file is no configuration
