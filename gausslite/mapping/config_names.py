"""Old setting names and their migration to the keys of now: the mapper's old flat names (:data:`FLAT_NAMES`), its
renamed settings (:data:`RENAMED_MAPPER_KEYS`), and :func:`migrate_flat_names`, which :class:`MapperConfig
<gausslite.mapping.config.MapperConfig>` and :class:`gausslite.mission.config.AgentConfig` apply to their input
(docs/reference.md#old-setting-names). :mod:`gausslite.mapping.config` re-exports them.
"""

from __future__ import annotations

import logging
import warnings
from typing import Any, Optional

from pydantic import BaseModel

log = logging.getLogger(__name__)

__all__ = ["FLAT_NAMES", "RENAMED_MAPPER_KEYS", "OLD_MAPPER_NAMES", "migrate_flat_names"]


#: old flat setting name → (group, name in the group), from before the settings were grouped. Input that still uses
#: one (YAML, ``--set``, keyword arguments) goes through :func:`migrate_flat_names`, which warns
#: (docs/mapper.md#old-flat-names)
FLAT_NAMES: dict[str, tuple[str, str]] = {
    "seeds_per_frame": ("seeding", "seeds_per_frame"),
    "first_frame_seeds": ("seeding", "first_frame_seeds"),
    "coverage_seeding": ("seeding", "coverage"),
    "coverage_alpha": ("seeding", "coverage_alpha"),
    "coverage_depth_factor": ("seeding", "coverage_depth_factor"),
    "rho": ("seeding", "rho"),
    "m_roi": ("seeding", "m_roi"),
    "m_bg": ("seeding", "m_bg"),
    "m_uniform": ("seeding", "m_uniform"),
    "gfd_eps": ("seeding", "gfd_eps"),
    "knn": ("seeding", "knn"),
    "init_opacity": ("seeding", "init_opacity"),
    "max_gaussians": ("budget", "max_gaussians"),
    "gaussians_per_pixel": ("budget", "gaussians_per_pixel"),
    "budget_mode": ("budget", "mode"),
    "gaussians_per_voxel": ("budget", "gaussians_per_voxel"),
    "budget_voxel_m": ("budget", "voxel_m"),
    "max_gaussians_cap": ("budget", "cap"),
    "evict": ("budget", "evict"),
    "roi_protect": ("budget", "roi_protect"),
    "pose_refine": ("pose", "refine"),
    "pose_track_iters": ("pose", "track_iters"),
    "pose_track_alpha": ("pose", "track_alpha"),
    "pose_lr_rot": ("pose", "lr_rot"),
    "pose_lr_trans": ("pose", "lr_trans"),
    "pose_init": ("pose", "init"),
    "exposure_comp": ("sensor", "exposure_comp"),
    "exposure_lr": ("sensor", "exposure_lr"),
    "motion_blur": ("sensor", "motion_blur"),
    "blur_exposure_s": ("sensor", "blur_exposure_s"),
    "blur_px_per_sample": ("sensor", "blur_px_per_sample"),
    "blur_max_samples": ("sensor", "blur_max_samples"),
    "rolling_shutter_s": ("sensor", "rolling_shutter_s"),
    "motion_estimate": ("sensor", "motion_estimate"),
    "rs_px_per_band": ("sensor", "rs_px_per_band"),
    "rs_max_bands": ("sensor", "rs_max_bands"),
    "blur_max_dt": ("sensor", "blur_max_dt"),
    "torch_threads": ("performance", "torch_threads"),
    "render_threads": ("performance", "render_threads"),
    "cpu_kernel": ("performance", "cpu_kernel"),
    "frustum_cull": ("performance", "frustum_cull"),
    "frustum_cull_min": ("performance", "frustum_cull_min"),
    "reference_paths": ("performance", "reference_paths"),
    "ssim_cache_views": ("performance", "ssim_cache_views"),
    "coarse_iters": ("performance", "coarse_iters"),
    "coarse_downscale": ("performance", "coarse_downscale"),
    "full_crop_fraction": ("performance", "full_crop_fraction"),
    "roi_cull": ("performance", "roi_cull"),
}


