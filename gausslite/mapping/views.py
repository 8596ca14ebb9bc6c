"""Training views of the mapper: the :class:`Keyframe` (float tensors on the mapper's device) and the
crops, windows and pyramid levels an iteration renders (paper Sec. III-D).

A keyframe's compact form (uint8 colour, float16 depth, CPU) is its serialisation: :meth:`Keyframe.compact`
gives it and :meth:`~gausslite.mapping.memory.StoredKeyframe.to_keyframe` reads it back; the mission's
keyframe store and the mapper's checkpoints hold that form.

A keyframe may carry a *detail crop* (``detail``): the same view's task region at a finer resolution than the
mapping resolution (:mod:`gausslite.mapping.detail`), a :class:`Keyframe` of its own with the same frame id that
shares the keyframe's pose tensor, so a refined or corrected pose moves both.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from gausslite.camera import rotation_angle
from gausslite.datasets.base import Frame


@dataclass
class Keyframe:
    """A training view kept in the mapper's window (tensors on the mapper's device).

    rgb (H,W,3) float32 [0,1]; depth (H,W) float32 metres (0 invalid); c2w (4,4) float64;
    K (3,3) float32; roi (H,W) bool or None; roi_box (x0, y0, x1, y1) pixels, the half-open
    bounding box of the ROI pixels, or None when the ROI is absent or empty; detail: the keyframe's detail crop
    (:mod:`gausslite.mapping.detail`: the task region at a finer resolution, its own size and K, the same frame id
    and the same ``c2w`` tensor) or None.
    """

    frame_id: int
    rgb: torch.Tensor
    depth: torch.Tensor
    c2w: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    roi: Optional[torch.Tensor]
    roi_box: Optional[tuple[int, int, int, int]] = None
    #: cached :func:`gausslite.metrics.ssim_gt_stats` of ``rgb`` (filled by the first loss on this view;
    #: the mapper also keeps recent views' statistics, see ``MapperConfig.performance.ssim_cache_views``)
    ssim_stats: Optional[tuple] = field(default=None, repr=False, compare=False)
    detail: Optional["Keyframe"] = field(default=None, repr=False, compare=False)

    def to(self, device: torch.device | str) -> "Keyframe":
        """This keyframe with its tensors (and its detail crop's) on ``device`` (a shallow copy; no cached SSIM
        statistics)."""
        move = {k: getattr(self, k).to(device) for k in ("rgb", "depth", "c2w", "K")}
        if self.roi is not None:
            move["roi"] = self.roi.to(device)
        if self.detail is not None:
            move["detail"] = dataclasses.replace(self.detail.to(device), c2w=move["c2w"])
        return dataclasses.replace(self, ssim_stats=None, **move)

    def compact(self) -> "StoredKeyframe":
        """This keyframe in its compact stored form (CPU; colour rounded to uint8, depth to float16), with its
        detail crop's compact form sharing the stored pose tensor."""
        st = StoredKeyframe(
            frame_id=int(self.frame_id), rgb=(self.rgb.detach().clamp(0, 1) * 255.0 + 0.5).to("cpu", torch.uint8),
            depth=self.depth.detach().to("cpu", torch.float16), c2w=self.c2w.detach().to("cpu", torch.float64),
            K=self.K.detach().to("cpu", torch.float32), width=int(self.width), height=int(self.height),
            roi=None if self.roi is None else self.roi.detach().to("cpu", torch.bool), roi_box=self.roi_box,
        )
        if self.detail is not None:
            st.detail = dataclasses.replace(self.detail.compact(), c2w=st.c2w)
        return st


