"""Adam on selected rows of a parameter, in one Warp launch (CPU, float32): the ROI phase's masked step.

:meth:`GaussianModel.step(update=...) <gausslite.mapping.model.GaussianModel.step>` updates only the rows of the
active Gaussians (paper Sec. III-D.1). In torch that step is about ten small ops per parameter tensor (gathers of
the gradient and both moments, the moment updates, scatters back, the update): about 50 launches of the torch
dispatcher per iteration, which cost more than the arithmetic at a few thousand rows. Here each parameter tensor
takes one kernel launch that updates its selected rows in place, with the update of ``torch.optim.Adam`` (Kingma &
Ba 2015; no weight decay, no amsgrad):

    m ← m + (1 − β₁)(g − m),  v ← β₂ v + (1 − β₂) g²,  p ← p − lr / (1 − β₁ᵗ) · m / (√v / √(1 − β₂ᵗ) + ε).

:meth:`GaussianModel._masked_adam_torch <gausslite.mapping.model.GaussianModel._masked_adam_torch>` is the torch
reference; they agree to float32 rounding (tests/mapping/test_model_step.py).
"""

from __future__ import annotations

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


__all__ = ["fused_available", "masked_adam_", "masked_adam_kernel"]
