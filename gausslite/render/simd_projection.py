"""SIMD CPU EWA projection: :func:`~gausslite.render.warp_kernels.project_fwd_kernel` and
:func:`~gausslite.render.warp_kernels.project_bwd_kernel` with eight Gaussians per call, in native C++
(``wp.func_native``) written with clang vector types.

Same formulas, culling, radius rule and gradient conventions as the Warp kernels (the conventions:
:mod:`gausslite.render.warp_kernels_common`, "EWA projection"), in float64 whatever the input dtype: the
eight Gaussians' rows are loaded into 8-lane double vectors (one AVX-512 register; two AVX2 ones), every
branch of the scalar kernels becomes a lane mask and a select, and the rows are written back lane by lane.
``exp`` of the log-scales is a vector Cephes ``exp`` (within 1–2 ulp of libm's); everything is vector arithmetic,
compiled with ``#pragma clang fp contract(fast)``, so products and sums fuse into FMAs: the results move from the Warp
kernels' at float64 rounding (the outputs are float32 or float64 rows; tests/render/test_render_projection.py
holds the parity test against the Warp kernels and the pure-PyTorch reference).

Why: the projection was about a tenth of a mapping iteration and a quarter of a pose-tracking iteration
(docs/realtime.md, "Mapping throughput"); the scalar Warp kernels took about 105 ns per Gaussian forward and
140 ns backward on one core.

Arguments are passed as raw pointers (``torch.Tensor.data_ptr()``) to C-contiguous rows of one dtype (float32
or float64, ``is64``): one kernel serves both, where a ``wp.func_native`` needs its array types fixed.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

#: Gaussians per kernel thread (the vector width)
LANES = 8

_HEAD = r"""
#pragma clang fp contract(fast)
typedef double vd __attribute__((ext_vector_type(8)));
typedef long vm __attribute__((ext_vector_type(8)));
const int n = end - start;
auto fin = [](const vd x) -> vm { return (x - x) == (vd)(0.0); };
auto vmax = [](const vd a, const vd b) -> vd { return __builtin_elementwise_max(a, b); };
auto vmin = [](const vd a, const vd b) -> vd { return __builtin_elementwise_min(a, b); };
// exp(x) of finite x: Cephes exp (x = n ln2 + r, |r| <= ln2 / 2, a (3, 3) Pade form of e^r, 2^n through the
// exponent bits), within 1-2 ulp of libm; overflow gives +inf, x below -708.39 gives 0 (no subnormals)
auto vexp = [](const vd x) -> vd {
    const vd n = __builtin_elementwise_floor(x * 1.4426950408889634073599 + 0.5);
    const vd r = (x - n * 6.93145751953125E-1) - n * 1.42860682030941723212E-6;
    const vd rr = r * r;
    const vd p = r * ((1.26177193074810590878E-4 * rr + 3.02994407707441961300E-2) * rr
                      + 9.99999999999999999910E-1);
    const vd q = ((3.00198505138664455042E-6 * rr + 2.52448340349684104192E-3) * rr
                  + 2.27265548208155028766E-1) * rr + 2.00000000000000000009E0;
    const vd e = 1.0 + 2.0 * (p / (q - p));
    const vd nc = __builtin_elementwise_min(__builtin_elementwise_max(n, (vd)(-1022.0)), (vd)(1023.0));
    const vd scale = __builtin_bit_cast(vd, (__builtin_convertvector(nc, vm) + 1023) << 52);
    const vd y = e * scale;
    return x > 709.782712893384 ? (vd)(__builtin_inf()) : (x < -708.3964185322641 ? (vd)(0.0) : y);
};
auto body = [&](auto tag) {
using T = decltype(tag);
// the rows of Gaussians start .. end - 1; lanes past the end repeat the first row (computed, never written)
auto ld = [&](const unsigned long long ptr, const int cols, const int c) -> vd {
    const T* p = (const T*)ptr;
    vd v;
    if (n == 8) {
        for (int l = 0; l < 8; ++l) v[l] = (double)p[(long)(start + l) * cols + c];
    } else {
        for (int l = 0; l < 8; ++l) v[l] = (double)p[(long)(start + (l < n ? l : 0)) * cols + c];
    }
    return v;
};
const vd mx = ld(means, 3, 0), my = ld(means, 3, 1), mz = ld(means, 3, 2);
vd qw = ld(quats, 4, 0), qx = ld(quats, 4, 1), qy = ld(quats, 4, 2), qz = ld(quats, 4, 3);
vd l0 = ld(log_scales, 3, 0), l1 = ld(log_scales, 3, 1), l2 = ld(log_scales, 3, 2);
// each row's camera (its row of the camera table: rot (9, row-major), trans (3), fx, fy, cx, cy, the clamp
// limits of x/z and y/z (4))
const double* cam = (const double*)cams;
const int* crow = (const int*)cam_of_row;
int ci[8];
for (int l = 0; l < 8; ++l) ci[l] = crow ? crow[start + (l < n ? l : 0)] : 0;
auto ldc = [&](const int k) -> vd {
    vd v;
    for (int l = 0; l < 8; ++l) v[l] = cam[20 * ci[l] + k];
    return v;
};
const vd r00 = ldc(0), r01 = ldc(1), r02 = ldc(2), r10 = ldc(3), r11 = ldc(4), r12 = ldc(5);
const vd r20 = ldc(6), r21 = ldc(7), r22 = ldc(8), t0 = ldc(9), t1 = ldc(10), t2 = ldc(11);
const vd fx = ldc(12), fy = ldc(13), cx = ldc(14), cy = ldc(15);
const vd lim0 = ldc(16), lim1 = ldc(17), lim2 = ldc(18), lim3 = ldc(19);
// camera-frame centre rot @ mean + trans
const vd px = r00 * mx + r01 * my + r02 * mz + t0;
const vd py = r10 * mx + r11 * my + r12 * mz + t1;
const vd pz = r20 * mx + r21 * my + r22 * mz + t2;
const vm finite = fin(px) & fin(py) & fin(pz) & fin(qw) & fin(qx) & fin(qy) & fin(qz) & fin(l0) & fin(l1)
                  & fin(l2);
vm valid = finite & (pz > near) & (pz < far);
const vd xs = valid ? px : (vd)(0.0), ys = valid ? py : (vd)(0.0), zs = valid ? pz : (vd)(1.0);
qw = valid ? qw : (vd)(1.0); qx = valid ? qx : (vd)(1.0); qy = valid ? qy : (vd)(1.0); qz = valid ? qz : (vd)(1.0);
l0 = valid ? l0 : (vd)(0.0); l1 = valid ? l1 : (vd)(0.0); l2 = valid ? l2 : (vd)(0.0);
// unit quaternion, its rotation Rq, the scales and M = rot Rq diag(s), cov = M M^T
const vd qlen = __builtin_elementwise_sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
const vd qden = vmax(qlen, (vd)(1e-12));
const vd iq = 1.0 / qden;
const vd w = qw * iq, x = qx * iq, y = qy * iq, z = qz * iq;
const vd R00 = 1.0 - 2.0 * (y * y + z * z), R01 = 2.0 * (x * y - w * z), R02 = 2.0 * (x * z + w * y);
const vd R10 = 2.0 * (x * y + w * z), R11 = 1.0 - 2.0 * (x * x + z * z), R12 = 2.0 * (y * z - w * x);
const vd R20 = 2.0 * (x * z - w * y), R21 = 2.0 * (y * z + w * x), R22 = 1.0 - 2.0 * (x * x + y * y);
const vd s0 = vexp(l0), s1 = vexp(l1), s2 = vexp(l2);
const vd N00 = R00 * s0, N01 = R01 * s1, N02 = R02 * s2;
const vd N10 = R10 * s0, N11 = R11 * s1, N12 = R12 * s2;
const vd N20 = R20 * s0, N21 = R21 * s1, N22 = R22 * s2;
const vd M00 = r00 * N00 + r01 * N10 + r02 * N20, M01 = r00 * N01 + r01 * N11 + r02 * N21,
         M02 = r00 * N02 + r01 * N12 + r02 * N22;
const vd M10 = r10 * N00 + r11 * N10 + r12 * N20, M11 = r10 * N01 + r11 * N11 + r12 * N21,
         M12 = r10 * N02 + r11 * N12 + r12 * N22;
const vd M20 = r20 * N00 + r21 * N10 + r22 * N20, M21 = r20 * N01 + r21 * N11 + r22 * N21,
         M22 = r20 * N02 + r21 * N12 + r22 * N22;
const vd C00 = M00 * M00 + M01 * M01 + M02 * M02, C01 = M00 * M10 + M01 * M11 + M02 * M12,
         C02 = M00 * M20 + M01 * M21 + M02 * M22;
const vd C11 = M10 * M10 + M11 * M11 + M12 * M12, C12 = M10 * M20 + M11 * M21 + M12 * M22;
const vd C22 = M20 * M20 + M21 * M21 + M22 * M22;
// the EWA Jacobian at the clamped x/z, y/z (limits: the image widened by 30 % of the half field of view)
const double wf = (double)width, hf = (double)height;
const vd rz = 1.0 / zs;
const vd xr = xs * rz, yr = ys * rz;
const vd txc = vmin(vmax(xr, -lim1), lim0), tyc = vmin(vmax(yr, -lim3), lim2);
const vd tx = zs * txc, ty = zs * tyc;
const vd j00 = fx * rz, j02 = -fx * tx * rz * rz, j11 = fy * rz, j12 = -fy * ty * rz * rz;
// w0 = cov j0, w1 = cov j1, and the low-passed screen covariance (a, b, c)
const vd w00 = C00 * j00 + C02 * j02, w01 = C01 * j00 + C12 * j02, w02 = C02 * j00 + C22 * j02;
const vd w10 = C01 * j11 + C02 * j12, w11 = C11 * j11 + C12 * j12, w12 = C12 * j11 + C22 * j12;
const vd a = j00 * w00 + j02 * w02 + eps2d, b = j11 * w01 + j12 * w02, c = j11 * w11 + j12 * w12 + eps2d;
const vd det = a * c - b * b;
const vm pd = (det > 0.0) & fin(det);
"""

_FWD = _HEAD + r"""
valid = valid & pd;
const vd det_s = valid ? det : (vd)(1.0);
const vd u = fx * xs * rz + cx, v = fy * ys * rz + cy;
const vd mid = 0.5 * (a + c);
const vd lam = valid ? mid + __builtin_elementwise_sqrt(vmax(mid * mid - det, (vd)(0.1))) : (vd)(1.0);
const vd r = __builtin_elementwise_ceil(3.0 * __builtin_elementwise_sqrt(lam));
const vm inside = (u + r >= 0.0) & (u - r <= wf - 1.0) & (v + r >= 0.0) & (v - r <= hf - 1.0);
const vm keep = valid & inside & fin(r) & fin(u) & fin(v);
const vd id = 1.0 / det_s;
const vd ca = c * id, cb = -b * id, cc = a * id;
T* o2 = (T*)means2d;
T* oc = (T*)conics;
T* od = (T*)depths;
int* orad = (int*)radii;
for (int l = 0; l < n; ++l) {
    const long i = start + l;
    o2[2 * i] = (T)u[l]; o2[2 * i + 1] = (T)v[l];
    oc[3 * i] = (T)ca[l]; oc[3 * i + 1] = (T)cb[l]; oc[3 * i + 2] = (T)cc[l];
    od[i] = (T)zs[l];
    orad[i] = keep[l] ? (int)(r[l] < 1073741824.0 ? r[l] : 1073741824.0) : 0;
}
};
if (is64) body(0.0); else body(0.0f);
"""

_BWD = _HEAD + r"""
// the conic (c, -b, a) / det: its gradient w.r.t. (a, b, c); (c, -b, a) where the covariance is not positive definite
const vd gA = ld(g_conics, 3, 0), gB = ld(g_conics, 3, 1), gC = ld(g_conics, 3, 2);
const vd idet = 1.0 / det;
const vd gdet = -(gA * c - gB * b + gC * a) * idet * idet;
const vd ga = pd ? gC * idet + gdet * c : gC;
const vd gc = pd ? gA * idet + gdet * a : gA;
const vd gb = pd ? -gB * idet - 2.0 * gdet * b : -gB;
// cov2 = J cov J^T with the symmetric upstream gradient [[ga, gb/2], [gb/2, gc]]
const vd gj00 = 2.0 * ga * w00 + gb * w10, gj01 = 2.0 * ga * w01 + gb * w11, gj02 = 2.0 * ga * w02 + gb * w12;
const vd gj10 = gb * w00 + 2.0 * gc * w10, gj11 = gb * w01 + 2.0 * gc * w11, gj12 = gb * w02 + 2.0 * gc * w12;
// gcov = ga j0 j0^T + gb/2 (j0 j1^T + j1 j0^T) + gc j1 j1^T, j0 = (j00, 0, j02), j1 = (0, j11, j12)
const vd hb = 0.5 * gb;
const vd G00 = ga * j00 * j00, G01 = hb * j00 * j11, G02 = ga * j00 * j02 + hb * j00 * j12;
const vd G11 = gc * j11 * j11, G12 = hb * j02 * j11 + gc * j11 * j12;
const vd G22 = ga * j02 * j02 + hb * (j02 * j12 + j12 * j02) + gc * j12 * j12;
// gmm = 2 gcov M, gn = rot^T gmm (the gradient of N = Rq diag(s))
const vd H00 = 2.0 * (G00 * M00 + G01 * M10 + G02 * M20), H01 = 2.0 * (G00 * M01 + G01 * M11 + G02 * M21),
         H02 = 2.0 * (G00 * M02 + G01 * M12 + G02 * M22);
