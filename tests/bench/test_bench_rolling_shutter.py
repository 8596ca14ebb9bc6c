"""The rolling-shutter calibration bench (bench.rolling_shutter): its warp PSNR and camera velocities on frames of a
known readout."""

import numpy as np

from bench.rolling_shutter import velocities, warp_psnr
from tests._scenes import plane_frame
from tests.mapping.test_rolling_shutter import READOUT, H, W, rolling_shutter_frame


def test_bench_warp_psnr_peaks_at_the_true_readout():
    """bench.rolling_shutter's calibration on frames with a known 50 ms readout: two views of the plane taken
    sliding left and right at 2 m/s warp into each other best with the true readout, worse with a global
    shutter, worst with the rows read bottom first; the velocities are the poses' central differences."""
    fi = rolling_shutter_frame(0, 0.0, 2.0, 0.0)
    fj = rolling_shutter_frame(1, 0.03, -2.0, 0.1)
    vi, vj = np.array([0, 0, 0, 2.0, 0, 0]), np.array([0, 0, 0, -2.0, 0, 0])
    true, cover = warp_psnr(fi, fj, vi, vj, READOUT)
    gs = warp_psnr(fi, fj, vi, vj, 0.0)[0]
    flipped = warp_psnr(fi, fj, vi, vj, READOUT, rows_top_first=False)[0]
    assert cover > 0.5
    assert true > gs + 3.0 and gs > flipped, (true, gs, flipped)
    frames = [plane_frame(i, 0.1 * i, H, W) for i in range(3)]  # 0.1 m per 1/30 s: 3 m/s along x
    v = velocities(frames)
    np.testing.assert_allclose(v[1], [0, 0, 0, 3.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(v[0], v[1], atol=1e-9)  # one-sided at the ends
