"""One typed configuration tree for everything a GaussLite YAML file sets; its defaults are the measured settings.

``GaussLiteConfig{mapper, agent, sim, fusion}``: the mapper (:class:`gausslite.mapping.config.MapperConfig`, its
knobs grouped by prefix), the agent's mission (:class:`gausslite.mission.config.AgentConfig`), the local
two-agent simulation (:class:`SimConfig`) and the fusion server (:class:`FusionSettings`). :func:`load_config`
is the one loader of the tree: YAML, then dotted ``key=value`` overrides, then validation, so a typo fails before
anything starts; each part takes its own group (``cfg.mapper``, ``cfg.agent``, ``cfg.sim``, ``cfg.fusion``).
:func:`load_mapper_config` reads a mapper-only file (``gausslite map --config``). Old setting names (the mapper's old
flat names, and the old names of renamed settings: :data:`OLD_NAMES`) go through :func:`migrate_flat_names`, which
warns. ``gausslite config --show`` prints the effective tree, ``--schema`` its JSON schema.
"""

from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gausslite.fusion.holdout import RefineValidation
from gausslite.mapping.config import (FLAT_NAMES, OLD_MAPPER_NAMES, MapperConfig, apply_overrides, deep_merge,
                                      migrate_flat_names, read_yaml)
from gausslite.mission.config import OLD_AGENT_NAMES, AgentSections

__all__ = ["SimScene", "SimFuse", "SimConfig", "FusionSettings", "GaussLiteConfig", "load_config",
           "load_mapper_config", "migrate_flat_names", "FLAT_NAMES", "OLD_NAMES", "read_yaml", "DEFAULT_CONFIG_PATH",
           "ROLE_SECTIONS"]

#: every old setting name the tree still loads, per YAML section: old key → new key, dotted within the section (a
#: ``DeprecationWarning`` names the new key; docs/reference.md#old-setting-names, docs/mapper.md#old-flat-names)
OLD_NAMES: Dict[str, Dict[str, str]] = {"mapper": OLD_MAPPER_NAMES, "agent": OLD_AGENT_NAMES}

#: the site file shipped with the repository (compose and Kubernetes mount it); it changes no measured setting
DEFAULT_CONFIG_PATH = Path(__file__).resolve().parents[1] / "deploy" / "gausslite.yaml"


class SimScene(BaseModel):
    """The synthetic default scene of ``gausslite sim`` without ``--dataset`` (:func:`gausslite.synthetic.make_scene`).

    Attributes:
        seed: scene and trajectory seed.
        width, height: image size (pixels).
        frames: frames rendered along each robot's arc.
        novel_every: on this scene the robots' replays withhold every this many frames from their mappers, scored
            under ``novel`` (the scene's own ``agent.scoring.novel_every``; a value given for
            ``agent.scoring.novel_every`` wins). 31 frames with every second withheld: each robot maps 16 frames, the
            arc's 16 evenly spaced poses, and 15 views between them score every map on views no map trained on, so
            the answer's interval is narrow enough to read (docs/sharing.md#what-to-read-in-a-report).
    """

    model_config = ConfigDict(extra="forbid")
    seed: int = 0
    width: int = Field(320, ge=16)
    height: int = Field(240, ge=12)
    frames: int = Field(31, ge=2)
    novel_every: int = Field(2, ge=2)


class SimFuse(BaseModel):
    """How the simulation fuses (paper Sec. III-E; ``docs/sharing.md``).

    Attributes:
        voxel_size: δ of the vote (m; paper 0.10).
        contest_radius: vote neighbourhood in voxels for offline sims (0 = the paper's per-voxel rule).
        live_contest_radius: the same for live sims (``sim --realtime``).
        refine_iters: joint refinement iterations.
    """

    model_config = ConfigDict(extra="forbid")
    voxel_size: float = Field(0.10, gt=0)
    contest_radius: int = Field(1, ge=0, le=8)
    live_contest_radius: int = Field(0, ge=0, le=8)
    refine_iters: int = Field(300, ge=0)

    def settings(self, realtime: bool = False) -> dict:
        """``{"voxel_size", "contest_radius", "refine_iters"}`` of an offline or a live (``realtime``) run."""
        return {"voxel_size": self.voxel_size,
                "contest_radius": self.live_contest_radius if realtime else self.contest_radius,
                "refine_iters": self.refine_iters}