@dataclass
class StoredKeyframe:
    """A :class:`Keyframe` in its compact form (CPU tensors): the keyframe store's and checkpoints' serialisation.

    rgb (H,W,3) uint8; depth (H,W) float16 metres (0 invalid; ≈1 mm resolution at 2 m);
    c2w (4,4) float64 camera-to-world (OpenCV camera axes, metres); K (3,3) float32 pixels;
    roi (H,W) bool or None; roi_box (x0,y0,x1,y1) half-open pixel box of the ROI or None; detail: the compact
    detail crop (:mod:`gausslite.mapping.detail`; its ``c2w`` is this keyframe's tensor) or None.
    """

    frame_id: int
    rgb: torch.Tensor
    depth: torch.Tensor
    c2w: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    roi: Optional[torch.Tensor]
    roi_box: Optional[tuple[int, int, int, int]]
    detail: Optional["StoredKeyframe"] = None

    @property
    def nbytes(self) -> int:
        """Bytes held by the image tensors (the detail crop's included)."""
        n = self.rgb.numel() + 2 * self.depth.numel()
        n += self.detail.nbytes if self.detail is not None else 0
        return n + (self.roi.numel() if self.roi is not None else 0)

    @property
    def sees_roi(self) -> bool:
        """True when the keyframe has at least one ROI pixel."""
        return self.roi_box is not None

    def to_keyframe(self, device: torch.device) -> Keyframe:
        """This keyframe as a float :class:`Keyframe` on ``device`` (rgb (H,W,3) float32 in [0, 1], depth (H,W)
        float32 metres; c2w, K and roi shared with this object on CPU), with its detail crop likewise (sharing the
        keyframe's ``c2w`` tensor)."""
        kf = Keyframe(
            frame_id=self.frame_id, rgb=self.rgb.to(device, torch.float32) / 255.0,
            depth=self.depth.to(device, torch.float32), c2w=self.c2w.to(device), K=self.K.to(device),
            width=self.width, height=self.height, roi=None if self.roi is None else self.roi.to(device),
            roi_box=self.roi_box,
        )
        if self.detail is not None:
            kf.detail = dataclasses.replace(self.detail.to_keyframe(device), c2w=kf.c2w)
        return kf



def roi_box(roi: Optional[np.ndarray]) -> Optional[tuple[int, int, int, int]]:
    """Bounding box ``(x0, y0, x1, y1)`` in pixels (x1, y1 exclusive) of an (H, W) bool ROI; None when the ROI is
    None or empty (``Keyframe.roi_box``)."""
    if roi is None:
        return None
    ys, xs = np.nonzero(roi)
    if not ys.size:
        return None
    return (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)


class StoredViews:
    """A list of :class:`StoredKeyframe` views (compact, CPU) with what every store of training views shares: length,
    indexing, iteration, their bytes, a refined pose written back, and the checkpoint form of the views."""

    def __init__(self) -> None:
        self._items: list[StoredKeyframe] = []

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int) -> StoredKeyframe:
        return self._items[i]

    def __iter__(self):
        return iter(self._items)

    @property
    def nbytes(self) -> int:
        """Bytes held by the stored views' images."""
        return sum(k.nbytes for k in self._items)

    def set_pose(self, frame_id: int, c2w: torch.Tensor) -> bool:
        """Replace the stored pose of view ``frame_id`` by ``c2w`` (4, 4) float64 camera-to-world (pose refinement);
        False when that view is not (or no longer) stored."""
        for k in reversed(self._items):
            if k.frame_id == int(frame_id):
                k.c2w.copy_(c2w.detach().to("cpu", torch.float64))
                if k.detail is not None:  # the same tensor unless a caller replaced it
                    k.detail.c2w.copy_(k.c2w)
                return True
        return False

    @staticmethod
    def _dump(items) -> list:
        """``items`` as plain dicts of their compact fields (CPU tensor copies: training refines poses in place); a
        detail crop as a nested dict under ``"detail"`` (no key without one)."""
        out = []
        for k in items:
            d = {f.name: (v.clone() if torch.is_tensor(v := getattr(k, f.name)) else v)
                 for f in dataclasses.fields(k) if f.name != "detail"}
            if k.detail is not None:
                d["detail"] = StoredViews._dump([k.detail])[0]
            out.append(d)
        return out

    @staticmethod
    def _undump(dicts) -> list:
        """Views from :meth:`_dump`'s dicts (copies; a detail crop shares its keyframe's pose tensor again)."""
        out = []
        for d in dicts:
            nested = d.get("detail")
            k = StoredKeyframe(**{n: v.clone() if torch.is_tensor(v) else v for n, v in d.items() if n != "detail"})
            if nested is not None:
                k.detail = dataclasses.replace(StoredViews._undump([nested])[0], c2w=k.c2w)
            out.append(k)
        return out


