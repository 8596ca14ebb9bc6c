"""What a long mission's mapper remembers: its keyframes, the surface it has observed, and which
pixels of a new frame its map does not yet explain.

- :class:`KeyframeStore`: every keyframe of the mission, stored compactly (uint8 colour, float16
  depth, bool ROI: 3.0 B/pixel + ROI instead of 16 B/pixel as float32 tensors), bounded by
  ``stored_keyframes_max`` (the most redundant old keyframe is dropped), with the view sampler of
  multi-view optimisation: a draw from the recent window or from the whole mission, weighted towards
  keyframes that see the ROI. A keyframe may also keep a detail crop (its task region at a finer resolution,
  :mod:`gausslite.mapping.detail`); those crops are bounded by ``max_detail_bytes`` (the most redundant one is
  dropped, its keyframe stays). This follows MonoGS (Matsuki et al., CVPR 2024, Sec. 3.3.1: a window
  of recent keyframes plus randomly drawn past keyframes each iteration, against forgetting) and
  SplaTAM's covisibility-driven keyframe choice (Keetha et al., CVPR 2024, Sec. 3.5), with "sees the
  ROI" as the covisibility test.
- :class:`SurfaceVoxels`: the set of coarse voxels that valid depth has hit, in world metres. The
  scene-following Gaussian budget is ``gaussians_per_voxel × len(voxels)``.
- :func:`unexplained_mask`: SplaTAM's densification mask (Sec. 3.4, Eq. 9): pixels whose rendered
  silhouette is below 0.5, or where the rendered surface lies behind the observed depth by more than
  50 × the median depth error. New Gaussians are seeded only there.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from gausslite.camera import Intrinsics, backproject, rotation_angle
from gausslite.mapping.views import StoredKeyframe, StoredViews, closest_pose_pair, roi_box


class KeyframeStore(StoredViews):
    """The mission's keyframes, compact and bounded, with MVO's view sampler.

    Args:
        stored_keyframes_max: bound on stored keyframes; when exceeded, the old keyframe (outside the
            recent ``protect_recent``) whose pose is closest to its predecessor's is dropped
            (translation in metres + rotation angle in radians × ``rot_weight_m``).
        protect_recent: this many newest keyframes are never dropped (the MVO window).
        max_detail_bytes: bound on the bytes of the keyframes' detail crops (:mod:`gausslite.mapping.detail`); past
            it, the detail crop of the keyframe whose pose is closest to another detail keyframe's is dropped (the
            older of the pair; the newest keyframe's crop last), the keyframe itself stays.
    Attributes:
        n_dropped: keyframes dropped so far. n_detail_dropped: detail crops dropped so far.
    Raises:
        ValueError: ``stored_keyframes_max`` or ``max_detail_bytes`` below 1.
    """

    def __init__(self, stored_keyframes_max: int = 500, protect_recent: int = 8, rot_weight_m: float = 0.5,
                 max_detail_bytes: int = 64 << 20) -> None:
        if stored_keyframes_max < 1 or max_detail_bytes < 1:
            raise ValueError(f"stored_keyframes_max and max_detail_bytes must be >= 1, got {stored_keyframes_max}, "
                             f"{max_detail_bytes}")
        self.stored_keyframes_max = int(stored_keyframes_max)
        self.protect_recent = int(protect_recent)
        self.rot_weight_m = float(rot_weight_m)
        self.max_detail_bytes = int(max_detail_bytes)
        super().__init__()
        self.n_dropped = 0
        self.n_detail_dropped = 0

    @property
    def detail_nbytes(self) -> int:
        """Bytes held by the stored keyframes' detail crops (part of :attr:`nbytes`)."""
        return sum(k.detail.nbytes for k in self._items if k.detail is not None)

    def state_dict(self, newest: Optional[int] = None) -> dict:
        """``{"keyframes": [...]}``: the newest ``newest`` stored keyframes (None: all) as plain dicts of their
        compact fields (copies: CPU tensors; ``torch.save``-able). Copies, because training refines a stored
        keyframe's pose in place."""
        first = 0 if newest is None else max(0, len(self._items) - newest)
        return {"keyframes": self._dump(self._items[first:])}

    def load_state_dict(self, state: dict) -> None:
        """Replace the stored keyframes by copies of those of a :meth:`state_dict`.

        Raises:
            KeyError / TypeError: a dict without ``keyframes`` or with keyframes of other fields.
        """
        self._items = self._undump(state["keyframes"])

    def add(self, kf) -> StoredKeyframe:
        """Store a :class:`~gausslite.mapping.views.Keyframe` (float tensors) compactly; returns it.

        Drops the most redundant old keyframe when the store is over ``stored_keyframes_max``, then detail crops while
        they hold more than ``max_detail_bytes``.
        """
        st = kf.compact()
        self._items.append(st)
        if len(self._items) > self.stored_keyframes_max:
            self._drop_redundant()
        while st.detail is not None and self.detail_nbytes > self.max_detail_bytes:
            self._drop_detail()
        return st

    def _drop_detail(self) -> None:
        """Drop one detail crop: of the closest pair of detail keyframes (pose distance as :meth:`_drop_redundant`),
        the older one's; the only one left is dropped last."""
        idx = [i for i, k in enumerate(self._items) if k.detail is not None]
        if len(idx) == 1:
            j = idx[0]
        else:
            c2w = torch.stack([self._items[i].c2w for i in idx]).numpy()
            j = idx[closest_pose_pair(c2w, self.rot_weight_m)[0]]
        self._items[j].detail = None
        self.n_detail_dropped += 1

    def _drop_redundant(self) -> None:
        n_old = len(self._items) - self.protect_recent
        if n_old < 2:  # nothing but the window: drop the oldest
            self._items.pop(0)
            self.n_dropped += 1
            return
        c2w = torch.stack([k.c2w for k in self._items[: n_old + 1]]).numpy()
        dt = np.linalg.norm(c2w[1:, :3, 3] - c2w[:-1, :3, 3], axis=1)
        rel = np.einsum("nji,njk->nik", c2w[:-1, :3, :3], c2w[1:, :3, :3])
        ang = rotation_angle(rel)
        cost = dt + self.rot_weight_m * ang  # distance of keyframe j+1 to keyframe j, j+1 ∈ [1, n_old]
        j = int(np.argmin(cost[: n_old - 1])) + 1  # never the first keyframe, never the window
        self._items.pop(j)
        self.n_dropped += 1

    def set_roi(self, i: int, roi: Optional[np.ndarray]) -> None:
        """Replace keyframe ``i``'s ROI by ``roi`` ((H, W) bool, or None: no ROI), with its box (a new task). Its
        detail crop, cut around the old task's region, is dropped.

        Raises:
            ValueError: a mask of another size than the keyframe.
        """
        k = self._items[i]
        if roi is not None and tuple(np.shape(roi)) != (k.height, k.width):
            raise ValueError(f"keyframe {k.frame_id}: roi {np.shape(roi)} does not match {k.width}x{k.height}")
        box = roi_box(roi)
        k.roi = None if box is None else torch.from_numpy(np.asarray(roi, bool).copy())
        k.roi_box = box
        k.detail = None

    def clear_roi(self) -> None:
        """Every stored keyframe loses its ROI and its detail crop (the task changed)."""
        for i in range(len(self._items)):
            self.set_roi(i, None)

    def load(self, i: int, device: torch.device):
        """Keyframe ``i`` as a float :class:`~gausslite.mapping.views.Keyframe` on ``device``
        (:meth:`StoredKeyframe.to_keyframe`)."""
        return self._items[i].to_keyframe(device)

    def sample_index(self, rng: np.random.Generator, window: int, recent_prob: float,
                     roi_weight: float = 0.0, roi_only: bool = False) -> int:
        """Index of a training view for one iteration.

        With probability ``recent_prob`` (or when the store holds no more than ``window``
        keyframes) a uniform draw from the ``window`` newest keyframes; otherwise a draw over the
        whole mission with weight ``1 + roi_weight`` for keyframes that see the ROI and 1 for the
        others (``roi_weight=0``: uniform over the mission). ``roi_only``: the same draw among the
        keyframes that see the ROI alone (an ROI-phase iteration; all keyframes when none does).

        Raises:
            ValueError: the store is empty.
        """
        n = len(self._items)
        if n == 0:
            raise ValueError("no keyframes to sample from")
        # the draw's pool: every keyframe, or (roi_only) the ROI keyframes in store order
        pool = [i for i, k in enumerate(self._items) if k.sees_roi] if roi_only else []
        m = len(pool) or n
        if m <= window or rng.random() < recent_prob:
            w = min(window, m)
            j = m - w + int(rng.integers(w))
            return pool[j] if pool else j
        if pool:
            return pool[int(rng.integers(m))]
        if roi_weight <= 0:
            return int(rng.integers(n))
        wts = np.array([1.0 + roi_weight * k.sees_roi for k in self._items])
        return int(rng.choice(n, p=wts / wts.sum()))