#: the two agents' task ids per default scene kind (task ids of the scene's ``tasks.json``)
DEFAULT_SIM_TASKS: Dict[str, List[str]] = {"synthetic": ["synth-pick-object", "synth-find-chair"],
                                           "room0": ["room0-pick-plant", "room0-find-ottoman"]}


class SimConfig(BaseModel):
    """``gausslite sim``: the default scene, the two agents' task ids per scene kind, fusion, the overall bound (s)."""

    model_config = ConfigDict(extra="forbid")
    scene: SimScene = SimScene()
    tasks: Dict[str, List[str]] = Field(default_factory=lambda: {k: list(v) for k, v in DEFAULT_SIM_TASKS.items()})
    fuse: SimFuse = SimFuse()
    timeout_s: float = Field(1800.0, gt=0)


class TeamMapSettings(BaseModel):
    """The team map the fusion server keeps refined while the team maps (the ``fusion.team_map`` section;
    docs/sharing.md#the-team-map-while-the-team-maps).

    Whenever an agent's latest subset or the server's keyframes change, the server waits ``settle_s`` (uploads come
    in bursts), then votes the latest subsets and refines the vote over every agent's uploaded views, validated on
    views it holds out (``refine_validation``), in a worker process at niceness ``nice``; one refinement at a time
    across every replica on the store, at most one start every ``min_interval_s``. Uploads and reads never wait for
    it. ``Fuse`` with ``team_map`` serves its latest complete version at once.

    Attributes:
        enabled: keep the team map refined (needs the refinement's extra, ``mapper``; on by default, so that
            ``Fuse`` with ``team_map`` answers on every server).
        refine_iters: the refinement's iterations at most (fewer over few views, and it stops early).
        settle_s: seconds without a new upload before a refinement starts.
        min_interval_s: seconds between the starts of two refinements.
        nice: niceness of the refinement process (0-19): the handler threads keep the cores.
        voxel_size: the vote's δ in metres (None: ``default_voxel_size``).
        contest_radius: the vote's neighbourhood in voxels (None: ``default_contest_radius``).
        seed: the refinement's seed.
        keep: team-map versions kept (they have their own retention, apart from the ``Fuse`` results).
    """

    model_config = ConfigDict(extra="forbid")
    enabled: bool = True
    refine_iters: int = Field(300, ge=1)
    settle_s: float = Field(1.0, ge=0)
    min_interval_s: float = Field(5.0, ge=0)
    nice: int = Field(10, ge=0, le=19)
    voxel_size: Optional[float] = Field(None, gt=0)
    contest_radius: Optional[int] = Field(None, ge=0, le=8)
    seed: int = 0
    keep: int = Field(4, ge=1)


