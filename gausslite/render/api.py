"""Public entry point :func:`rasterize` of the differentiable Gaussian rasterizer."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .autograd import RasterizeWarp, default_num_threads, project_gaussians_warp
from .binning import bin_gaussians
from .gsplat_backend import gsplat_available, rasterize_gsplat
from .projection import Projection, project_gaussians
from .reference import rasterize_reference
from .simd_kernels import check_cpu_kernel

BACKENDS = ("auto", "warp", "torch", "gsplat")


@dataclass
class RenderOutput:
    """Rendered image and per-Gaussian screen-space data.

    Attributes:
        color: (H, W, 3) float32 RGB composited over the background (float64 only for
            backend="torch" with float64 inputs; likewise depth and alpha).
        depth: (H, W) float32 expected camera-z depth in metres, ``sum w_i z_i / alpha``;
            0 where alpha < 1e-6.
        alpha: (H, W) float32 accumulated opacity ``sum w_i = 1 - T_final``.
        means2d: (M, 2) projected centres in pixels (dtype of the inputs); non-leaf, with
            ``retain_grad()`` applied when grad is enabled so ``means2d.grad`` is readable after
            backward (densification statistics).
        radii: (M,) int32 screen radius in pixels (0 = culled).
        ids: (M,) int64 indices into the N input Gaussians of the rows of means2d/radii.
        n_bands: row bands the image was rendered in, each from its own pose (:func:`rasterize_bands`): a
            Gaussian seen by several bands has a row in means2d/radii/ids for each.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    ids: torch.Tensor
    n_bands: int = 1


def _as_tensor(x, name: str, shape: tuple, device, dtype) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(x)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"{name} must be a tensor/array of shape {shape}, got {type(x)}") from e
    if tuple(x.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(x.shape)}")
    xd = x.detach().to(device=device, dtype=torch.float64)
    if not torch.isfinite(xd).all():
        raise ValueError(f"{name} contains NaN or Inf")
    return xd


def _check_params(means, quats, log_scales, opacity_logits, colors):
    for name, t in (("means", means), ("quats", quats), ("log_scales", log_scales),
                    ("opacity_logits", opacity_logits), ("colors", colors)):
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t)}")
        if not t.is_floating_point():
            raise ValueError(f"{name} must be floating point, got {t.dtype}")
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
    N = means.shape[0]
    for name, t, shp in (("quats", quats, (N, 4)), ("log_scales", log_scales, (N, 3)),
                         ("opacity_logits", opacity_logits, (N,)), ("colors", colors, (N, 3))):
        if tuple(t.shape) != shp:
            raise ValueError(f"{name} must have shape {shp} (N={N}), got {tuple(t.shape)}")
        if t.device != means.device:
            raise ValueError(f"{name} is on {t.device} but means is on {means.device}")
    return N


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")
    if backend == "auto":
        if device.type == "cuda":
            return "gsplat" if gsplat_available() else "warp"
        return "warp"
    if backend == "gsplat":
        if device.type != "cuda" or not gsplat_available():
            raise ValueError("backend='gsplat' needs CUDA tensors and an importable gsplat package")
    return backend


def _camera_tensors(K, c2w, viewmat, device: torch.device, dtype: torch.dtype):
    """``(K64, vm64)``: the (3, 3) intrinsics (pixels) and (4, 4) world-to-camera matrix as ``dtype`` tensors on
    ``device``, from ``K`` and exactly one of ``c2w`` / ``viewmat``.

    Raises:
        ValueError: both or neither pose given, bad shapes, NaN/Inf, non-positive focal lengths.
    """
    if (c2w is None) == (viewmat is None):
        raise ValueError("give exactly one of c2w (camera-to-world) or viewmat (world-to-camera)")
    K64 = _as_tensor(K, "K", (3, 3), device, dtype)
    if K64[0, 0] <= 0 or K64[1, 1] <= 0:
        raise ValueError(f"K must have positive focal lengths, got fx={K64[0, 0]} fy={K64[1, 1]}")
    if c2w is not None:
        vm64 = torch.linalg.inv(_as_tensor(c2w, "c2w", (4, 4), device, dtype))
    else:
        vm64 = _as_tensor(viewmat, "viewmat", (4, 4), device, dtype)
    return K64, vm64