#: mapper settings renamed so that each name says what it bounds and means one thing across the configuration tree:
#: old name → new key (docs/reference.md#old-setting-names)
RENAMED_MAPPER_KEYS: dict[str, str] = {
    "max_keyframes": "stored_keyframes_max",
    "keyframe_every": "store_keyframe_every",
}

#: every old mapper setting name → its key now (dotted within the mapper section): the flat names
#: (:data:`FLAT_NAMES`) and the renamed settings (:data:`RENAMED_MAPPER_KEYS`); :class:`MapperConfig
#: <gausslite.mapping.config.MapperConfig>` migrates them
OLD_MAPPER_NAMES: dict[str, str] = {**{k: ".".join(v) for k, v in FLAT_NAMES.items()}, **RENAMED_MAPPER_KEYS}


def migrate_flat_names(data: Any, names: Optional[dict[str, str]] = None, where: str = "mapper") -> Any:
    """The one migration of old setting names to their keys now: the mapper's old flat names to their groups
    (:data:`FLAT_NAMES`) and renamed settings of every section to their new names.

    Each old key of the mapping ``data`` (a key path, dotted for a setting of a nested section: ``max_gaussians``,
    ``odometry.loop.max_keyframes``) is moved to its new key (``budget.max_gaussians``,
    ``odometry.loop.keyframe_images_max``). An old name wins over the same setting given by its new key: it comes from
    a later layer (a ``--set`` override or a keyword argument over a YAML file). Every use is reported: one
    ``DeprecationWarning`` and one warning log line naming the section and listing each old key with its new key
    (``docs/reference.md#old-setting-names``). :class:`~gausslite.mapping.config.MapperConfig` applies it to its input with
    :data:`OLD_MAPPER_NAMES`, :class:`gausslite.mission.config.AgentConfig` with its own table, so a YAML file, a
    ``--set`` override or a keyword argument written with the old names still loads, to the same values.

    Args:
        data: the settings of one section as a mapping (the ``mapper`` section of a GaussLite YAML, a mapper-only
            file, keyword arguments, the ``agent`` section); anything else is returned unchanged.
        names: old key → new key, both dotted within the section (None: :data:`OLD_MAPPER_NAMES`).
        where: the section's name in the messages.
    Returns:
        ``data`` itself when it holds no old name, else a new dict (sections along a moved key are copied, and
        sections given as models dumped to dicts of their explicitly set fields); the input is not modified.
    Raises:
        ValueError: a section along a new key is given as something other than a mapping.
    """
    if not isinstance(data, dict):
        return data
    names = OLD_MAPPER_NAMES if names is None else names
    found = [k for k in data if k in names] + [k for k in names if "." in k and _holds(data, k.split("."))]
    if not found:
        return data
    moves = ", ".join(f"{k} -> {names[k]}" for k in found)
    msg = f"old {where} setting names, use the new keys instead: {moves} (docs/reference.md#old-setting-names)"
    warnings.warn(msg, DeprecationWarning, stacklevel=2)
    log.warning("%s", msg)
    data = dict(data)
    for k in found:
        *old_path, old_leaf = k.split(".")
        value = _section(data, old_path, where).pop(old_leaf)
        *new_path, new_leaf = names[k].split(".")
        _section(data, new_path, where)[new_leaf] = value
    return data


def _holds(data: dict, path: list[str]) -> bool:
    """Whether the nested mapping ``data`` has a value at the key path ``path``."""
    node: Any = data
    for key in path[:-1]:
        node = node.get(key)
        if not isinstance(node, dict):
            return False
    return path[-1] in node


def _section(data: dict, path: list[str], where: str) -> dict:
    """The mapping at the key path ``path`` of ``data``, each level along it replaced in its parent by a copy (a
    model by a dict of its explicitly set fields, an absent or null section by an empty dict), so that changing it
    changes no input. Raises ValueError when a level is neither a mapping nor a model."""
    node = data
    for i, key in enumerate(path):
        sub = node.get(key) or {}
        if isinstance(sub, BaseModel):
            sub = sub.model_dump(exclude_unset=True)
        elif not isinstance(sub, dict):
            raise ValueError(f"{where}.{'.'.join(path[:i + 1])} must be a section (a mapping), got {sub!r}")
        node[key] = sub = dict(sub)
        node = sub
    return node
