"""Typed mapper configuration with defaults from the paper (Sec. III-C/III-D).

The loaders live in :mod:`gausslite.config`: :func:`gausslite.config.load_config` reads the whole GaussLite YAML
(its ``mapper`` section is ``cfg.mapper``), :func:`gausslite.config.load_mapper_config` a mapper-only file
(``gausslite map --config``). Both override single fields with ``key=value`` strings (dotted keys reach nested
groups, e.g. ``lr.means=2e-4``, ``seeding.seeds_per_frame=800``). Settings named by their old flat names
(:data:`FLAT_NAMES`) or by the old names of renamed settings (:data:`RENAMED_MAPPER_KEYS`) are moved to their keys by
:func:`migrate_flat_names`, with a ``DeprecationWarning``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Literal, Optional

import yaml
from pydantic import Field, model_validator

# the sections and the old-name migration live in modules of their own; imported from here as before
from gausslite.mapping.config_names import FLAT_NAMES, OLD_MAPPER_NAMES, RENAMED_MAPPER_KEYS, migrate_flat_names
from gausslite.mapping.config_sections import (BudgetConfig, ComponentSwitches, DensifyConfig, DetailConfig,
                                               LearningRates, PerformanceConfig, PoseConfig, RoiViewConfig,
                                               SeedingConfig, SensorConfig, StrictModel, WorkCostConfig)

__all__ = ["MapperConfig", "apply_overrides", "read_yaml", "deep_merge", "ablation_rows",
           "FLAT_NAMES", "RENAMED_MAPPER_KEYS", "OLD_MAPPER_NAMES", "migrate_flat_names", "StrictModel",
           "LearningRates", "DensifyConfig", "WorkCostConfig", "ComponentSwitches", "SeedingConfig", "BudgetConfig",
           "PoseConfig", "SensorConfig", "RoiViewConfig", "DetailConfig", "PerformanceConfig"]


class MapperConfig(StrictModel):
    """Mapper configuration. Defaults: paper values where it gives them, tuned otherwise.

    ``mode='uniform'`` is the baseline: relevance is ignored for seeding and optimisation (every
    component switch is treated as off). ``mode='gausslite'`` applies the switches in
    ``components``. Both modes share the Gaussian budget (``budget.max_gaussians``), seeds per frame
    (``seeding.seeds_per_frame``) and iterations per frame (``iters_per_frame``): the matched-budget
    comparison of paper Sec. IV.

    The settings of one concern are grouped: ``seeding``, ``budget``, ``pose``, ``sensor``, ``performance``,
    ``densify``, ``lr``, ``components``, ``roi_views``, ``detail``. Input that names a grouped setting by its old flat
    name (``max_gaussians``, ``pose_refine``, …: :data:`FLAT_NAMES`) or a renamed setting by its old name
    (``max_keyframes``, ``keyframe_every``: :data:`RENAMED_MAPPER_KEYS`) is migrated by :func:`migrate_flat_names`,
    with a warning.
    """

    mode: Literal["uniform", "gausslite"] = "uniform"
    seed: int = 0
    device: str = "cpu"
    backend: Literal["auto", "warp", "torch", "gsplat"] = "auto"
    iters_per_frame: int = Field(30, ge=1, description="Adam iterations per mapped frame")
    keyframe_budget_s: Optional[float] = Field(
        None, gt=0, description="online agent: wall-clock seconds per mapped keyframe (seeding included); "
        "iterations run until it is spent instead of iters_per_frame. None = iters_per_frame (offline map/ablate "
        "keep this for matched-budget comparisons)"
    )
    budget_clock: Literal["wall", "work"] = Field(
        "wall", description="clock of keyframe_budget_s and of optimize/finalize time bounds: 'wall' = wall time "
        "(a live robot); 'work' = the deterministic twin, modelled seconds of the work done (work_cost; "
        "gausslite.mapping.budget), for tests and reproducible budget studies"
    )
    work_cost: WorkCostConfig = WorkCostConfig()
    warmup_iters: int = Field(
        10, ge=0, description="ROI phase: full-image iterations before the active-only phase"
    )
    window: int = Field(8, ge=1, description="recent-keyframe window of view sampling")
    recent_prob: float = Field(
        0.5, ge=0, le=1, description="view sampling: probability of a draw from the recent window; otherwise "
        "the draw is over the whole mission's keyframes (MonoGS-style window + random past keyframes)"
    )
    roi_covis_weight: float = Field(
        2.0, ge=0, description="MVO mission-wide draws: keyframes that see the ROI weigh 1 + this (gausslite "
        "mode with MVO), the others 1"
    )
    stored_keyframes_max: int = Field(
        600, ge=1, description="keyframes the mapper's keyframe store keeps for the view draws and the final pass "
        "(compact: uint8 colour, float16 depth); beyond, the old keyframe closest in pose to its predecessor is dropped"
    )
    store_keyframe_every: int = Field(
        1, ge=1, description="every k-th mapped frame is stored in the keyframe store (the others are fitted "
        "while they are mapped only)"
    )
    current_frame_prob: float = Field(
        0.5, ge=0, le=1, description="without MVO: probability that an iteration uses the current frame"
    )
    final_iters: int = Field(
        0, ge=0, description="extra iterations over all keyframes after the last frame (0 = none)"
    )
    final_iters_per_keyframe: float = Field(
        0.0, ge=0, description="more final iterations: this many per keyframe, added to final_iters (the "
        "hand-held profile sets 20, the rendered one 5)"
    )
    final_schedule: Literal["full", "mapping"] = Field(
        "full", description="final pass iterations: 'full' = full-image, all Gaussians (both modes); 'mapping' = "
        "the mapping schedule in gausslite mode (per iters_per_frame final iterations, warmup_iters full-image, the "
        "rest ROI-phase on keyframes that see the ROI; uniform mode stays full-image)"
    )
    footprint_alpha: float = Field(
        0.5, ge=0, le=1, description="ROI phase: pixels with rendered alpha above this are the footprint"
    )
    roi_render: Literal["context", "active", "alternate"] = Field(
        "context", description="ROI phase render. 'active': the active Gaussians alone (the paper's wording); "
        "'context': every Gaussian, inactive ones frozen (no update, no κ), so the active ones are fitted to "
        "the pixels the full map shows; 'alternate': the two on successive ROI-phase iterations (measured: "
        "docs/results.md)"
    )
    roi_update: Literal["active", "visible", "all"] = Field(
        "visible", description="ROI phase: which Gaussians the Adam step updates: 'visible' (default: every "
        "Gaussian the ROI render draws, so inactive ones covering ROI pixels are fitted too; the others keep their "
        "values and moments; live under a keyframe budget 'active' loses to uniform: docs/realtime.md); 'active' "
        "(a = 1, the paper's rule); 'all' (a full Adam step). κ counts active Gaussians only"
    )
    roi_min_iters: int = Field(
        2, ge=0, description="ROI schedule: iterations of each keyframe the task region is owed, however few the "
        "budget buys: the warm-up ends early to leave this many, and the ROI phase's first this-many draws are among "
        "the keyframes that see the ROI (docs/mapper.md \"The ROI schedule\"); 0: the plain split"
    )
    roi_phase_views: Literal["any", "roi"] = Field(
        "any", description="ROI phase: the view is drawn as in the warm-up ('any'; a drawn view without ROI pixels "
        "gets a full-image iteration) or among the keyframes that see the ROI ('roi'; same recent-window / mission "
        "split, MVO)"
    )
    roi_loss: Literal["roi", "crop"] = Field(
        "roi", description="ROI phase loss: on ROI pixels inside the rendered footprint ('roi', the paper's Eq. 1 "
        "restriction) or on every pixel of the ROI crop ('crop': the ROI's box and roi_crop_pad around it, so "
        "Gaussians fitted to ROI pixels cannot spread over their neighbours unpenalised)"
    )
    roi_crop_pad: int = Field(
        8, ge=0, description="ROI phase: render only the ROI bounding box grown by this many pixels"
    )
    roi_outside_alpha: float = Field(
        0.0, ge=0, description="ROI phase: weight of a penalty on the rendered alpha of the crop's pixels outside the "
        "ROI (grown by roi_outside_margin_px), added to Eq. 1, so that what the step fits draws its ROI and nothing "
        "beside it. 0 = off (the mapper's own map: the background there is the map's). The share fine-tune "
        "(gausslite.sharing.finetune_subset) sets it: a subset rendered alone must not spread over its neighbours in a "
        "fused map (docs/sharing.md)"
    )
    roi_outside_margin_px: int = Field(
        2, ge=0, description="roi_outside_alpha: pixels around the ROI left out of the penalty (its anti-aliased edge)"
    )
    lambda_depth: float = Field(1.0, ge=0, description="λ_d in L = L1_c + λ_d L1_d + λ_s (1-SSIM)")
    roi_lambda_depth: Optional[float] = Field(
        None, ge=0, description="ROI phase: λ_d of ROI-phase iterations (depth supervision weighted up where the task "
        "is, against fitting few views' colour alone); None = lambda_depth"
    )
    roi_iso_weight: float = Field(
        0.0, ge=0, description="ROI phase: weight of an isotropy regulariser on the Gaussians the step updates, the "
        "mean |s - mean(s)| of their scales in metres (Gaussian-SLAM's isotropic term, Yugay et al. 2023), against "
        "needle-like Gaussians that fit their training views only; 0 = off"
    )
    lambda_ssim: float = Field(0.2, ge=0, description="λ_s")
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    lr: LearningRates = LearningRates()
    densify: DensifyConfig = DensifyConfig()
    components: ComponentSwitches = ComponentSwitches()
    seeding: SeedingConfig = SeedingConfig()
    budget: BudgetConfig = BudgetConfig()
    pose: PoseConfig = PoseConfig()
    sensor: SensorConfig = SensorConfig()
    performance: PerformanceConfig = PerformanceConfig()
    roi_views: RoiViewConfig = RoiViewConfig()
    detail: DetailConfig = DetailConfig()

    @model_validator(mode="before")
    @classmethod
    def _group_flat_names(cls, data: Any) -> Any:
        """Old names to their keys now (:func:`migrate_flat_names`, which warns)."""
        return migrate_flat_names(data)

    @model_validator(mode="after")
    def _check(self) -> "MapperConfig":
        if self.warmup_iters > self.iters_per_frame:
            raise ValueError(
                f"warmup_iters ({self.warmup_iters}) must not exceed iters_per_frame ({self.iters_per_frame})"
            )
        return self

    def effective(self) -> ComponentSwitches:
        """Switches actually in force: all off in uniform mode."""
        if self.mode == "uniform":
            return ComponentSwitches(sb=False, mvo=False, roi=False, sis=False, gfd=False)
        return self.components


def _coerce(text: str) -> Any:
    return yaml.safe_load(text)


def apply_overrides(data: dict, overrides: Iterable[str]) -> dict:
    """Apply ``key=value`` overrides (dotted keys, YAML-typed values) to a config dict.

    Raises:
        ValueError: an override without ``=``.
    """
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override must look like key=value, got {item!r}")
        key, value = item.split("=", 1)
        node = data
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"override {item!r}: {p} is not a section")
        node[parts[-1]] = _coerce(value)
    return data


def read_yaml(path: str | Path) -> dict:
    """The mapping at the top of a YAML file (the one reader of GaussLite configuration files).

    Raises:
        FileNotFoundError: missing file. ValueError: the top level is not a mapping.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    data = yaml.safe_load(p.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{p}: top level must be a mapping, got {type(data).__name__}")
    return data


def deep_merge(base: dict, top: dict) -> dict:
    """``base`` updated by ``top`` section by section (nested dicts merged, other values replaced); a new dict.
    Neither input is modified."""
    out = dict(base)
    for k, v in top.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def ablation_rows() -> list[tuple[str, ComponentSwitches]]:
    """The paper's Table 3 rows, enabling SB, MVO, ROI, SIS, GFD cumulatively."""
    names = ["sb", "mvo", "roi", "sis", "gfd"]
    rows = [("none", ComponentSwitches(sb=False, mvo=False, roi=False, sis=False, gfd=False))]
    on: dict[str, bool] = {n: False for n in names}
    for n in names:
        on[n] = True
        rows.append(("+" + n.upper(), ComponentSwitches(**on)))
    return rows
