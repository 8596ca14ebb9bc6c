"""The map's Adam (:class:`Adam`), and Adam on selected rows of a parameter in one Warp launch (CPU, float32): the
ROI phase's masked step.

:meth:`GaussianModel.step(update=...) <gausslite.mapping.model.GaussianModel.step>` updates only the rows of the
active Gaussians (paper Sec. III-D.1). In torch that step is about ten small ops per parameter tensor (gathers of
the gradient and both moments, the moment updates, scatters back, the update): about 50 launches of the torch
dispatcher per iteration, which cost more than the arithmetic at a few thousand rows. Here each parameter tensor
takes one kernel launch that updates its selected rows in place, with the update of ``torch.optim.Adam`` (Kingma &
Ba 2015; no weight decay, no amsgrad):

    m ← m + (1 − β₁)(g − m),  v ← β₂ v + (1 − β₂) g²,  p ← p − lr / (1 − β₁ᵗ) · m / (√v / √(1 − β₂ᵗ) + ε).

:func:`adam_torch_` is the torch reference; they agree to float32 rounding, and both with ``torch.optim.Adam``
(tests/mapping/test_model_step.py).

:class:`Adam` is the optimiser of :class:`~gausslite.mapping.model.GaussianModel` in place of ``torch.optim.Adam``:
the same update, the same state layout (``param_groups``, ``state[p]`` with ``step``, ``exp_avg``, ``exp_avg_sq``)
and, for a full step, the same fused kernel; a masked step is the Warp launch above. ``torch.optim``'s optimisers
are not used: the first one a process makes imports ``torch._dynamo``, about a second of every mapping process's
start (a robot's mission, each service of the simulation, every CLI call that maps).
"""

from __future__ import annotations

from typing import Optional

import torch
import warp as wp

from gausslite.render.launch import launch_cpu
from gausslite.render.warp_kernels import ensure_module_loaded

wp.set_module_options({"enable_backward": False})


@wp.kernel
def masked_adam_kernel(rows: wp.array(dtype=wp.int64), grad: wp.array2d(dtype=wp.float32), w1: float, b2: float,
                       w2: float, step_size: float, bias2_sqrt: float, eps: float, param: wp.array2d(dtype=wp.float32),
                       exp_avg: wp.array2d(dtype=wp.float32), exp_avg_sq: wp.array2d(dtype=wp.float32)):
    """Thread (i, j): Adam on element (rows[i], j), in place (module docstring). ``w1`` = 1 − β₁ and ``w2`` =
    1 − β₂ (formed in float64 by the caller, as torch does), ``step_size`` = lr / (1 − β₁ᵗ), ``bias2_sqrt`` =
    √(1 − β₂ᵗ)."""
    i, j = wp.tid()
    r = rows[i]
    g = grad[r, j]
    m = exp_avg[r, j]
    m = m + w1 * (g - m)
    v = exp_avg_sq[r, j] * b2 + w2 * (g * g)
    exp_avg[r, j] = m
    exp_avg_sq[r, j] = v
    param[r, j] = param[r, j] - step_size * (m / (wp.sqrt(v) / bias2_sqrt + eps))


def fused_available(p: torch.Tensor) -> bool:
    """Whether :func:`masked_adam_` takes parameter ``p``: a contiguous CPU float32 tensor."""
    return p.device.type == "cpu" and p.dtype == torch.float32 and p.is_contiguous()


def masked_adam_(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
                 rows: torch.Tensor, lr: float, b1: float, b2: float, eps: float, step: int) -> None:
    """Adam step ``step`` (1-based) on rows ``rows`` of ``param``, in place, with its moments ``exp_avg`` and
    ``exp_avg_sq`` (module docstring).

    Args:
        param, grad, exp_avg, exp_avg_sq: (N, ...) contiguous CPU float32 tensors of one shape (a 1-D one is
            updated as (N, 1)).
        rows: (K,) int64 distinct row indices in [0, N).
        lr, b1, b2, eps: Adam's learning rate and hyper-parameters; step: the step count after this step.
    Raises:
        ValueError: tensors of different shapes, or not contiguous CPU float32 ones.
    """
    ts = (param, grad, exp_avg, exp_avg_sq)
    if any(t.shape != param.shape for t in ts) or not all(fused_available(t) for t in ts):
        raise ValueError("masked_adam_ takes contiguous CPU float32 tensors of one shape")
    if rows.numel() == 0:
        return
    cols = param.numel() // len(param)  # rows are given, so the tensor has rows
    p2, g2, m2, v2 = (t.view(len(param), cols) for t in ts)
    ensure_module_loaded(__name__, "cpu")
    launch_cpu(masked_adam_kernel, (int(rows.numel()), cols),
               [rows.to(torch.int64).contiguous(), g2, 1.0 - float(b1), float(b2), 1.0 - float(b2),
                float(lr) / (1.0 - b1 ** step),
                (1.0 - b2 ** step) ** 0.5, float(eps), p2, m2, v2])