def _image_settings(width, height, tile_size: int, cpu_kernel: str, background, device: torch.device,
                    dtype: torch.dtype) -> tuple[int, int, torch.Tensor]:
    """``(width, height, bg)``: the image size as ints and the background as a (3,) float32 tensor (black when None).

    Raises:
        ValueError: width/height or tile_size <= 0, an unknown cpu_kernel, a background not of shape (3,).
    """
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be > 0, got {width}x{height}")
    if tile_size <= 0:
        raise ValueError(f"tile_size must be > 0, got {tile_size}")
    check_cpu_kernel(cpu_kernel)
    if background is None:
        return int(width), int(height), torch.zeros(3, dtype=torch.float32, device=device)
    return int(width), int(height), _as_tensor(background, "background", (3,), device, dtype).to(torch.float32)


def _launch_threads(num_threads) -> int:
    """The warp backend's CPU launch threads: ``num_threads``, or :func:`default_num_threads` when None.
    Raises ValueError when <= 0."""
    nt = default_num_threads() if num_threads is None else int(num_threads)
    if nt <= 0:
        raise ValueError(f"num_threads must be > 0, got {num_threads}")
    return nt


def _gather_subset(subset, N: int, device: torch.device, params: tuple):
    """``(ids, sel)``: the (M,) int64 rows to render and ``params`` (the five (N, ...) parameter tensors) gathered
    at them; ``subset`` None keeps every row and makes no copy (autograd scatters gradients back into the full
    tensors).

    Raises:
        ValueError: a bool mask not of shape (N,), indices outside [0, N), or another kind of ``subset``.
    """
    if subset is None:
        return torch.arange(N, device=device), params
    if not isinstance(subset, torch.Tensor):
        subset = torch.as_tensor(np.asarray(subset))
    subset = subset.to(device)
    if subset.dtype == torch.bool:
        if tuple(subset.shape) != (N,):
            raise ValueError(f"bool subset must have shape ({N},), got {tuple(subset.shape)}")
        ids = torch.nonzero(subset).squeeze(1)
    elif not subset.is_floating_point() and subset.dim() == 1:
        ids = subset.to(torch.int64)
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= N):
            raise ValueError(f"subset indices must be in [0, {N}), got range "
                             f"[{int(ids.min())}, {int(ids.max())}]")
    else:
        raise ValueError("subset must be None, a (N,) bool mask or a 1-D integer index tensor")
    return ids, tuple(t.index_select(0, ids) for t in params)


def _rasterize_warp_cpu(m, q, ls, ol, col, vm64, K64, width, height, *, near, far, eps2d, tile_size, nt, bg,
                        cpu_kernel, ids) -> RenderOutput:
    """The warp backend's CPU fast path (float32/float64 parameters): projection, binning, sigmoid, compositing over
    the background ``bg`` and depth normalisation all run in Warp kernels (few per-element torch ops). Arguments as
    :func:`rasterize` (``m, q, ls, ol, col``: the gathered rows; ``nt``: launch threads)."""
    dtype = m.dtype
    proj = project_gaussians_warp(m, q.to(dtype), ls.to(dtype), vm64, K64, width, height,
                                  near=near, far=far, eps2d=eps2d, num_threads=nt, simd=cpu_kernel == "simd")
    return _composite_warp_cpu(proj, ol, col, ids, width, height, tile_size, nt, bg, cpu_kernel)


def _composite_warp_cpu(proj: Projection, ol, col, ids, width: int, height: int, tile_size: int, nt: int, bg,
                        cpu_kernel: str, tile_rows: torch.Tensor | None = None, n_bands: int = 1) -> RenderOutput:
    """Bin the projected rows ``proj`` (to their ``tile_rows`` when given: :func:`rasterize_bands`) and composite
    them with the Warp kernels over the background ``bg``; ``ol``, ``col``, ``ids``: the rows' opacity logits,
    colours and Gaussian indices. ``proj.means2d`` keeps its gradient (density statistics)."""
    means2d, radii = proj.means2d, proj.radii
    if torch.is_grad_enabled() and means2d.requires_grad:
        means2d.retain_grad()
    bins = bin_gaussians(means2d, radii, proj.depths, width, height, tile_size, num_threads=nt, tile_rows=tile_rows)
    color, depth, alpha = RasterizeWarp.apply(
        means2d, proj.conics, ol, col, proj.depths, bins.gids, bins.tile_start,
        bins.tile_end, width, height, tile_size, bins.tiles_x, bins.tiles_y, nt, True, bg, cpu_kernel,
    )
    return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=means2d, radii=radii, ids=ids,
                        n_bands=n_bands)


