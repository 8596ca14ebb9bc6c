"""The sensor renderer: the map rendered as the camera took a view (paper Sec. III-D, hand-held sensors).

A view is rendered with the configured rasterizer (:func:`gausslite.render.rasterize`) and, when the
sensor calls for it:

- its exposure response (``exposure_comp``, :mod:`gausslite.mapping.exposure`; MonoGS);
- the camera's motion blur (``motion_blur``, :mod:`gausslite.mapping.blur`; BAD-Gaussians, MBA-SLAM): the mean
  of renders at virtual poses along the motion during the exposure;
- its rolling shutter (``rolling_shutter_s``, :mod:`gausslite.mapping.shutter`; Kerl et al. ICCV 2015):
  row bands, each rendered from the pose at its readout time.

The camera's motion comes from the sensor's poses of consecutive mapped frames (:meth:`SensorRenderer.observe`).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch

from gausslite.datasets.base import Frame
from gausslite.mapping.blur import blur_samples, exposure_twist, motion_deltas
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.exposure import ExposureModel, apply_exposure
from gausslite.mapping.model import GaussianModel
from gausslite.mapping.poses import move_gaussians_for_pose_delta, nearest_key
from gausslite.mapping.shutter import readout_norm, shutter_bands
from gausslite.render import RenderOutput, blend_weights, blend_weights_inside, rasterize, rasterize_bands
from gausslite.render.culling import frustum_cull_mask, frustum_cull_masks

#: the rasterizer's tile edge (px): rolling-shutter bands start on tile rows to render in one pass
TILE_SIZE = 16


def _within(vis: torch.Tensor, subset: Optional[torch.Tensor]) -> torch.Tensor:
    """Culling masks ``vis`` ((N,) or (B, N) bool, modified in place) narrowed to ``subset`` (None, (N,) bool or
    int64 rows)."""
    if subset is not None:
        vis &= subset if subset.dtype == torch.bool else torch.zeros(vis.shape[-1], dtype=torch.bool,
                                                                     device=vis.device).index_fill_(0, subset, True)
    return vis


class SensorRenderer:
    """Renders a :class:`~gausslite.mapping.model.GaussianModel` as the sensor saw each view.

    Args:
        cfg: mapper configuration (backend, threads, culling and the sensor switches above).
        model: the Gaussians being optimised (read at every render; never modified here).
        clock: the mapper's budget clock; a deterministic clock (``charges``) is charged for every render.
    Attributes:
        exposure: per-keyframe exposure response (``cfg.sensor.exposure_comp``), None when off.
        blur: frame id → (6,) float64 ξ_b = τ · (ω, v), the camera's motion over the exposure of every mapped
            frame (``cfg.sensor.motion_blur`` / ``cfg.sensor.rolling_shutter_s``; τ = ``cfg.sensor.blur_exposure_s``).
        rs_norm: rolling-shutter readout time per unit of normalised image y of the full image (seconds;
            :func:`gausslite.mapping.shutter.readout_norm`), set by the first observed frame.
        last_sensor: (timestamp s, c2w (4, 4) float64, frame id) of the last observed frame, or None.
    """

    def __init__(self, cfg: MapperConfig, model: GaussianModel, clock) -> None:
        self.cfg = cfg
        self.model = model
        self.clock = clock
        self.device = model.device
        self.background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.exposure: Optional[ExposureModel] = (ExposureModel(cfg.sensor.exposure_lr,
                                                                cfg.pose.between_keyframes == "interpolate")
                                                  if cfg.sensor.exposure_comp
                                                  else None)
        self.blur: dict[int, np.ndarray] = {}
        self.rs_norm = 0.0
        self.last_sensor: Optional[tuple] = None

    # ------------------------------------------------------------------ sensor state
    def observe(self, frame: Frame) -> None:
        """Record the camera's motion over ``frame``'s exposure from the sensor's poses (before refinement):
        backward from the previous observed frame, and under ``motion_estimate: central`` the previous frame's
        estimate becomes the mean of its backward and forward ones. No-op without motion blur or rolling
        shutter."""
        sc = self.cfg.sensor
        if not (sc.motion_blur or sc.rolling_shutter_s > 0):
            return
        prev = self.last_sensor
        xi_b = (np.zeros(6) if prev is None else
                exposure_twist(prev[1], prev[0], frame.c2w, frame.timestamp, sc.blur_exposure_s, sc.blur_max_dt))
        self.blur[frame.frame_id] = xi_b
        if sc.motion_estimate == "central" and prev is not None and len(prev) > 2 and prev[2] in self.blur \
                and xi_b.any():
            # the previous frame's motion is now known on both sides: the mean of its backward and forward
            # estimates (the forward one alone for the first frame, which had none)
            back = self.blur[prev[2]]
            self.blur[prev[2]] = 0.5 * (back + xi_b) if back.any() else xi_b.copy()
        self.last_sensor = (float(frame.timestamp), np.asarray(frame.c2w, np.float64).copy(), int(frame.frame_id))
        self.rs_norm = readout_norm(sc.rolling_shutter_s, frame.intrinsics.fy, frame.intrinsics.height)

    def state_dict(self) -> dict:
        """Plain-data copy for checkpoints: ``exposure`` (None when off), ``blur``, ``last_sensor``, ``rs_norm``."""
        return {"exposure": None if self.exposure is None else self.exposure.state_dict(),
                "blur": {k: v.copy() for k, v in self.blur.items()}, "last_sensor": self.last_sensor,
                "rs_norm": self.rs_norm}

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict` (absent keys: the defaults of a new renderer)."""
        if self.exposure is not None and state.get("exposure"):
            self.exposure.load_state_dict(state["exposure"])
        self.blur = {int(k): np.asarray(v, np.float64) for k, v in (state.get("blur") or {}).items()}
        self.last_sensor = state.get("last_sensor")
        self.rs_norm = float(state.get("rs_norm", 0.0))

    # ------------------------------------------------------------------ renders
    def exposed(self, out: RenderOutput, frame_id: int,
                requires_grad: bool = False) -> tuple[RenderOutput, Optional[torch.Tensor]]:
        """``out`` with frame ``frame_id``'s exposure response applied to its colour (its keyframe's θ, or
        the nearest keyframe's), and that θ (6,) as a leaf tensor, with gradients if ``requires_grad``;
        ``(out, None)`` without exposure compensation or before the first keyframe."""
        if self.exposure is None or not self.exposure.params:
            return out, None
        theta = self.exposure.tensor(frame_id, self.device, requires_grad=requires_grad)
        return dataclasses.replace(out, color=apply_exposure(out.color, theta)), theta

    def render_view(self, c2w, K, width: int, height: int, frame_id: int, subset: Optional[torch.Tensor],
                    pose_xi: Optional[torch.Tensor] = None, detach_map: bool = False,
                    parts: Optional[list] = None, cull: bool = False) -> RenderOutput:
        """:meth:`rasterize` of frame ``frame_id``'s view as the camera took it while moving (the nearest
        mapped frame's motion for a frame that was not mapped):

        - ``cfg.sensor.motion_blur`` (:mod:`gausslite.mapping.blur`): the mean colour, depth and alpha of K renders at
          ``c2w · E(s_k ξ_b)``;
        - ``cfg.sensor.rolling_shutter_s`` (:mod:`gausslite.mapping.shutter`): row bands, band b's rows rendered
          from ``c2w · E(t_b ξ_b / τ)`` (and blurred around that pose), stacked top to bottom. Under
          ``performance.bands_in_one_pass`` the band edges lie on tile rows and every blur sample and band is drawn in
          one render (:meth:`_one_pass`); otherwise each band is rendered alone, its rows only.

        The screen-space data (means2d, radii, ids) are the middle render's. ``parts``: a list that receives
        the renders as groups, one group per blur sample holding its bands, or one group holding the one-pass
        render (nothing when the view is rendered as one sharp image), for density statistics
        (:meth:`DensityStrategy.accumulate <gausslite.mapping.strategy.DensityStrategy.accumulate>`).
        """
        sc = self.cfg.sensor
        rs = sc.rolling_shutter_s > 0 and self.rs_norm > 0
        if not ((sc.motion_blur or rs) and self.blur):
            return self.rasterize(c2w, K, width, height, subset, pose_xi=pose_xi, detach_map=detach_map, cull=cull)
        xi_b = self.blur[nearest_key(self.blur, frame_id)]
        n_blur = (blur_samples(xi_b, float(K[0, 0]), width, height, sc.blur_px_per_sample, sc.blur_max_samples)
                  if sc.motion_blur else 1)
        one_pass = self.cfg.performance.bands_in_one_pass
        bands = (shutter_bands(K, width, height, xi_b / sc.blur_exposure_s, self.rs_norm, sc.rs_px_per_band,
                               sc.rs_max_bands, align=TILE_SIZE if one_pass else 1) if rs else [(0, height, 0.0)])
        if n_blur <= 1 and len(bands) == 1 and bands[0][2] == 0.0:
            return self.rasterize(c2w, K, width, height, subset, pose_xi=pose_xi, detach_map=detach_map, cull=cull)
        # the blur's virtual poses around each band's readout time t (t / τ exposures from the frame's pose):
        # deltas[b][k] is band b's pose in blur sample k
        deltas = [motion_deltas(xi_b, n_blur, t / sc.blur_exposure_s, self.device) for _, _, t in bands]
        if one_pass:
            return self._one_pass(c2w, K, width, height, subset, bands, deltas, pose_xi, detach_map, parts)
        groups: list[list[RenderOutput]] = [[] for _ in range(n_blur)]
        for b, (y0, y1, _) in enumerate(bands):
            Kb = torch.as_tensor(K).clone()  # the band's rows alone: principal point moved up by its first row
            Kb[1, 2] -= y0
            for g, delta in zip(groups, deltas[b]):
                g.append(self.rasterize(c2w, Kb, width, y1 - y0, subset, pose_xi=pose_xi, detach_map=detach_map,
                                        view_delta=delta, cull=cull))
        if parts is not None:
            parts.extend(groups)

        def stacked(field: str) -> torch.Tensor:
            per_sample = [torch.cat([getattr(o, field) for o in g], 0) if len(g) > 1 else getattr(g[0], field)
                          for g in groups]
            return per_sample[0] if len(per_sample) == 1 else torch.stack(per_sample).mean(0)

        mid_group = groups[len(groups) // 2]
        mid = mid_group[len(mid_group) // 2]
        return dataclasses.replace(mid, color=stacked("color"), depth=stacked("depth"), alpha=stacked("alpha"))

    def _one_pass(self, c2w, K, width: int, height: int, subset: Optional[torch.Tensor], bands: list, deltas: list,
                  pose_xi: Optional[torch.Tensor], detach_map: bool, parts: Optional[list]) -> RenderOutput:
        """:meth:`render_view`'s blur samples and shutter bands in one render (:meth:`rasterize_bands`): blur sample
        k is drawn ``k · Hp`` rows below the first (``Hp`` = the height rounded up to whole tiles; the last band of
        each sample but the last also draws the padding rows, which are discarded), each (sample, band) from its own
        pose, and the samples' images are averaged. ``parts`` receives one group holding the render."""
        n_blur = len(deltas[0])
        hp = -(-height // TILE_SIZE) * TILE_SIZE if n_blur > 1 else height
        K0 = torch.as_tensor(K)
        rows = []
        for k in range(n_blur):
            Kk = K0.clone()
            Kk[1, 2] += k * hp
            for b, (y0, y1, _) in enumerate(bands):
                end = hp if b == len(bands) - 1 and k < n_blur - 1 else y1
                rows.append((k * hp + y0, k * hp + end, deltas[b][k], Kk))
        out = self.rasterize_bands(c2w, K0, width, (n_blur - 1) * hp + height, subset, rows, pose_xi=pose_xi,
                                   detach_map=detach_map)
        if parts is not None:
            parts.append([out])
        if n_blur == 1:
            return out

        def mean(x: torch.Tensor) -> torch.Tensor:
            return torch.stack([x[k * hp:k * hp + height] for k in range(n_blur)]).mean(0)

        return dataclasses.replace(out, color=mean(out.color), depth=mean(out.depth), alpha=mean(out.alpha))

    def _posed(self, c2w, pose_xi: Optional[torch.Tensor], detach_map: bool) -> tuple[dict, torch.Tensor, torch.Tensor]:
        """``(params, means, quats)``: the map's parameters (detached under ``detach_map``) and its means and
        quaternions moved for the pose delta ``pose_xi`` (:func:`move_gaussians_for_pose_delta`)."""
        p = self.model.params
        if detach_map:
            p = {k: v.detach() for k, v in p.items()}
        means, quats = p["means"], p["quats"]
        if pose_xi is not None:
            c2w_t = torch.as_tensor(c2w, dtype=torch.float64, device=means.device)
            means, quats = move_gaussians_for_pose_delta(means, quats, c2w_t, pose_xi)
        return p, means, quats

    def _visible(self, means: torch.Tensor, log_scales: torch.Tensor, vm: torch.Tensor, K, width: int, height: int,
                 subset: Optional[torch.Tensor], cull: bool) -> Optional[torch.Tensor]:
        """``subset`` narrowed to the Gaussians that may reach the view (frustum culling when the map has
        ``frustum_cull_min`` Gaussians or more, or ``cull``), and a deterministic clock charged for the render."""
        if self.cfg.performance.frustum_cull and (len(means) >= self.cfg.performance.frustum_cull_min or cull):
            subset = _within(frustum_cull_mask(means, log_scales, vm, K, width, height), subset)
        if self.clock.charges:
            n_render = len(means) if subset is None else (
                int(subset.sum()) if subset.dtype == torch.bool else int(subset.numel()))
            self.clock.charge_render(int(width) * int(height), n_render, torch.is_grad_enabled())
        return subset

    def _visible_bands(self, means: torch.Tensor, log_scales: torch.Tensor, vms: list, Ks: list, width: int,
                       heights: list, subset: Optional[torch.Tensor]) -> list:
        """:meth:`_visible` of B row bands (``vms`` (4, 4) world-to-camera, ``Ks`` (3, 3) with the band's principal
        point, ``heights`` its rows) by one culling pass (:func:`gausslite.render.culling.frustum_cull_masks`),
        culled whatever the map size; a clock is charged per band."""
        if not self.cfg.performance.frustum_cull:
            return [self._visible(means, log_scales, vm, K, width, h, subset, True)
                    for vm, K, h in zip(vms, Ks, heights)]
        vis = _within(frustum_cull_masks(means, log_scales, vms, Ks, width, heights), subset)
        if self.clock.charges:
            for b, h in enumerate(heights):
                self.clock.charge_render(int(width) * int(h), int(vis[b].sum()), torch.is_grad_enabled())
        return list(vis)

    def rasterize_bands(self, c2w, K, width: int, height: int, subset: Optional[torch.Tensor], bands: list,
                        pose_xi: Optional[torch.Tensor] = None, detach_map: bool = False) -> RenderOutput:
        """:meth:`rasterize` of an image whose row bands ``bands`` = ``[(y0, y1, view_delta, K_b)]`` (rows
        ``y0 ≤ v < y1``, edges on tile rows) are each seen from ``c2w · E(ξ) · view_delta`` (4, 4 float64) with
        intrinsics ``K_b`` (3, 3), in one pass (:func:`gausslite.render.rasterize_bands`); each band is
        frustum-culled to its own rows whatever the map size (``frustum_cull``). Arguments otherwise as
        :meth:`rasterize`."""
        p, means, quats = self._posed(c2w, pose_xi, detach_map)
        cam = torch.as_tensor(c2w, dtype=torch.float64, device=means.device)
        vms = list(torch.linalg.inv(cam @ torch.stack([b[2].to(cam.device) for b in bands])))
        Ks = [torch.as_tensor(b[3]) for b in bands]
        Kbs = []
        for (y0, _, _, _), Kband in zip(bands, Ks):
            Kbs.append(Kband.clone())
            Kbs[-1][1, 2] -= y0
        # always culled to the band's rows (whatever the map size): its Gaussians are projected for the whole
        # image but drawn in its rows only
        subsets = self._visible_bands(means, p["log_scales"], vms, Kbs, width, [b[1] - b[0] for b in bands], subset)
        return rasterize_bands(
            means, quats, p["log_scales"], p["opacity_logits"], p["colors"], K=K, width=width, height=height,
            viewmats=vms, rows=[(b[0], b[1]) for b in bands], subsets=subsets, Ks=Ks, background=self.background,
            backend=self.cfg.backend, num_threads=self.cfg.performance.render_threads,
            cpu_kernel=self.cfg.performance.cpu_kernel, tile_size=TILE_SIZE)

    def rasterize(self, c2w, K, width: int, height: int, subset: Optional[torch.Tensor],
                  pose_xi: Optional[torch.Tensor] = None, detach_map: bool = False,
                  view_delta: Optional[torch.Tensor] = None, cull: bool = False) -> RenderOutput:
        """Render the current parameters (differentiable) with the configured backend and threads, from
        camera-to-world ``c2w`` (4, 4) with intrinsics ``K`` (3, 3) at ``width`` × ``height`` pixels.

        ``subset``: (N,) bool or int64 rows to render (None: all). ``pose_xi`` (6,) float64: render from
        ``c2w · E(ξ)`` with gradients reaching ξ (:func:`~gausslite.mapping.poses.move_gaussians_for_pose_delta`);
        ``detach_map``: no gradient reaches the Gaussians (pose tracking); ``view_delta`` (4, 4) float64: render
        from ``c2w · E(ξ) · view_delta`` (a virtual pose within the exposure, :meth:`render_view`); ``cull``:
        frustum culling whatever the map size (``frustum_cull_min``; ROI crops, ``roi_cull``)."""
        p, means, quats = self._posed(c2w, pose_xi, detach_map)
        cam = torch.as_tensor(c2w, dtype=torch.float64, device=means.device)
        if view_delta is not None:
            cam = cam @ view_delta.to(cam.device)
        vm = torch.linalg.inv(cam)
        subset = self._visible(means, p["log_scales"], vm, K, width, height, subset, cull)
        return rasterize(
            means, quats, p["log_scales"], p["opacity_logits"], p["colors"],
            K=K, width=width, height=height, viewmat=vm, subset=subset, background=self.background,
            backend=self.cfg.backend, num_threads=self.cfg.performance.render_threads,
            cpu_kernel=self.cfg.performance.cpu_kernel,
        )

    def blend_weights(self, K: torch.Tensor, width: int, height: int, c2w: torch.Tensor) -> torch.Tensor:
        """(N,) float32 alpha-blending weight Σ_pixels T_i α_i of every Gaussian in the (sharp) view
        (:func:`gausslite.render.blend_weights`); a deterministic clock is charged for the render."""
        p = self.model.params
        if self.clock.charges:
            self.clock.charge_render(width * height, len(self.model), grad=False)
        return blend_weights(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], K=K, width=width,
            height=height, c2w=c2w, background=self.background, backend=self.cfg.backend,
            num_threads=self.cfg.performance.render_threads)


    def blend_weights_inside(self, K: torch.Tensor, width: int, height: int, c2w: torch.Tensor,
                             pixel_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(inside, total)``: (N,) float32 alpha-blending weights of every Gaussian in the (sharp) view inside
        ``pixel_mask`` (H, W) bool and over the whole view, from one render
        (:func:`gausslite.render.blend_weights_inside`); a deterministic clock is charged for it."""
        p = self.model.params
        if self.clock.charges:
            self.clock.charge_render(width * height, len(self.model), grad=False)
        return blend_weights_inside(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], K=K, width=width,
            height=height, c2w=c2w, pixel_mask=pixel_mask, background=self.background, backend=self.cfg.backend,
            num_threads=self.cfg.performance.render_threads)


__all__ = ["SensorRenderer"]
