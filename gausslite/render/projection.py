"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (vectorised PyTorch).

The backward pass is left to autograd. The pure PyTorch reference backend (and the Warp backend
on CUDA) consume the output of :func:`project_gaussians`. The Warp backend on CPU uses its
per-Gaussian twin :class:`gausslite.render.autograd.ProjectWarp` (same formulas, culling and
radius rule, hand-written backward; evaluated in float64, so for float64 inputs it agrees with
this function to rounding, and for float32 inputs it is the more accurate of the two).

Sources: Kerbl et al. 2023, "3D Gaussian Splatting for Real-Time Radiance Field Rendering"
(``computeCov2D`` / ``preprocessCUDA`` in diff-gaussian-rasterization); Zwicker et al. 2001,
"EWA Volume Splatting" (local affine approximation of the perspective projection); gsplat
(Ye et al. 2024) for the screen-space clamp of the Jacobian and the 0.3 px^2 low-pass filter.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class Projection(NamedTuple):
    """Screen-space Gaussians produced by :func:`project_gaussians` (M = number of input rows).

    Attributes:
        means2d: (M, 2) pixel coordinates (u, v) of the projected centres; pixel centres sit at
            integer coordinates, ``u = fx * x / z + cx``. Differentiable. Culled rows hold finite
            placeholder values.
        conics: (M, 3) upper triangle (a, b, c) of the inverse 2D covariance in px^-2, i.e. the
            Mahalanobis form is ``a dx^2 + 2 b dx dy + c dy^2``. Differentiable.
        depths: (M,) camera-frame z of the centres in metres. Differentiable.
        radii: (M,) int32 screen-space radius in pixels, ``ceil(3 sqrt(lambda))`` with
            ``lambda = mid + sqrt(max(0.1, mid^2 - det))`` (>= the largest eigenvalue; the 0.1
            floor is Kerbl et al.'s); 0 = culled.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: (N, 4) quaternions (w, x, y, z), any float dtype; normalised here (a zero quaternion
            maps to a finite, non-rotation matrix rather than NaN).

    Returns:
        (N, 3, 3) rotation matrices of the same dtype.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e4,
    eps2d: float = 0.3,
) -> Projection:
    """Project 3D Gaussians into a pinhole camera (EWA splatting).

    Steps: world->camera transform; 3D covariance ``R S S^T R^T`` (R from the normalised
    quaternion, S = diag(exp(log_scales))); rotation into the camera frame; EWA Jacobian of the
    perspective map ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` with x/z, y/z clamped
    to 1.3x the field of view as in Kerbl et al. 2023; 2D covariance ``J W Sigma W^T J^T +
    eps2d I``; conic = its inverse; radius = ``ceil(3 sqrt(lambda))`` with
    ``lambda = mid + sqrt(max(0.1, mid^2 - det))``, ``mid = trace / 2`` (Kerbl et al. 2023).

    A row is culled (radius 0) when its depth is outside (near, far), the 2D covariance is not
    positive definite, any value is non-finite, or its bounding square
    ``[u - r, u + r] x [v - r, v + r]`` contains no pixel centre of the image
    (i.e. ``u + r < 0 or u - r > width - 1``, same for v).

    Args:
        means: (N, 3) centres in world coordinates (metres), float32 or float64.
        quats: (N, 4) rotations (w, x, y, z), unnormalised.
        log_scales: (N, 3) log of the per-axis standard deviations (metres).
        viewmat: (4, 4) world-to-camera transform (OpenCV axes: x right, y down, z forward),
            same dtype/device as ``means``.
        K: (3, 3) pinhole intrinsics in pixels, same dtype/device as ``means``.
        width, height: image size in pixels.
        near, far: depth clipping planes in metres.
        eps2d: low-pass filter variance in px^2 added to the 2D covariance diagonal.

    Returns:
        :class:`Projection` with per-row screen-space parameters (rows are not reordered).
    """
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    finite = torch.isfinite(p).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(log_scales).all(-1)
    valid = finite & (z > near) & (z < far)
    # Sanitise before dividing so that culled rows never produce inf/NaN (which would turn into
    # NaN gradients through torch.where).
    one = torch.ones_like(z)
    zs = torch.where(valid, z, one)
    xs = torch.where(valid, x, torch.zeros_like(x))
    ys = torch.where(valid, y, torch.zeros_like(y))
    ls = torch.where(valid[:, None], log_scales, torch.zeros_like(log_scales))
    qs = torch.where(valid[:, None], quats, torch.ones_like(quats))

    Rq = quat_to_rotmat(qs)
    M = R @ (Rq * torch.exp(ls)[:, None, :])  # camera-frame R_view R_q S, (N, 3, 3)
    cov_c = M @ M.transpose(-1, -2)

    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    rz = 1.0 / zs
    tx = zs * torch.minimum(torch.maximum(xs * rz, -lim_x_neg), lim_x_pos)
    ty = zs * torch.minimum(torch.maximum(ys * rz, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1
    ).reshape(-1, 2, 3)
    cov2 = J @ cov_c @ J.transpose(-1, -2)
    a = cov2[:, 0, 0] + eps2d
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + eps2d
    det = a * c - b * b
    valid = valid & (det > 0) & torch.isfinite(det)
    det_s = torch.where(valid, det, one)
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)

    u = fx * xs * rz + cx
    v = fy * ys * rz + cy
    means2d = torch.stack([u, v], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        r = torch.ceil(3.0 * torch.sqrt(torch.where(valid, lam, one)))
        inside = (u + r >= 0) & (u - r <= width - 1) & (v + r >= 0) & (v - r <= height - 1)
        keep = valid & inside & torch.isfinite(r) & torch.isfinite(means2d).all(-1)
        radii = torch.where(keep, r, torch.zeros_like(r)).to(torch.int32)
    return Projection(means2d=means2d, conics=conics, depths=zs, radii=radii)