def _rasterize_raw(m, q, ls, ol, col, vm64, K64, width, height, *, backend, near, far, eps2d, tile_size, nt,
                   cpu_kernel):
    """Projection and sigmoid in torch, then compositing by the Warp kernels (``backend`` "warp") or the torch
    reference ("torch"), without background or depth normalisation.

    Returns:
        ``(color_raw (H, W, 3), depth_sum (H, W), alpha (H, W), means2d (M, 2), radii (M,))``.
    """
    dtype = m.dtype
    proj = project_gaussians(m, q, ls, vm64.to(dtype), K64.to(dtype), width, height,
                             near=near, far=far, eps2d=eps2d)
    means2d, radii = proj.means2d, proj.radii
    if torch.is_grad_enabled() and means2d.requires_grad:
        means2d.retain_grad()
    opac = torch.sigmoid(ol)
    bins = bin_gaussians(means2d, radii, proj.depths, width, height, tile_size)
    if backend == "warp":
        color_raw, depth_sum, alpha = RasterizeWarp.apply(
            means2d, proj.conics, opac, col, proj.depths, bins.gids, bins.tile_start,
            bins.tile_end, width, height, tile_size, bins.tiles_x, bins.tiles_y, nt, False, None,
            cpu_kernel,
        )
    else:
        color_raw, depth_sum, alpha = rasterize_reference(
            means2d, proj.conics, opac, col, proj.depths, bins, width, height, tile_size
        )
        if torch.is_grad_enabled() and not color_raw.requires_grad and means2d.requires_grad:
            # Nothing was visible: keep the outputs attached to the graph (zero gradients).
            z = 0.0 * (means2d.sum() + proj.conics.sum() + opac.sum() + col.sum() + proj.depths.sum())
            color_raw, depth_sum, alpha = color_raw + z, depth_sum + z, alpha + z
    return color_raw, depth_sum, alpha, means2d, radii