def keyframe_from_frame(frame: Frame, device: torch.device, roi: Optional[np.ndarray] = None) -> Keyframe:
    """Convert a posed RGB-D ``Frame`` (uint8 rgb (H, W, 3), float32 depth (H, W) metres, ``c2w`` (4, 4)
    camera-to-world, pinhole intrinsics in pixels) and its optional (H, W) bool ROI into a tensor ``Keyframe``.

    Raises:
        ValueError: rgb, depth or roi of another size than the intrinsics' width × height.
    """
    h, w = frame.intrinsics.height, frame.intrinsics.width
    if np.shape(frame.rgb) != (h, w, 3) or np.shape(frame.depth) != (h, w):
        raise ValueError(f"frame {frame.frame_id}: rgb {np.shape(frame.rgb)} / depth {np.shape(frame.depth)} do not "
                         f"match {w}x{h}")
    if roi is not None and np.shape(roi) != (h, w):
        raise ValueError(f"frame {frame.frame_id}: roi {np.shape(roi)} does not match {w}x{h}")
    box = roi_box(roi)
    return Keyframe(
        frame_id=frame.frame_id,
        rgb=torch.from_numpy(frame.rgb).to(device, torch.float32) / 255.0,
        depth=torch.from_numpy(np.ascontiguousarray(frame.depth)).to(device, torch.float32),
        c2w=torch.from_numpy(np.asarray(frame.c2w, dtype=np.float64)).to(device),
        K=torch.from_numpy(frame.intrinsics.K).to(device, torch.float32),
        width=frame.intrinsics.width,
        height=frame.intrinsics.height,
        roi=None if roi is None else torch.from_numpy(np.asarray(roi, dtype=bool)).to(device),
        roi_box=box,
    )


def downscale_keyframe(kf: Keyframe, factor: int) -> Keyframe:
    """The keyframe at 1/``factor`` resolution, for coarse full-image iterations (a two-level image
    pyramid, as Photo-SLAM's Gaussian-pyramid training; cost of an iteration ∝ pixels).

    Colour is the ``factor`` × ``factor`` area mean; depth the mean of the valid (> 0) depths of a block
    (0 where none is valid); the ROI a block's any. Intrinsics follow the pixel-centre convention of
    :mod:`gausslite.camera`: fx' = fx / f, cx' = (cx + 0.5) / f − 0.5 (same for y). Trailing rows and
    columns that do not fill a block are dropped. ``factor`` 1 returns ``kf`` itself.
    Raises ValueError for a factor < 1 or one that leaves no pixel.
    """
    f = int(factor)
    if f < 1 or kf.width < f or kf.height < f:
        raise ValueError(f"cannot downscale a {kf.width}x{kf.height} keyframe by {factor}")
    if f == 1:
        return kf
    h, w = kf.height // f, kf.width // f
    rgb = kf.rgb[: h * f, : w * f].reshape(h, f, w, f, 3).mean(dim=(1, 3))
    d = kf.depth[: h * f, : w * f].reshape(h, f, w, f)
    valid = (d > 0).sum(dim=(1, 3))
    depth = torch.where(valid > 0, d.sum(dim=(1, 3)) / valid.clamp_min(1), torch.zeros((), dtype=d.dtype))
    K = kf.K.clone()
    K[0, 0] /= f
    K[1, 1] /= f
    K[0, 2] = (K[0, 2] + 0.5) / f - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / f - 0.5
    roi, box = None, None
    if kf.roi is not None:
        roi = kf.roi[: h * f, : w * f].reshape(h, f, w, f).any(dim=3).any(dim=1)
        ys, xs = torch.nonzero(roi, as_tuple=True)
        if len(ys):
            box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    return Keyframe(frame_id=kf.frame_id, rgb=rgb.contiguous(), depth=depth.contiguous(), c2w=kf.c2w, K=K,
                    width=w, height=h, roi=roi, roi_box=box)


