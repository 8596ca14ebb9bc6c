"""Native CPU tile binning: the count and scatter passes of :func:`gausslite.render.binning.bin_gaussians` as plain C++
loops (``wp.func_native``).

The same tile lists as the torch binning :func:`~gausslite.render.binning._bin_torch`, their reference
(tests/render/test_render_binning.py: identical lists and counts, float32 and float64, banded or not, one or more
stripes). A row's tile rectangle is ``floor((u -+ r) / ts)`` (and likewise in v) clamped to the grid, evaluated in the
input dtype, as the torch expression evaluates it.

Why: the Warp kernels these loops replaced indexed generic 2-D arrays through strides and evaluated in float64 with
conversions; on the mapper's keyframe case (18k visible rows, 38k tile entries, three row bands) their count pass took
0.55 ms and their scatter pass 0.83 ms of binning's 1.7 ms, these 0.32 and 0.46 ms (docs/realtime.md, "Mapping
throughput").
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

# the tile rectangle (tx0, tx1, ty0, ty1) of row i, clipped to its band's tile rows when banded
_RECT = r"""
#pragma clang fp contract(off)
const int* RAD = (const int*)radii;
const int* TR = (const int*)tile_rows;
// the tile of coordinate c (pixels, in the input dtype): floor(c / tile_size) clamped to 0 .. n - 1
auto cell = [&](auto c, const int n) -> int {
    using T = decltype(c);
    const T qt = c / (T)tile_size;
    T t = (T)__builtin_floor((double)qt);
    if (t < (T)0) t = (T)0;
    if (t > (T)(n - 1)) t = (T)(n - 1);
    return (int)t;
};
auto rect = [&](auto zero, const decltype(zero)* uv, const long i, int* q) {
    using T = decltype(zero);
    const T r = (T)RAD[i];
    const T u = uv[2 * i], v = uv[2 * i + 1];
    q[0] = cell(u - r, tiles_x); q[1] = cell(u + r, tiles_x);
    q[2] = cell(v - r, tiles_y); q[3] = cell(v + r, tiles_y);
    if (banded) {
        if (TR[2 * i] > q[2]) q[2] = TR[2 * i];
        if (TR[2 * i + 1] < q[3]) q[3] = TR[2 * i + 1];
    }
};
// the tiles s[0] .. s[1] (none when s[0] > s[1]) of tile row ty that row i is binned to: its rectangle's columns q[0]
// .. q[1], narrowed, when tight, to the columns that the ellipse a dx^2 + 2 b dx dy + c dy^2 <= t (conic (a, b, c),
// level t = levels[i]) reaches within the tile row's pixel rows, widened by a pixel on each side (a rectangle one tile
// wide keeps the tile rows that the ellipse reaches); t <= 0: no tile.
// foot(i, f) evaluates the row's terms once into f (a, b, t, det, ymax, dy of the rightmost point, u, v) and returns
// the mode (0: the rectangle, 1: the ellipse, 2: no tile); span(mode, zero, f, ...) narrows one tile row.
const auto* CON = (const void*)conics;
auto foot = [&](auto zero, const decltype(zero)* uv, const long i, decltype(zero)* f) -> int {
    using T = decltype(zero);
    if (!tight) return 0;
    const T* C = (const T*)CON;
    const T a = C[3 * i], b = C[3 * i + 1], c = C[3 * i + 2], t = ((const T*)levels)[i];
    const T det = a * c - b * b;
    if (!(a > (T)0) || !(c > (T)0) || !(det > (T)0) || !__builtin_isfinite(det) || !__builtin_isfinite(t)) return 0;
    if (!(t > (T)0)) return 2;
    f[0] = a; f[1] = b; f[2] = t; f[3] = det;
    f[4] = __builtin_sqrt(t * a / det);
    f[5] = -(b / c) * __builtin_sqrt(t * c / det);
    f[6] = uv[2 * i]; f[7] = uv[2 * i + 1];
    return 1;
};
auto span = [&](const int mode, auto zero, const decltype(zero)* f, const int* q, const int ty, int* s) {
    using T = decltype(zero);
    s[0] = q[0]; s[1] = q[1];
    if (mode == 0) return;
    if (mode == 2) { s[0] = 1; s[1] = 0; return; }
    const T ts = (T)tile_size, one = (T)1;
    const T a = f[0], b = f[1], t = f[2], det = f[3], ymax = f[4], dyr = f[5];
    const T dy0 = (T)ty * ts - f[7], dy1 = dy0 + (ts - one);
    if (dy0 > ymax + one || dy1 < -ymax - one) { s[0] = 1; s[1] = 0; return; }
    if (q[0] == q[1]) return;  // one column: nothing to narrow
    T lo = dy0 > -ymax ? dy0 : -ymax, hi = dy1 < ymax ? dy1 : ymax;
    if (lo > hi) { lo = dy0 > (T)0 ? ymax : -ymax; hi = lo; }
    const T dR = dyr < lo ? lo : (dyr > hi ? hi : dyr);
    const T dL = -dyr < lo ? lo : (-dyr > hi ? hi : -dyr);
    T wR = a * t - det * dR * dR, wL = a * t - det * dL * dL;
    if (!(wR > (T)0)) wR = (T)0;
    if (!(wL > (T)0)) wL = (T)0;
    const T xr = (__builtin_sqrt(wR) - b * dR) / a, xl = (-__builtin_sqrt(wL) - b * dL) / a;
    const int c0 = cell(f[6] + xl - one, tiles_x), c1 = cell(f[6] + xr + one, tiles_x);
    if (c0 > s[0]) s[0] = c0;
    if (c1 < s[1]) s[1] = c1;
};
"""

_COUNT = _RECT + r"""
float* K = (float*)keys;
int* R = (int*)rows;
int* TS = (int*)tile_start;
int* TE = (int*)tile_end;
int n = 0;
auto body = [&](auto zero, const decltype(zero)* uv, const decltype(zero)* dep) {
    for (long i = 0; i < m; ++i) {
        if (RAD[i] <= 0) continue;
        K[n] = (float)dep[i];
        R[n] = (int)i;
        ++n;
        int q[4], sp[2];
        rect(zero, uv, i, q);
        decltype(zero) f[8];
        const int mode = foot(zero, uv, i, f);
        for (int ty = q[2]; ty <= q[3]; ++ty) {
            span(mode, zero, f, q, ty, sp);
            for (int tx = sp[0]; tx <= sp[1]; ++tx) TE[ty * tiles_x + tx] += 1;
        }
    }
};
if (is64) body(0.0, (const double*)means2d, (const double*)depths);
else body(0.0f, (const float*)means2d, (const float*)depths);
((int*)n_rows)[0] = n;
int acc = 0;
for (int t = 0; t < tiles_x * tiles_y; ++t) { TS[t] = acc; acc += TE[t]; TE[t] = acc; }
"""

_SCATTER = _RECT + r"""
const int* R = (const int*)rows;
int* C = (int*)cursor;
int* G = (int*)gids;
auto body = [&](auto zero, const decltype(zero)* uv) {
    for (int k = 0; k < n; ++k) {
        const int i = R[k];
        int q[4], sp[2];
        rect(zero, uv, i, q);
        const int ty0 = q[2] + (stripe - q[2] % nstripes + nstripes) % nstripes;
        if (ty0 > q[3]) continue;
        decltype(zero) f[8];
        const int mode = foot(zero, uv, i, f);
        for (int ty = ty0; ty <= q[3]; ty += nstripes) {
            span(mode, zero, f, q, ty, sp);
            for (int tx = sp[0]; tx <= sp[1]; ++tx) {
                const int t = ty * tiles_x + tx;
                G[C[t]++] = i;
            }
        }
    }
};
if (is64) body(0.0, (const double*)means2d); else body(0.0f, (const float*)means2d);
"""


@wp.func_native(_COUNT)
def _count_native(means2d: wp.uint64, radii: wp.uint64, depths: wp.uint64, is64: int, m: int, tile_size: int,
                  tiles_x: int, tiles_y: int, tile_rows: wp.uint64, banded: int, conics: wp.uint64, levels: wp.uint64,
                  tight: int, keys: wp.uint64, rows: wp.uint64, n_rows: wp.uint64, tile_start: wp.uint64,
                  tile_end: wp.uint64): ...


@wp.func_native(_SCATTER)
def _scatter_native(means2d: wp.uint64, radii: wp.uint64, rows: wp.uint64, n: int, is64: int, tile_size: int,
                    tiles_x: int, tiles_y: int, tile_rows: wp.uint64, banded: int, conics: wp.uint64,
                    levels: wp.uint64, tight: int, stripe: int, nstripes: int, cursor: wp.uint64,
                    gids: wp.uint64): ...


@wp.kernel
def bin_count_native_kernel(means2d: wp.uint64, radii: wp.uint64, depths: wp.uint64, is64: int, m: int,
                            tile_size: int, tiles_x: int, tiles_y: int, tile_rows: wp.uint64, banded: int,
                            conics: wp.uint64, levels: wp.uint64, tight: int, keys: wp.uint64, rows: wp.uint64,
                            n_rows: wp.uint64, tile_start: wp.uint64, tile_end: wp.uint64):
    """Serial (dim=1). Lists the rows with radius > 0 in increasing order in ``rows[:n]`` with their float32 depth in
    ``keys[:n]`` (``n_rows[0] = n``), and turns their per-tile intersection counts into ``tile_start`` / ``tile_end``
    (exclusive / inclusive prefix sums, so the number of intersections is ``tile_end[-1]``). ``banded`` != 0: row
    ``i`` is binned only to the tile rows ``tile_rows[i, 0] .. tile_rows[i, 1]`` (a row band of the image rendered
    from its own pose, :func:`gausslite.render.rasterize_bands`). Pointers to C-contiguous arrays: ``means2d`` (m, 2)
    and ``depths`` (m,) float64 if ``is64`` else float32, ``radii`` (m,) int32, ``tile_rows`` (m, 2) int32 (read
    only when banded); when ``tight`` != 0, ``conics`` (m, 3) and ``levels`` (m,) in the dtype of ``means2d`` narrow
    each tile row to the columns the row's footprint ellipse reaches (:func:`gausslite.render.binning.bin_gaussians`);
    outputs ``keys`` (float32) and ``rows`` (int32) of at least the visible rows, ``n_rows`` (1,)
    int32, ``tile_start`` and ``tile_end`` (tiles,) int32, ``tile_end`` zero on entry."""
    _count_native(means2d, radii, depths, is64, m, tile_size, tiles_x, tiles_y, tile_rows, banded, conics, levels,
                  tight, keys, rows, n_rows, tile_start, tile_end)


@wp.kernel
def bin_scatter_native_kernel(means2d: wp.uint64, radii: wp.uint64, rows: wp.uint64, n: int, is64: int,
                              tile_size: int, tiles_x: int, tiles_y: int, tile_rows: wp.uint64, banded: int,
                              conics: wp.uint64, levels: wp.uint64, tight: int, stripe: int, nstripes: int,
                              cursor: wp.uint64, gids: wp.uint64):
    """Serial (dim=1): append the rows ``rows[:n]`` (visited in that order) to the list of each tile they cover, for
    the tile rows ``ty`` with ``ty % nstripes == stripe`` (one launch per stripe; stripes write disjoint tiles).
    Pointers: the arrays of :func:`bin_count_native_kernel`, ``cursor`` (tiles,) int32 (starts as a copy of
    ``tile_start``, ends equal to ``tile_end``) and ``gids`` (entries,) int32."""
    _scatter_native(means2d, radii, rows, n, is64, tile_size, tiles_x, tiles_y, tile_rows, banded, conics, levels,
                    tight, stripe, nstripes, cursor, gids)


__all__ = ["bin_count_native_kernel", "bin_scatter_native_kernel"]