const vd H10 = 2.0 * (G01 * M00 + G11 * M10 + G12 * M20), H11 = 2.0 * (G01 * M01 + G11 * M11 + G12 * M21),
         H12 = 2.0 * (G01 * M02 + G11 * M12 + G12 * M22);
const vd H20 = 2.0 * (G02 * M00 + G12 * M10 + G22 * M20), H21 = 2.0 * (G02 * M01 + G12 * M11 + G22 * M21),
         H22 = 2.0 * (G02 * M02 + G12 * M12 + G22 * M22);
const vd n00 = r00 * H00 + r10 * H10 + r20 * H20, n01 = r00 * H01 + r10 * H11 + r20 * H21,
         n02 = r00 * H02 + r10 * H12 + r20 * H22;
const vd n10 = r01 * H00 + r11 * H10 + r21 * H20, n11 = r01 * H01 + r11 * H11 + r21 * H21,
         n12 = r01 * H02 + r11 * H12 + r21 * H22;
const vd n20 = r02 * H00 + r12 * H10 + r22 * H20, n21 = r02 * H01 + r12 * H11 + r22 * H21,
         n22 = r02 * H02 + r12 * H12 + r22 * H22;
const vd gl0 = (n00 * R00 + n10 * R10 + n20 * R20) * s0;
const vd gl1 = (n01 * R01 + n11 * R11 + n21 * R21) * s1;
const vd gl2 = (n02 * R02 + n12 * R12 + n22 * R22) * s2;
// grq = gn diag(s); the gradient w.r.t. the unit quaternion, then the raw one
const vd g00 = n00 * s0, g01 = n01 * s1, g02 = n02 * s2;
const vd g10 = n10 * s0, g11 = n11 * s1, g12 = n12 * s2;
const vd g20 = n20 * s0, g21 = n21 * s1, g22 = n22 * s2;
const vd gw = 2.0 * (-z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21);
const vd gx = 2.0 * (y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22);
const vd gy = 2.0 * (-2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22);
const vd gz = 2.0 * (-2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21);
const vm unit = qlen >= 1e-12;
const vd qd = w * gw + x * gx + y * gy + z * gz;
const vd gqw = (unit ? gw - w * qd : gw) * iq, gqx = (unit ? gx - x * qd : gx) * iq;
const vd gqy = (unit ? gy - y * qd : gy) * iq, gqz = (unit ? gz - z * qd : gz) * iq;
// the mean: through the Jacobian, the pixel centre and the depth, with the clamp's tie rule (1/2 on equality)
auto clampf = [](const vd t, const vd lo, const vd hi) -> vd {
    vd f = t < lo ? (vd)(0.0) : (t == lo ? (vd)(0.5) : (vd)(1.0));
    const vd m = t > lo ? t : lo;
    return m > hi ? (vd)(0.0) : (m == hi ? f * 0.5 : f);
};
const vd gu = ld(g_means2d, 2, 0), gv = ld(g_means2d, 2, 1), gdepth = ld(g_depths, 1, 0);
vd grz = fx * gj00 + fy * gj11 - 2.0 * fx * tx * rz * gj02 - 2.0 * fy * ty * rz * gj12;
const vd gtx = -fx * rz * rz * gj02, gty = -fy * rz * rz * gj12;
vd gxs = gu * fx * rz, gys = gv * fy * rz;
grz += gu * fx * xs + gv * fy * ys;
vd gzs = gdepth + gtx * txc + gty * tyc;
const vd gxr = gtx * zs * clampf(xr, -lim1, lim0), gyr = gty * zs * clampf(yr, -lim3, lim2);
gxs += gxr * rz;
gys += gyr * rz;
grz += gxr * xs + gyr * ys;
gzs += -grz * rz * rz;
const vd gm0 = r00 * gxs + r10 * gys + r20 * gzs, gm1 = r01 * gxs + r11 * gys + r21 * gzs,
         gm2 = r02 * gxs + r12 * gys + r22 * gzs;