def _composite_output(color_raw, depth_sum, alpha, bg, out_dt: torch.dtype, means2d, radii, ids) -> RenderOutput:
    """Composite ``color_raw`` over the background ``bg`` (3,) and normalise the depth by alpha (0 where alpha <
    1e-6), all in ``out_dt``."""
    color_raw = color_raw.to(out_dt)
    depth_sum = depth_sum.to(out_dt)
    alpha = alpha.to(out_dt)
    color = color_raw + (1.0 - alpha)[..., None] * bg.to(out_dt)
    ok = alpha >= 1e-6
    depth = torch.where(ok, depth_sum / torch.where(ok, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(depth_sum))
    return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=means2d,
                        radii=radii.to(torch.int32), ids=ids)


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    *,
    K,
    width: int,
    height: int,
    c2w=None,
    viewmat=None,
    subset=None,
    background=None,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e4,
    eps2d: float = 0.3,
    tile_size: int = 16,
    num_threads: int | None = None,
    cpu_kernel: str = "simd",
) -> RenderOutput:
    """Render 3D Gaussians into a pinhole camera, differentiably (Kerbl et al. 2023 3DGS).

    Pipeline: optional subset gather -> :func:`project_gaussians` (EWA splatting, Zwicker et al.
    2001) -> tile binning and depth sort -> per-pixel front-to-back alpha compositing (alpha
    clamped to 0.99, alpha < 1/255 skipped, stop before transmittance < 1e-4) -> background and
    depth normalisation. With backend "warp" on CPU (float32/float64 parameters) every stage runs
    in Warp kernels (projection by :class:`~gausslite.render.autograd.ProjectWarp`, evaluated in
    float64; sigmoid, background and depth normalisation fused into the compositing kernels);
    otherwise projection, sigmoid and the final normalisation are torch code.

    Args:
        means: (N, 3) float32/float64 centres, world frame, metres.
        quats: (N, 4) rotations (w, x, y, z), unnormalised (normalised inside).
        log_scales: (N, 3) log standard deviations (scale = exp), metres.
        opacity_logits: (N,) opacity logits (opacity = sigmoid).
        colors: (N, 3) RGB, used as-is.
        K: (3, 3) intrinsics in pixels (torch or numpy, any float dtype).
        width, height: image size in pixels (> 0).
        c2w: (4, 4) camera-to-world pose (OpenCV axes: x right, y down, z forward), or
        viewmat: (4, 4) world-to-camera; exactly one of the two must be given.
        subset: None, (N,) bool mask or int64 index tensor: render only those rows; gradients
            reach the full tensors (zero outside the subset). No copy of the full map is made.
        background: (3,) RGB composited behind (default black).
        backend: "auto" (gsplat on CUDA if importable, else warp), "warp", "torch" (slow
            reference, autograd only) or "gsplat" (CUDA only).
        near, far: depth clipping planes (metres).
        eps2d: low-pass variance added to the 2D covariance diagonal (px^2).
        tile_size: tile edge in pixels (binning and CPU work split).
        num_threads: CPU launch threads for the warp backend (default min(2, os.cpu_count())).
        cpu_kernel: compositing kernels of the warp backend on CPU: "simd" (vectorised,
            :mod:`gausslite.render.simd_kernels`; tiles up to 16 px) or "tile" (the Warp tile kernels;
            the same images to float32 rounding, about 1.6x slower).

    Returns:
        :class:`RenderOutput`.

    Raises:
        ValueError: bad shapes/dtypes, NaN/Inf in K or pose, both or neither pose given,
            width/height <= 0, unknown backend or cpu_kernel, out-of-range subset indices.
    """
    N = _check_params(means, quats, log_scales, opacity_logits, colors)
    device, dtype = means.device, means.dtype
    width, height, bg = _image_settings(width, height, tile_size, cpu_kernel, background, device, dtype)
    K64, vm64 = _camera_tensors(K, c2w, viewmat, device, dtype)
    backend = _resolve_backend(backend, device)
    ids, (m, q, ls, ol, col) = _gather_subset(subset, N, device, (means, quats, log_scales, opacity_logits, colors))

    if backend == "gsplat":
        color_raw, depth_sum, alpha, means2d, radii = rasterize_gsplat(
            m, q, ls, ol, col, viewmat=vm64.to(dtype), K=K64.to(dtype), width=width, height=height,
            near=near, far=far, eps2d=eps2d, tile_size=tile_size,
        )
    else:
        nt = _launch_threads(num_threads) if backend == "warp" else None
        kw = dict(near=near, far=far, eps2d=eps2d, tile_size=tile_size, nt=nt, cpu_kernel=cpu_kernel)
        if backend == "warp" and device.type == "cpu" and dtype in (torch.float32, torch.float64):
            return _rasterize_warp_cpu(m, q, ls, ol, col, vm64, K64, width, height, bg=bg, ids=ids, **kw)
        color_raw, depth_sum, alpha, means2d, radii = _rasterize_raw(m, q, ls, ol, col, vm64, K64, width, height,
                                                                     backend=backend, **kw)
    # float32 output, except the reference keeps float64 so it can be gradchecked end to end.
    out_dt = dtype if (backend == "torch" and dtype == torch.float64) else torch.float32
    return _composite_output(color_raw, depth_sum, alpha, bg, out_dt, means2d, radii, ids)


def _stack_bands(outs: list, rows: list) -> RenderOutput:
    """One image of full renders ``outs``, one per band: band b's rows ``rows[b]`` of ``outs[b]`` stacked, and the
    renders' projected rows stacked (:func:`rasterize_bands`' one-by-one path)."""
    cut = [(o, int(r[0]), int(r[1])) for o, r in zip(outs, rows)]
    return RenderOutput(color=torch.cat([o.color[a:b] for o, a, b in cut]),
                        depth=torch.cat([o.depth[a:b] for o, a, b in cut]),
                        alpha=torch.cat([o.alpha[a:b] for o, a, b in cut]),
                        means2d=torch.cat([o.means2d for o in outs]), radii=torch.cat([o.radii for o in outs]),
                        ids=torch.cat([o.ids for o in outs]), n_bands=len(outs))