@torch.no_grad()
def adam_torch_(param: torch.Tensor, state: dict, rows: Optional[torch.Tensor], lr: float, b1: float, b2: float,
                eps: float, step: int) -> None:
    """:func:`masked_adam_`'s update by torch ops, on any device and dtype: step ``step`` (1-based, already counted
    in ``state``) of ``param`` (N, ...) in place, its gradient ``param.grad`` and its moments ``state["exp_avg"]`` /
    ``state["exp_avg_sq"]`` (tensors of its shape), on ``rows`` (K,) int64 distinct rows, or every row when None.
    The reference of the Warp kernel."""
    if rows is None:
        m = state["exp_avg"].lerp_(param.grad, 1.0 - b1)
        v = state["exp_avg_sq"].mul_(b2).addcmul_(param.grad, param.grad, value=1.0 - b2)
        param.addcdiv_(m, (v.sqrt() / ((1.0 - b2 ** step) ** 0.5)).add_(eps), value=-lr / (1.0 - b1 ** step))
        return
    g = param.grad.index_select(0, rows)
    m = state["exp_avg"].index_select(0, rows).lerp_(g, 1.0 - b1)
    v = state["exp_avg_sq"].index_select(0, rows).mul_(b2).addcmul_(g, g, value=1.0 - b2)
    state["exp_avg"].index_copy_(0, rows, m)
    state["exp_avg_sq"].index_copy_(0, rows, v)
    denom = (v.sqrt() / ((1.0 - b2 ** step) ** 0.5)).add_(eps)
    param.index_add_(0, rows, m / denom, alpha=-lr / (1.0 - b1 ** step))


class Adam:
    """Adam (Kingma & Ba 2015; no weight decay, no amsgrad) over parameter groups, with ``torch.optim.Adam``'s
    update and state layout (module docstring).

    Args:
        groups: ``[{"params": [tensor, ...], "lr": float, ...}]``; other keys (a group's ``name``) are kept.
        betas: (β₁, β₂); eps: ε (added to the bias-corrected √v).
    Attributes:
        param_groups: the groups, each with ``lr``, ``betas`` and ``eps``; a group's ``lr`` may be changed between
            steps (:meth:`GaussianModel.set_lr_scale <gausslite.mapping.model.GaussianModel.set_lr_scale>`).
        state: parameter → ``{"step": () float32 tensor, "exp_avg", "exp_avg_sq"}``, made at its first step.
    """

    def __init__(self, groups: list, betas: tuple = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.param_groups = [{**g, "params": list(g["params"]), "betas": tuple(betas), "eps": float(eps)}
                             for g in groups]
        self.state: dict = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Clear every parameter's gradient (None, or zeros when ``set_to_none`` is False)."""
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    if set_to_none:
                        p.grad = None
                    else:
                        p.grad.zero_()

    @torch.no_grad()
    def step(self, rows: Optional[torch.Tensor] = None, fused: bool = True) -> None:
        """One step of every parameter that has a gradient, on ``rows`` (K,) int64 distinct rows of each (every row
        when None); the step count advances as in a full step. Contiguous CPU float32 parameters take, with
        ``fused``, torch's fused Adam kernel on every row (``torch._fused_adam_``, the one ``torch.optim.Adam(
        fused=True)`` calls: vectorised, and the same rounding) or one Warp launch on selected rows
        (:func:`masked_adam_`); any other parameter, or ``fused`` False, :func:`adam_torch_`."""
        for group in self.param_groups:
            b1, b2 = group["betas"]
            lr, eps = float(group["lr"]), float(group["eps"])
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state.get(p)
                if not st:
                    st = self.state[p] = {"step": torch.zeros((), dtype=torch.float32),
                                          "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                          "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
                st["step"] += 1
                t = int(st["step"])
                if fused and all(fused_available(x) for x in (p, p.grad, st["exp_avg"], st["exp_avg_sq"])):
                    if rows is None:  # the kernel torch.optim.Adam(fused=True) calls; it reads the counted step
                        torch._fused_adam_([p.data], [p.grad], [st["exp_avg"]], [st["exp_avg_sq"]], [], [st["step"]],
                                           lr=lr, beta1=b1, beta2=b2, weight_decay=0.0, eps=eps, amsgrad=False,
                                           maximize=False)
                    else:
                        masked_adam_(p.data, p.grad, st["exp_avg"], st["exp_avg_sq"], rows, lr, b1, b2, eps, t)
                else:
                    adam_torch_(p, st, rows, lr, b1, b2, eps, t)


__all__ = ["Adam", "adam_torch_", "fused_available", "masked_adam_", "masked_adam_kernel"]