T* om = (T*)g_means;
T* oq = (T*)g_quats;
T* ol = (T*)g_log_scales;
for (int l = 0; l < n; ++l) {
    const long i = start + l;
    const bool ok = valid[l] != 0;
    om[3 * i] = ok ? (T)gm0[l] : (T)0; om[3 * i + 1] = ok ? (T)gm1[l] : (T)0; om[3 * i + 2] = ok ? (T)gm2[l] : (T)0;
    ol[3 * i] = ok ? (T)gl0[l] : (T)0; ol[3 * i + 1] = ok ? (T)gl1[l] : (T)0; ol[3 * i + 2] = ok ? (T)gl2[l] : (T)0;
    oq[4 * i] = ok ? (T)gqw[l] : (T)0; oq[4 * i + 1] = ok ? (T)gqx[l] : (T)0;
    oq[4 * i + 2] = ok ? (T)gqy[l] : (T)0; oq[4 * i + 3] = ok ? (T)gqz[l] : (T)0;
}
};
if (is64) body(0.0); else body(0.0f);
"""


@wp.func_native(_FWD)
def _project_fwd_native(means: wp.uint64, quats: wp.uint64, log_scales: wp.uint64, is64: int,
                        cams: wp.uint64, cam_of_row: wp.uint64, width: int, height: int, near: wp.float64,
                        far: wp.float64, eps2d: wp.float64, start: int, end: int, means2d: wp.uint64, conics: wp.uint64,
                        depths: wp.uint64, radii: wp.uint64): ...


@wp.func_native(_BWD)
def _project_bwd_native(means: wp.uint64, quats: wp.uint64, log_scales: wp.uint64, is64: int,
                        cams: wp.uint64, cam_of_row: wp.uint64, width: int, height: int, near: wp.float64,
                        far: wp.float64, eps2d: wp.float64, start: int, end: int, g_means2d: wp.uint64,
                        g_conics: wp.uint64, g_depths: wp.uint64, g_means: wp.uint64, g_quats: wp.uint64,
                        g_log_scales: wp.uint64): ...


@wp.kernel
def project_fwd_simd_kernel(
    means: wp.uint64,
    quats: wp.uint64,
    log_scales: wp.uint64,
    is64: int,
    cams: wp.uint64,
    cam_of_row: wp.uint64,
    width: int,
    height: int,
    near: wp.float64,
    far: wp.float64,
    eps2d: wp.float64,
    offset: int,
    end: int,
    means2d: wp.uint64,
    conics: wp.uint64,
    depths: wp.uint64,
    radii: wp.uint64,
):
    """EWA projection of Gaussians ``offset + LANES·tid`` … (at most ``end`` − 1): the inputs and outputs of
    :func:`gausslite.render.warp_kernels.project_fwd_kernel` as pointers to C-contiguous rows, float64 if
    ``is64`` else float32 (``radii`` int32), each row seen by its own camera: ``cams`` points to (B, 20) float64
    rows (:func:`camera_table`), ``cam_of_row`` to the (N,) int32 camera of every row, or is 0 (camera 0 for all)."""
    s = offset + wp.tid() * LANES
    _project_fwd_native(means, quats, log_scales, is64, cams, cam_of_row, width, height, near, far, eps2d, s,
                        wp.min(s + LANES, end), means2d, conics, depths, radii)


@wp.kernel
def project_bwd_simd_kernel(
    means: wp.uint64,
    quats: wp.uint64,
    log_scales: wp.uint64,
    is64: int,
    cams: wp.uint64,
    cam_of_row: wp.uint64,
    width: int,
    height: int,
    near: wp.float64,
    far: wp.float64,
    eps2d: wp.float64,
    offset: int,
    end: int,
    g_means2d: wp.uint64,
    g_conics: wp.uint64,
    g_depths: wp.uint64,
    g_means: wp.uint64,
    g_quats: wp.uint64,
    g_log_scales: wp.uint64,
):
    """Gradients of :func:`project_fwd_simd_kernel`'s outputs w.r.t. means, quats and log-scales of Gaussians
    ``offset + LANES·tid`` … (at most ``end`` − 1): :func:`gausslite.render.warp_kernels.project_bwd_kernel`'s
    arguments as pointers to C-contiguous rows of one dtype (``is64``), the cameras as in
    :func:`project_fwd_simd_kernel`."""
    s = offset + wp.tid() * LANES
    _project_bwd_native(means, quats, log_scales, is64, cams, cam_of_row, width, height, near, far, eps2d, s,
                        wp.min(s + LANES, end), g_means2d, g_conics, g_depths, g_means, g_quats, g_log_scales)


def camera_table(viewmats, Ks, width: int, height: int):
    """The (B, 20) float64 camera rows the SIMD kernels read: per camera the world-to-camera rotation (9,
    row-major) and translation (3, metres), ``fx, fy, cx, cy`` (pixels) and the clamp limits of x/z and y/z of
    the EWA Jacobian (the image widened by 30 % of the half field of view, as
    :func:`~gausslite.render.warp_kernels_common.screen_cov` computes them).

    Args:
        viewmats: B (4, 4) world-to-camera matrices (OpenCV axes; tensors or arrays). Ks: B (3, 3) intrinsics
            (pixels). width, height: the image size (pixels) every camera projects to.
    Returns:
        (B, 20) float64 CPU tensor, C-contiguous.
    """
    import numpy as np
    import torch

    B = len(viewmats)
    vm = np.stack([np.asarray(v.detach().cpu() if isinstance(v, torch.Tensor) else v, np.float64) for v in viewmats])
    K = np.stack([np.asarray(k.detach().cpu() if isinstance(k, torch.Tensor) else k, np.float64) for k in Ks])
    out = np.empty((B, 20), np.float64)
    out[:, 0:9] = vm[:, :3, :3].reshape(B, 9)
    out[:, 9:12] = vm[:, :3, 3]
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    w, h = float(width), float(height)
    tfx, tfy = 0.5 * w / fx, 0.5 * h / fy
    out[:, 12], out[:, 13], out[:, 14], out[:, 15] = fx, fy, cx, cy
    out[:, 16], out[:, 17] = (w - cx) / fx + 0.3 * tfx, cx / fx + 0.3 * tfx
    out[:, 18], out[:, 19] = (h - cy) / fy + 0.3 * tfy, cy / fy + 0.3 * tfy
    return torch.from_numpy(out)


__all__ = ["LANES", "camera_table", "project_bwd_simd_kernel", "project_fwd_simd_kernel"]