class FusionSettings(BaseModel):
    """The fusion server's settings (the ``fusion`` section; ``gausslite_services.fusion_server`` serves with them).

    Attributes:
        data_dir (str): directory of the embedded SQLite store (used when ``store`` is empty).
        store (str): ``postgresql://user:pw@host:port/db`` DSN of a PostgreSQL store shared by
            replicas; empty = SQLite in ``data_dir``.
        store_pool_size (int): PostgreSQL connections per server process.
        store_acquire_timeout_s (float): PostgreSQL: how long a call waits for a database connection before
            it fails with UNAVAILABLE (the database is down or restarting; clients retry with backoff).
        max_keyframes_per_agent (int): keyframe buffer bound per agent (oldest dropped beyond it).
        max_subset_gaussians (int): largest accepted subset (RESOURCE_EXHAUSTED beyond).
        max_task_text_bytes (int): longest task text (INVALID_ARGUMENT beyond).
        default_voxel_size (float): δ in metres when a FuseRequest leaves it 0 (paper: 0.10 m).
        default_contest_radius (int): vote neighbourhood radius in voxels when a FuseRequest leaves it
            unset (0 = the paper's per-voxel rule; 1 = each voxel contested over its 3×3×3 block, what
            ``gausslite sim`` and the compose deployment request: :func:`gausslite.fusion.vote.voxel_vote`).
            An incremental update with r = 1 re-votes the 27-fold neighbourhood of what it touches.
        default_refine_iters (int): refinement iterations when a FuseRequest leaves them 0.
        max_refine_iters (int): largest accepted ``refine_iters`` (INVALID_ARGUMENT beyond).
        refine_validation (RefineValidation): the refinement's held-out check
            (:class:`gausslite.fusion.holdout.RefineValidation`): ``holdout_fraction`` of the uploaded keyframes held
            out of training and scored every ``check_every`` iterations, a stop after ``patience`` scores without a
            new best, the best state kept (the vote when nothing beat it), and at most ``per_view_iters`` iterations
            per training keyframe (``docs/sharing.md``).
        refine_options (dict): extra keyword arguments for ``refine_map`` (e.g. ``budget: {max_gaussians: N}``); they
            take precedence over ``refine_validation``.
        fused_keep_per_method (int): fused maps kept per fuse method (vote, concat), newest first: every ``Fuse``
            stores a map, so older ones are deleted (``DownloadFused`` of one is NOT_FOUND) and ``GetStats``, which
            lists the fused maps held, stays bounded.
        max_keyframe_pixels (int): largest keyframe (width × height) the server decodes; a larger one is
            INVALID_ARGUMENT before any image is decoded (default: a 4K frame; each decoded keyframe holds about
            7 bytes per pixel).
        health_probe_s (float): period of the store probe behind the health service: NOT_SERVING while the store
            cannot be reached (``gausslite_services.fusion_server.server.StoreHealth``).
        max_abs_mean_m (float), max_scale_m (float), max_abs_opacity_logit (float): plausibility bounds of pushed
            Gaussians (:func:`gausslite.fusion.check_plausible`): a mean farther than this from the map origin on any
            axis, a standard deviation above this on any axis, an opacity logit beyond ± this; an upload carrying one
            is INVALID_ARGUMENT, so one robot's absurd splat (a 1 km Gaussian) cannot spoil every fused map
            (``docs/security.md``).
        stream_idle_s (float): longest wait, seconds, for the next message of an upload stream (``UploadSubset``,
            ``UploadKeyframes``); a client that sends nothing for longer gets DEADLINE_EXCEEDED and frees its handler
            thread. What it delivered before stays as after a dropped link (an incomplete upload is resumable and
            invisible to ``Fuse``).
        max_upload_streams (int): upload streams in progress at once on one server (capped at half its handler
            threads), so stalled uploads cannot take the threads the acks, status calls and reads need. When all are
            taken, a new upload takes the slot of a stream waiting longer than ``stream_evict_idle_s`` for its next
            message (that call ends ABORTED); with none, the new upload is RESOURCE_EXHAUSTED at once.
        stream_evict_idle_s (float): how long, seconds, an upload stream must have waited for its next message
            before a new upload may take its slot when every slot is taken (a client sending its upload waits
            milliseconds between messages).
        max_upload_streams_per_caller (int): upload streams in progress at once per caller (authenticated agent id,
            else peer host); beyond it RESOURCE_EXHAUSTED, so one client cannot take every upload slot.
        team_map (TeamMapSettings): the team map kept refined in the background (on by default).
    """

    model_config = ConfigDict(extra="forbid")
    data_dir: str = "gausslite_fusion_data"
    store: str = ""
    store_pool_size: int = Field(12, ge=1)
    store_acquire_timeout_s: float = Field(5.0, gt=0)
    max_keyframes_per_agent: int = Field(64, ge=1)
    max_subset_gaussians: int = Field(4_000_000, ge=1)
    max_task_text_bytes: int = Field(4096, ge=1)
    default_voxel_size: float = Field(0.10, gt=0)
    default_contest_radius: int = Field(0, ge=0, le=8)
    default_refine_iters: int = Field(200, ge=0)
    max_refine_iters: int = Field(20000, ge=0)
    refine_validation: RefineValidation = Field(
        default_factory=RefineValidation,
        description="the refinement's held-out check: keyframes held out of training, early stop, best state kept, "
                    "iterations scaled to the training keyframes")
    refine_options: dict = Field(default_factory=dict)
    fused_keep_per_method: int = Field(32, ge=1)
    max_keyframe_pixels: int = Field(3840 * 2160, ge=1)
    health_probe_s: float = Field(2.0, gt=0)
    max_abs_mean_m: float = Field(1.0e4, gt=0)
    max_scale_m: float = Field(10.0, gt=0)
    max_abs_opacity_logit: float = Field(30.0, gt=0)
    stream_idle_s: float = Field(15.0, gt=0)
    max_upload_streams: int = Field(8, ge=1)
    stream_evict_idle_s: float = Field(1.0, gt=0)
    max_upload_streams_per_caller: int = Field(2, ge=1)
    team_map: TeamMapSettings = Field(default_factory=TeamMapSettings)

    @classmethod
    def from_file(cls, path: str | Path) -> "FusionSettings":
        """Load from a GaussLite YAML (its ``fusion`` section), or a JSON or TOML file whose keys are the fields.

        Raises:
            FileNotFoundError: missing file. ValueError: unknown keys, bad values or an unparsable file.
        """
        p = str(path)
        try:
            if p.endswith((".yaml", ".yml")):
                return load_config(p).fusion
            text = Path(p).read_text(encoding="utf-8")
            if p.endswith(".toml"):
                return cls.model_validate(tomllib.loads(text))
            return cls.model_validate(json.loads(text))
        except FileNotFoundError:
            raise
        except (ValidationError, ValueError) as e:  # parser errors, unknown keys, bad values
            raise ValueError(f"bad fusion config {path}: {e}") from e
        except Exception as e:  # noqa: BLE001 - any other parser error is a config error
            raise ValueError(f"cannot parse fusion config {path}: {e}") from e