#: offset of packed voxel keys: integer voxel indices in [-2^20, 2^20) pack into 21 bits per axis
VOXEL_KEY_OFFSET = 1 << 20


def pack_voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """(M,) int64 keys of integer voxel indices ``ijk`` (M, 3), clipped to ±2^20 per axis (±52 km at
    5 cm voxels); shared by the scene budget and the task region (:mod:`gausslite.sharing`)."""
    q = np.clip(np.asarray(ijk, np.int64) + VOXEL_KEY_OFFSET, 0, 2 * VOXEL_KEY_OFFSET - 1)
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


class SurfaceVoxels:
    """The set of coarse world voxels (edge ``voxel_m`` metres) that valid depth has observed.

    The scene-following budget counts them: it grows with the observed surface, not with the
    image size. Keys: :func:`pack_voxel_keys`.
    """

    def __init__(self, voxel_m: float = 0.05, pixel_stride: int = 4) -> None:
        if voxel_m <= 0:
            raise ValueError(f"voxel_m must be > 0, got {voxel_m}")
        self.voxel_m = float(voxel_m)
        self.pixel_stride = int(pixel_stride)
        self._keys = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return int(self._keys.size)

    def state_dict(self) -> dict:
        """``{"voxel_keys": (V,) int64}``: the observed voxels' packed keys (:func:`pack_voxel_keys`)."""
        return {"voxel_keys": self._keys.copy()}

    def load_state_dict(self, state: dict) -> None:
        """Replace the observed voxels by those of a :meth:`state_dict` (none when the key is absent)."""
        self._keys = np.asarray(state.get("voxel_keys", np.zeros(0, np.int64)), np.int64)

    def add_frame(self, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray) -> int:
        """Add the voxels hit by a frame's valid depth; returns the number of new voxels."""
        s = self.pixel_stride
        d = depth[::s, ::s]  # pixel (u', v') of the strided image is pixel (s u', s v'): K / s
        sub = Intrinsics(intr.fx / s, intr.fy / s, intr.cx / s, intr.cy / s, d.shape[1], d.shape[0])
        pts = backproject(d, sub, np.asarray(c2w, np.float64))[d > 0]
        if pts.size == 0:
            return 0
        keys = np.unique(pack_voxel_keys(np.floor(pts / self.voxel_m).astype(np.int64)))
        n0 = self._keys.size
        self._keys = np.union1d(self._keys, keys)
        return int(self._keys.size - n0)

    @property
    def area_m2(self) -> float:
        """Rough observed surface area: one voxel face per occupied voxel (m²)."""
        return len(self) * self.voxel_m ** 2


def unexplained_mask(
    depth_gt: np.ndarray,
    alpha: np.ndarray,
    depth_render: np.ndarray,
    alpha_threshold: float = 0.5,
    depth_error_factor: float = 50.0,
) -> np.ndarray:
    """Pixels of a new frame that the current map does not explain (SplaTAM Eq. 9).

    A valid-depth pixel is unexplained when the rendered silhouette (accumulated alpha) is below
    ``alpha_threshold``, or when the rendered depth lies *behind* the observed depth by more than
    ``depth_error_factor`` × the median absolute depth error over the silhouette (new geometry in
    front of the map).

    Args:
        depth_gt: (H, W) observed depth, metres, 0 = invalid.
        alpha: (H, W) rendered accumulated opacity in [0, 1].
        depth_render: (H, W) rendered expected depth, metres.
    Returns:
        (H, W) bool mask, always within ``depth_gt > 0``.
    """
    valid = depth_gt > 0
    sil = alpha >= alpha_threshold
    mask = valid & ~sil
    both = valid & sil
    if both.any():
        err = np.abs(depth_render - depth_gt)
        med = float(np.median(err[both]))
        mask |= both & (depth_render > depth_gt) & (err > depth_error_factor * med)
    return mask