def rasterize_bands(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    *,
    K,
    width: int,
    height: int,
    viewmats: list,
    rows: list,
    subsets: list | None = None,
    Ks: list | None = None,
    background=None,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e4,
    eps2d: float = 0.3,
    tile_size: int = 16,
    num_threads: int | None = None,
    cpu_kernel: str = "simd",
) -> RenderOutput:
    """One image whose row bands are each seen from their own pose (a rolling shutter: each band of rows is read
    out at its own time, :mod:`gausslite.mapping.shutter`), rendered in one pass: rows ``rows[b] = (y0, y1)`` are
    the rows of :func:`rasterize` from ``viewmats[b]``, with the image's size and intrinsics (``Ks[b]`` when given).

    The bands' Gaussians are projected each from its band's pose and composited together: the projected rows of
    every band are stacked, each binned only to its band's tile rows (:func:`~gausslite.render.binning.bin_gaussians`
    ``tile_rows``), and one compositing pass and one backward pass cover the image. So B bands cost one gather of
    their rows, one projection (the SIMD kernels, ``cpu_kernel`` "simd"; B with the Warp tile kernels), binning,
    compositing and backward, not B of each (with the Warp backend on CPU;
    elsewhere the bands are rendered one by one, each at the full image size, and their rows stacked: the reference
    of the parity test).

    Args:
        means … colors, K, width, height, background, backend, near, far, eps2d, tile_size, num_threads,
            cpu_kernel: as :func:`rasterize` (K (3, 3) pixels of the whole image).
        viewmats: B (4, 4) world-to-camera poses (OpenCV axes), one per band.
        rows: B ``(y0, y1)`` pixel row ranges that tile ``0 … height`` in order; every ``y0`` a multiple of
            ``tile_size`` (a tile lies in one band).
        subsets: None or B subsets (each as :func:`rasterize`'s ``subset``: None, (N,) bool or int64 rows), the
            Gaussians each band may draw (a band's frustum culling).
        Ks: None or B (3, 3) intrinsics, one per band (several views stacked in one image, each with its
            principal point moved down to its rows); None: ``K`` for every band.
    Returns:
        :class:`RenderOutput` of the image; ``means2d``, ``radii`` and ``ids`` stack the bands' projected rows (a
        Gaussian seen by two bands has two rows).
    Raises:
        ValueError: as :func:`rasterize`; bands that do not tile the image in order or start off a tile row;
            ``viewmats``, ``rows`` and ``subsets`` of different lengths.
    """
    B = len(viewmats)
    if B == 0 or len(rows) != B or (subsets is not None and len(subsets) != B) or (Ks is not None and len(Ks) != B):
        raise ValueError(f"need as many viewmats ({B}), rows ({len(rows)}), subsets and Ks as bands (at least one)")
    ends = [0] + [int(r[1]) for r in rows]
    if any(int(r[0]) != ends[b] or int(r[1]) <= int(r[0]) for b, r in enumerate(rows)) or ends[-1] != int(height):
        raise ValueError(f"rows must tile 0..{height} in order, got {list(rows)}")
    if any(int(r[0]) % int(tile_size) for r in rows):
        raise ValueError(f"every band must start on a tile row (multiple of {tile_size}), got {list(rows)}")
    subsets = subsets if subsets is not None else [None] * B
    Ks = Ks if Ks is not None else [K] * B
    N = _check_params(means, quats, log_scales, opacity_logits, colors)
    device, dtype = means.device, means.dtype
    params = (means, quats, log_scales, opacity_logits, colors)
    kw = dict(width=width, height=height, background=background, backend=backend, near=near, far=far,
              eps2d=eps2d, tile_size=tile_size, num_threads=num_threads, cpu_kernel=cpu_kernel)
    fast = (_resolve_backend(backend, device) == "warp" and device.type == "cpu"
            and dtype in (torch.float32, torch.float64))
    if B == 1 or not fast:
        outs = [rasterize(*params, K=Kb, viewmat=vm, subset=sub, **kw) for vm, sub, Kb in zip(viewmats, subsets, Ks)]
        return outs[0] if B == 1 else _stack_bands(outs, rows)
    width, height, bg = _image_settings(width, height, tile_size, cpu_kernel, background, device, dtype)
    nt = _launch_threads(num_threads)
    # every band's rows gathered at once (one gather per parameter, hence one scatter of its gradient), then
    # projected from their band's pose: in one launch by the SIMD kernels, else band by band
    band_ids = [_gather_subset(sub, N, device, ())[0] for sub in subsets]
    ids = torch.cat(band_ids)
    m, q, ls, ol, col = (t.index_select(0, ids) for t in params)
    q, ls = q.to(dtype), ls.to(dtype)
    cams = [_camera_tensors(Kb, None, vm, device, dtype) for vm, Kb in zip(viewmats, Ks)]
    counts = [len(bid) for bid in band_ids]
    tile_rows = torch.cat([torch.tensor([int(y0) // tile_size, (int(y1) - 1) // tile_size],
                                        dtype=torch.int32).expand(n, 2) for (y0, y1), n in zip(rows, counts)])
    if cpu_kernel == "simd":
        cam_of_row = torch.repeat_interleave(torch.arange(B, dtype=torch.int32), torch.tensor(counts))
        proj = project_gaussians_warp(m, q, ls, [vm64 for _, vm64 in cams], [K64 for K64, _ in cams], width,
                                      height, near=near, far=far, eps2d=eps2d, num_threads=nt, cam_of_row=cam_of_row)
    else:
        projs, a = [], 0
        for (K64, vm64), n in zip(cams, counts):
            projs.append(project_gaussians_warp(m[a:a + n], q[a:a + n], ls[a:a + n], vm64, K64, width, height,
                                                near=near, far=far, eps2d=eps2d, num_threads=nt, simd=False))
            a += n
        proj = Projection(*(torch.cat([getattr(p, f) for p in projs]) for f in Projection._fields))
    return _composite_warp_cpu(proj, ol, col, ids, width, height, tile_size, nt, bg, cpu_kernel,
                               tile_rows=tile_rows, n_bands=B)


def blend_weights(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    *,
    K,
    width: int,
    height: int,
    c2w,
    pixel_mask: torch.Tensor | None = None,
    subset: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    num_threads: int | None = None,
) -> torch.Tensor:
    """Per-Gaussian alpha-blending weight of one view: ``w_i = Σ_p T_ip α_ip`` over the image's pixels
    (or those of ``pixel_mask``).

    Exact and backend-independent: the rendered colour is linear in the colours,
    ``c_p = Σ_i T_ip α_ip c_i + T_p · background``, so the gradient of the (masked) red-channel sum
    with respect to ``colors[:, 0]`` is the weight. One forward and one backward pass; the map's
    parameters get no gradient.

    Args:
        means … colors: the map, shapes as in :func:`rasterize` (N, ...); detached here.
        K, width, height, c2w: the view (pixels; camera-to-world, OpenCV camera axes).
        pixel_mask: (height, width) bool pixels to sum over, or None for all.
        subset, background, backend, num_threads: as in :func:`rasterize`.
    Returns:
        (N,) float32 weights ≥ 0 (0 for Gaussians outside the view or the subset), on ``means.device``.
    """
    return _blend_weight_channels(means, quats, log_scales, opacity_logits, colors, K, width, height, c2w,
                                  pixel_mask, False, subset, background, backend, num_threads)[0]


def blend_weights_inside(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    colors: torch.Tensor,
    *,
    K,
    width: int,
    height: int,
    c2w,
    pixel_mask: torch.Tensor,
    subset: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    num_threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-Gaussian alpha-blending weight of one view inside ``pixel_mask`` and over the whole image, from one
    forward and one backward pass (:func:`blend_weights`: the red channel summed over the mask, the green channel
    over every pixel; the colour channels blend independently).

    Args: as :func:`blend_weights`; ``pixel_mask`` (height, width) bool is required.
    Returns:
        ``(inside, total)``: two (N,) float32 tensors ≥ 0 on ``means.device`` (``inside ≤ total``).
    """
    return _blend_weight_channels(means, quats, log_scales, opacity_logits, colors, K, width, height, c2w,
                                  pixel_mask, True, subset, background, backend, num_threads)


def _blend_weight_channels(means, quats, log_scales, opacity_logits, colors, K, width, height, c2w, pixel_mask,
                           with_total: bool, subset, background, backend, num_threads) -> tuple:
    """(weights in ``pixel_mask`` (or all pixels), and with ``with_total`` the weights over all pixels)."""
    cols = colors.detach().clone().requires_grad_(True)
    out = rasterize(means.detach(), quats.detach(), log_scales.detach(), opacity_logits.detach(), cols,
                    K=K, width=width, height=height, c2w=c2w, subset=subset, background=background,
                    backend=backend, num_threads=num_threads)
    red = out.color[..., 0]
    if pixel_mask is not None:
        red = red[pixel_mask.to(red.device)]
    total = red.sum()
    if with_total:
        total = total + out.color[..., 1].sum()
    total.backward()
    if cols.grad is None:
        zero = torch.zeros(means.shape[0], device=means.device)
        return zero, zero.clone()
    g = cols.grad.detach().float().clamp_min(0)
    return g[:, 0], g[:, 1]