#: the configuration sections each process runs with (:meth:`GaussLiteConfig.sections`)
ROLE_SECTIONS: Dict[str, tuple] = {"agent": ("agent", "mapper"), "fusion": ("fusion",),
                                   "sim": ("agent", "mapper", "sim", "fusion"), "all": ("agent", "mapper", "sim", "fusion")}


class GaussLiteConfig(AgentSections):
    """The whole configuration (module docstring). In YAML the mapper is a top-level section; here it is also
    ``agent.mapper``, the agent's copy, which the YAML's ``mapper`` section sets."""

    model_config = ConfigDict(extra="forbid")
    sim: SimConfig = SimConfig()
    fusion: FusionSettings = FusionSettings()

    def to_yaml_dict(self, given_only: bool = False) -> dict:
        """The configuration in the YAML's layout (``mapper`` as its own section).

        Args:
            given_only: only the settings given explicitly (in the YAML, by overrides or keywords; pydantic's
                ``exclude_unset``), the form to hand to an agent: a replayed dataset's sensor profile fills in every
                mapper setting left unset (:func:`gausslite.mapping.profiles.with_profile`), which a tree with every
                default written out would override. False: every setting, defaults included (the effective tree,
                ``gausslite config --show``).
        """
        kw = {"mode": "json", "exclude_unset": given_only}
        agent = self.agent.model_dump(exclude={"mapper"}, **kw)
        return {"agent": agent, "mapper": self.agent.mapper.model_dump(**kw),
                "sim": self.sim.model_dump(**kw), "fusion": self.fusion.model_dump(**kw)}

    def sections(self, role: str = "all") -> dict:
        """The sections one process runs with, in the YAML's layout, every default written out: what
        ``gausslite config --show --role ROLE`` prints and what ``gausslite serve ROLE`` logs at start-up
        (``effective configuration: {...}``).

        Args:
            role: ``agent`` (``agent`` and ``mapper``), ``fusion`` (``fusion``), ``sim`` or ``all`` (every section).
        Raises:
            ValueError: an unknown role.
        """
        tree = self.to_yaml_dict()
        if role not in ROLE_SECTIONS:
            raise ValueError(f"unknown role {role!r}: one of {', '.join(ROLE_SECTIONS)}")
        return {k: tree[k] for k in ROLE_SECTIONS[role]}

    @classmethod
    def json_schema(cls) -> dict:
        """JSON schema of the YAML layout."""
        schema = cls.model_json_schema()
        schema.setdefault("properties", {})["mapper"] = {"$ref": "#/$defs/MapperConfig"}
        schema.setdefault("$defs", {}).setdefault("MapperConfig", MapperConfig.model_json_schema())
        return schema


