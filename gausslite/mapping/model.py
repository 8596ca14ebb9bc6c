"""Learnable Gaussian parameters with their Adam optimiser, kept consistent through density control.

The map's structure changes every mapped frame (new seeds, clone/split, prune, budget cap). This
class owns the ``torch.nn.Parameter`` tensors and the Adam state, and rebuilds both from a
``GaussianMap`` plus a ``parent_index`` that says which old row each new row derives from, so Adam
moments survive density control for the first row of each parent; brand-new rows (parent −1), clones
and further split daughters start from zero moments, as in 3DGS (``densification_postfix``) and gsplat.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

from gausslite.gaussians import GaussianMap
from gausslite.mapping.adam import Adam
from gausslite.mapping.config import LearningRates
from gausslite.mapping.poses import quat_mul, quat_of_rotvec

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "colors")


def cosine_lr_factor(it: int, iters: int, final: float) -> float:
    """Learning-rate factor of iteration ``it`` (0-based) of ``iters``: a cosine from 1 at the first
    iteration down to ``final`` at the last (SGDR without restarts, Loshchilov & Hutter 2017)."""
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * it / max(int(iters) - 1, 1)))


class GaussianModel:
    """Parameters of a ``GaussianMap`` under optimisation.

    Attributes:
        params: dict name → ``nn.Parameter`` for the five learnable fields (shapes as GaussianMap).
        active: (N,) bool task flag a_i. kappa: (N,) int64 κ_i.
        ids: (N,) int64 stable per-agent Gaussian ids (CPU), carried along ``parent_index`` by
            :meth:`set_map`: the first row deriving from a parent keeps the parent's id (a kept
            original, or the first daughter of a split), every further child (clones, the other
            daughters) and every new seed (parent −1) gets a fresh id; ids of removed rows (prune,
            budget replacement) are never reused.  Delta pushes key on them.
        anchors: (N,) int64 (CPU) keyframe anchor of each row: the frame id of the mapped frame whose seeds it
            derives from, −1 for an unanchored row (a map loaded from outside). Every child of a parent (kept
            original, clones, split daughters) keeps the parent's anchor; new seeds take ``set_map``'s
            ``new_anchor``. :meth:`Mapper.apply_pose_corrections
            <gausslite.mapping.mapper.Mapper.apply_pose_corrections>` moves the rows of a keyframe whose pose changed.
        optimizer: :class:`~gausslite.mapping.adam.Adam` (``torch.optim.Adam``'s update) with one parameter group
            per field.
    """

    def __init__(self, lr: LearningRates, device: str | torch.device = "cpu") -> None:
        self.lr = lr
        self.device = torch.device(device)
        self.params: dict[str, torch.nn.Parameter] = {}
        self.optimizer: Optional[Adam] = None
        self.ids = torch.zeros(0, dtype=torch.int64)
        self.anchors = torch.zeros(0, dtype=torch.int64)
        self._next_id = 0
        self.set_map(GaussianMap.empty(device=self.device))

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def active_size(self) -> tuple[int, float]:
        """``(task Gaussians, the median over them of their largest axis's standard deviation in metres)``;
        ``(0, 0.0)`` without task Gaussians."""
        n = int(self.active.sum())
        if n == 0:
            return 0, 0.0
        with torch.no_grad():
            largest = self.params["log_scales"].detach()[self.active].max(dim=1).values
            return n, float(torch.exp(largest.median()))

    def to_map(self) -> GaussianMap:
        """A detached ``GaussianMap`` snapshot of the current parameters (shares storage)."""
        p = {k: v.detach() for k, v in self.params.items()}
        return GaussianMap(active=self.active, kappa=self.kappa, **p)

    def set_map(self, gmap: GaussianMap, parent_index: Optional[torch.Tensor] = None, new_anchor: int = -1) -> None:
        """Replace the parameters by ``gmap``'s fields, carrying Adam state, stable ids and keyframe anchors along
        ``parent_index``.

        Args:
            gmap: the new map (its tensors are copied into fresh parameters).
            parent_index: (M,) int64, for each row of ``gmap`` the row of the current parameters it
                derives from, or −1 for a brand-new Gaussian. The first row of each parent carries its Adam
                moments; other rows of the same parent (clones, second split daughters) and brand-new rows
                start from zero moments. None drops all optimiser state.
            new_anchor: the keyframe anchor (frame id) of the brand-new rows (parent −1, or every row when
                ``parent_index`` is None); −1 = unanchored.
        """
        old_state = {}
        old_n = len(self) if self.params else 0
        if self.optimizer is not None and parent_index is not None:
            for name in PARAM_NAMES:
                st = self.optimizer.state.get(self.params[name], None)
                if st:
                    old_state[name] = st
        if parent_index is not None and int(parent_index.shape[0]) != len(gmap.means):
            raise ValueError(f"parent_index has {parent_index.shape[0]} rows, map has {len(gmap.means)}")
        self.ids = self._carry_ids(parent_index, len(gmap.means))
        self.anchors = self._carry_anchors(parent_index, len(gmap.means), new_anchor)
        new_params = {
            name: torch.nn.Parameter(getattr(gmap, name).detach().to(self.device, torch.float32).clone().contiguous())
            for name in PARAM_NAMES
        }
        self.active = gmap.active.to(self.device, torch.bool).clone()
        self.kappa = gmap.kappa.to(self.device, torch.int64).clone()
        groups = [{"params": [new_params[n]], "lr": getattr(self.lr, n), "name": n} for n in PARAM_NAMES]
        opt = Adam(groups, eps=1e-15)
        if parent_index is not None and old_state:
            pi = parent_index.to(self.device)
            # only the first child of a parent keeps its Adam moments; clones and further daughters start
            # from zero moments (3DGS ``densification_postfix``, gsplat's strategy). A clone that inherited
            # them would take exactly its parent's steps (co-located copies get proportional gradients,
            # which Adam normalises away), never separate, and be cloned again at every density step:
            # stacks of up to 11 identical Gaussians formed bright specks (room0 map-ottomans, 8 dB ROI PSNR)
            has_parent = self._first_children(pi).to(self.device)
            src = pi.clamp_min(0)
            for name, st in old_state.items():
                new_st = {}
                for key, val in st.items():
                    if torch.is_tensor(val) and val.dim() > 0 and val.shape[0] == old_n:
                        carried = val[src].clone()
                        carried[~has_parent] = 0
                        new_st[key] = carried
                    else:
                        new_st[key] = val.clone() if torch.is_tensor(val) else val
                opt.state[new_params[name]] = new_st
        self.params = new_params
        self.optimizer = opt

    def state_dict(self) -> dict:
        """CPU copy of the map for checkpoints: ``gaussians`` (the :class:`GaussianMap` fields, κ and task flags
        included), ``ids`` (N,) int64, ``next_id`` and ``anchors`` (N,) int64; not the Adam moments (a loaded model
        restarts them at zero, as for new seeds)."""
        g = self.to_map().to("cpu")
        return {"gaussians": {f: getattr(g, f).clone() for f in ("means", "quats", "log_scales", "opacity_logits",
                                                                 "colors", "active", "kappa")},
                "ids": self.ids.clone(), "next_id": int(self._next_id), "anchors": self.anchors.clone()}

    def load_state_dict(self, state: dict) -> None:
        """Replace the map by a :meth:`state_dict`'s; its stable ids and keyframe anchors are kept when present and
        of the map's length (otherwise the rows get fresh ids and no anchor, −1).

        Raises:
            KeyError / TypeError / ValueError: no ``gaussians``, or fields of inconsistent shapes.
        """
        self.set_map(GaussianMap(**{k: v.to(self.device) for k, v in state["gaussians"].items()}))
        if "ids" in state and int(state["ids"].shape[0]) == len(self):
            self.ids = state["ids"].clone()
            self._next_id = int(state["next_id"])
        anchors = state.get("anchors")
        if anchors is not None and int(anchors.shape[0]) == len(self):
            self.anchors = anchors.to("cpu", torch.int64).clone()

    @staticmethod
    def _first_children(parent_index: torch.Tensor) -> torch.Tensor:
        """(M,) bool on CPU: rows that are the first (in row order) of their parent's children. The
        original of a clone comes first in :meth:`GaussianMap.densify`'s row order, so it is the one."""
        pi = parent_index.detach().to("cpu", torch.int64)
        rows = torch.nonzero(pi >= 0).squeeze(1)
        par = pi[rows]
        # first occurrence of each parent (rows are in order): stable sort by parent
        order = torch.sort(par, stable=True).indices
        sp = par[order]
        first = torch.ones_like(sp, dtype=torch.bool)
        first[1:] = sp[1:] != sp[:-1]
        out = torch.zeros(len(pi), dtype=torch.bool)
        out[rows[order[first]]] = True
        return out

    def _carry_ids(self, parent_index: Optional[torch.Tensor], n_new: int) -> torch.Tensor:
        """(n_new,) int64 ids of the rows of a new map (see the ``ids`` attribute)."""
        ids = torch.empty(n_new, dtype=torch.int64)
        if parent_index is None:
            fresh = torch.ones(n_new, dtype=torch.bool)
        else:
            pi = parent_index.detach().to("cpu", torch.int64)
            if pi.numel() and int(pi.max()) >= len(self.ids):
                raise ValueError(f"parent_index refers to row {int(pi.max())} of a {len(self.ids)}-row map")
            inherit = self._first_children(pi)
            ids[inherit] = self.ids[pi[inherit]]
            fresh = ~inherit
        k = int(fresh.sum())
        ids[fresh] = torch.arange(self._next_id, self._next_id + k, dtype=torch.int64)
        self._next_id += k
        return ids

    def _carry_anchors(self, parent_index: Optional[torch.Tensor], n_new: int, new_anchor: int) -> torch.Tensor:
        """(n_new,) int64 keyframe anchors of the rows of a new map (see the ``anchors`` attribute)."""
        out = torch.full((n_new,), int(new_anchor), dtype=torch.int64)
        if parent_index is not None:
            pi = parent_index.detach().to("cpu", torch.int64)
            has = pi >= 0
            out[has] = self.anchors[pi[has]]
        return out

    @torch.no_grad()
    def move_rows(self, rows: torch.Tensor, T: np.ndarray) -> None:
        """Apply the world-frame rigid transform ``T`` to the Gaussians ``rows``: ``means ← R means + t``,
        ``quats ← q_R ⊗ quats`` (their rotations turn with the frame; scales, opacity and colour are intrinsic).
        Their Adam moments of the two moved fields restart at zero (as for new rows: moments taken in the old
        frame do not apply in the new one).

        Args:
            rows: (K,) int64 row indices (any device). T: (4, 4) float64 rigid transform (rotation R, translation t
                in metres).
        Raises:
            ValueError: ``T`` not a finite (4, 4) rigid transform.
        """
        T = np.asarray(T, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3),
                                                                              atol=1e-6):
            raise ValueError(f"expected a finite (4, 4) rigid transform, got {T!r}")
        rows = rows.to(self.device, torch.int64)
        if rows.numel() == 0:
            return
        R = torch.from_numpy(T[:3, :3]).to(self.device)
        t = torch.from_numpy(T[:3, 3]).to(self.device)
        means, quats = self.params["means"], self.params["quats"]
        moved = means[rows].double() @ R.T + t
        means.index_copy_(0, rows, moved.to(means.dtype))
        qR = quat_of_matrix(T[:3, :3]).to(self.device, quats.dtype)
        quats.index_copy_(0, rows, quat_mul(qR, quats[rows]))
        for p in (means, quats):
            st = self.optimizer.state.get(p) if self.optimizer is not None else None
            for key in ("exp_avg", "exp_avg_sq"):
                if st and key in st:
                    st[key].index_fill_(0, rows, 0.0)

    def set_lr_scale(self, factor: float) -> None:
        """Set every parameter group's learning rate to ``factor`` × its configured rate (``self.lr``).
        A rebuild of the optimiser by :meth:`set_map` restores the configured rates."""
        for group in self.optimizer.param_groups:
            group["lr"] = getattr(self.lr, group["name"]) * float(factor)

    def step(self, update: Optional[torch.Tensor] = None, reference: bool = False) -> None:
        """One Adam step, then clear gradients.

        Args:
            update: optional (N,) bool; rows outside it keep their values and Adam moments exactly
                (the ROI phase updates only active Gaussians: a zero gradient alone would still move
                them through Adam's momentum). The masked step runs Adam on the selected rows only
                (:meth:`_masked_adam`): the same update as a full step followed by restoring the other
                rows (:func:`masked_step_reference`, the parity test), at the cost of the selected rows.
            reference: take the masked step by :func:`masked_step_reference` (bench baseline).
        """
        assert self.optimizer is not None
        if update is not None and not bool(update.all()) and reference:
            masked_step_reference(self, update.to(self.device))
            return
        if update is not None and not bool(update.all()):
            self._masked_adam(torch.nonzero(update.to(self.device)).squeeze(1))
        else:
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def _masked_adam(self, rows: torch.Tensor, fused: bool = True) -> None:
        """Adam (as ``torch.optim.Adam``) on ``rows`` (K,) int64 of every parameter that has a gradient; the step
        count advances as in a full step (:meth:`Adam.step <gausslite.mapping.adam.Adam.step>`: a Warp launch per
        CPU float32 parameter, the torch ops of :func:`~gausslite.mapping.adam.adam_torch_` without ``fused``)."""
        self.optimizer.step(rows, fused=fused)


def quat_of_matrix(R: np.ndarray) -> torch.Tensor:
    """(4,) float64 unit quaternion (w, x, y, z) of a (3, 3) rotation matrix ``R`` (via its rotation vector,
    SciPy's ``Rotation``)."""
    # lazy: keeps gausslite.mapping.model importable without SciPy
    from scipy.spatial.transform import Rotation

    return quat_of_rotvec(torch.from_numpy(Rotation.from_matrix(np.asarray(R, np.float64)).as_rotvec()))


def masked_step_reference(model: GaussianModel, update: torch.Tensor) -> None:
    """Reference for :meth:`GaussianModel.step` with a mask: a full step on every row by torch ops
    (:func:`~gausslite.mapping.adam.adam_torch_`), then the rows outside ``update`` (and their Adam moments, zero
    before the first step) restored. Slow (copies every tensor twice); kept for the parity test."""
    opt = model.optimizer
    keep = ~update
    frozen = {}
    for name, p in model.params.items():
        st = opt.state.get(p) or {"exp_avg": torch.zeros_like(p), "exp_avg_sq": torch.zeros_like(p)}
        frozen[name] = (p.detach()[keep].clone(),
                        {k: v[keep].clone() for k, v in st.items() if torch.is_tensor(v) and v.dim() > 0})
    opt.step(fused=False)
    opt.zero_grad(set_to_none=True)
    with torch.no_grad():
        for name, (vals, st) in frozen.items():
            p = model.params[name]
            p[keep] = vals
            for k, v in st.items():
                opt.state[p][k][keep] = v