def window_keyframe(kf: Keyframe, x0: int, y0: int, x1: int, y1: int) -> Keyframe:
    """The keyframe restricted to pixels [x0, x1) × [y0, y1) (clipped to the image): the principal
    point moves with the window (cx -= x0, cy -= y0), so the window's render shows the same pixels as the
    full render (see :func:`crop_keyframe`). The ROI, if any, is cropped along."""
    x0, y0 = max(0, int(x0)), max(0, int(y0))
    x1, y1 = min(kf.width, int(x1)), min(kf.height, int(y1))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"empty window [{x0}, {x1}) x [{y0}, {y1}) of keyframe {kf.frame_id}")
    K = kf.K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    roi, box = None, None
    if kf.roi is not None:
        roi = kf.roi[y0:y1, x0:x1]
        if kf.roi_box is not None:
            bx0, by0, bx1, by1 = kf.roi_box
            cx0, cy0, cx1, cy1 = max(bx0, x0), max(by0, y0), min(bx1, x1), min(by1, y1)
            box = (cx0 - x0, cy0 - y0, cx1 - x0, cy1 - y0) if cx1 > cx0 and cy1 > cy0 else None
    return Keyframe(frame_id=kf.frame_id, rgb=kf.rgb[y0:y1, x0:x1], depth=kf.depth[y0:y1, x0:x1], c2w=kf.c2w,
                    K=K, width=x1 - x0, height=y1 - y0, roi=roi, roi_box=box)


def random_window(kf: Keyframe, fraction: float, rng: np.random.Generator) -> Keyframe:
    """A window of up to ``fraction`` of the keyframe's area (the image's aspect ratio) for a full-image
    iteration: stochastic pixel subsampling at full resolution (no aliasing, unlike a downscaled view).

    The window's corner is drawn uniformly from positions that let it hang over the image border by up to
    its size less 8 pixels, and it is clipped to the image: every pixel is then covered about equally
    often (a window kept inside the image would cover a corner pixel 1/((W−w+1)(H−h+1)) as often as the
    centre). Windows at the border are smaller, hence cheaper.
    """
    s = float(np.sqrt(fraction))
    w = min(kf.width, max(16, int(round(kf.width * s))))
    h = min(kf.height, max(16, int(round(kf.height * s))))
    mx, my = min(8, w), min(8, h)
    x0 = int(rng.integers(-(w - mx), kf.width - mx + 1))
    y0 = int(rng.integers(-(h - my), kf.height - my + 1))
    return window_keyframe(kf, x0, y0, x0 + w, y0 + h)


def crop_keyframe(kf: Keyframe, pad: int) -> Keyframe:
    """The keyframe restricted to its ROI bounding box grown by ``pad`` pixels (clipped to the image).

    The principal point moves with the crop (cx -= x0, cy -= y0), so a render with the cropped K at
    the cropped size shows the same pixels as the full render, up to the EWA Jacobian clamp that
    follows the image bounds (Gaussians centred far outside the crop; ≤ 3e-3 colour in the tests).
    Raises ValueError without an ROI.
    """
    if kf.roi_box is None or kf.roi is None:
        raise ValueError(f"keyframe {kf.frame_id} has no ROI to crop to")
    bx0, by0, bx1, by1 = kf.roi_box
    return window_keyframe(kf, bx0 - pad, by0 - pad, bx1 + pad, by1 + pad)



def closest_pose_pair(c2w: np.ndarray, rot_weight_m: float) -> tuple[int, int]:
    """The two views whose poses lie closest: translation distance in metres plus the relative rotation angle in
    radians times ``rot_weight_m`` (the rule by which the keyframe and ROI view stores drop a redundant view).

    Args:
        c2w: (N, 4, 4) camera-to-world poses, N ≥ 2 (metres, OpenCV camera axes).
        rot_weight_m: metres one radian of rotation counts as.
    Returns:
        the pair's indices ``(a, b)``, ``a < b``.
    """
    t = c2w[:, :3, 3]
    dt = np.linalg.norm(t[:, None] - t[None], axis=-1)
    rel = np.einsum("aji,bjk->abik", c2w[:, :3, :3], c2w[:, :3, :3])
    ang = rotation_angle(rel)
    cost = dt + rot_weight_m * ang
    np.fill_diagonal(cost, np.inf)
    a, b = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return int(min(a, b)), int(max(a, b))