def load_config(path: Optional[str | Path] = None, overrides: Iterable[str] = ()) -> GaussLiteConfig:
    """The one loader of the configuration tree: read a GaussLite YAML file, apply dotted ``key=value`` overrides
    (``agent.push.every=3``, ``mapper.iters_per_frame=5``, ``sim.fuse.refine_iters=100``) and validate. Each part
    takes its own group: ``cfg.mapper`` (the mapper), ``cfg.agent`` (an agent's mission), ``cfg.sim``
    (``gausslite sim``), ``cfg.fusion`` (the fusion server).

    The models' defaults are the measured settings (docs/results.md): ``gausslite serve``, ``gausslite sim``,
    compose and Kubernetes run the same mapper, sharing and team map with or without a file, which holds only what
    a site changes (``deploy/gausslite.yaml``).

    Args:
        path: the YAML file; None = no file, every section at its model's defaults.
        overrides: dotted ``key=value`` strings, values parsed as YAML, applied in order after the file.
    Returns:
        The validated tree. Old setting names (:data:`OLD_NAMES`) go through :func:`migrate_flat_names` (a
        ``DeprecationWarning`` naming the new key).
    Raises:
        FileNotFoundError: missing file. ValueError: not a mapping, or a bad override.
        pydantic.ValidationError: unknown keys or bad values (the message names them).
    """
    data: dict = {} if path is None else read_yaml(path)
    return GaussLiteConfig.model_validate(apply_overrides(data, list(overrides)))


def load_mapper_config(path: Optional[str | Path] = None, overrides: Iterable[str] = (), *,
                       defaults: Optional[dict] = None, **fields: Any) -> MapperConfig:
    """The mapper's settings alone (``gausslite map`` and ``gausslite ablate``; a Python caller of the mapper), from
    a mapper-only YAML file whose top-level keys are :class:`MapperConfig` fields (the ``mapper`` section of a
    GaussLite YAML, as its own file; the whole tree's mapper is ``load_config(...).mapper``).

    Layers, lowest first: ``defaults`` (e.g. a sensor profile's), the file, ``key=value`` overrides (dotted keys
    reach groups: ``seeding.seeds_per_frame=800``), then keyword fields (``iters_per_frame=20``,
    ``seeding={"seeds_per_frame": 800}``). Groups are merged key by key; a keyword field that is None counts as not
    given.

    Raises:
        FileNotFoundError: ``path`` does not exist. ValueError: a bad override.
        pydantic.ValidationError: unknown keys or invalid values (the message names the field).
    """
    data: dict = copy.deepcopy(defaults or {})  # the overrides below write into nested groups in place
    if path is not None:
        data = deep_merge(data, read_yaml(path))
    data = apply_overrides(data, overrides)
    data = deep_merge(data, _given(fields))
    return MapperConfig.model_validate(data)


def _given(fields: dict) -> dict:
    """``fields`` without the None values (in groups too) and without groups left empty."""
    out = {}
    for k, v in fields.items():
        if isinstance(v, dict):
            v = _given(v)
            if not v:
                continue
        if v is not None:
            out[k] = v
    return out
