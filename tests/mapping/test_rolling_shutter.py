"""Rolling shutter (gausslite.mapping.shutter; row bands rendered from the pose at their readout time)."""

import dataclasses

import numpy as np
import pytest
import torch

from gausslite.evaluation import score_view
from gausslite.mapping.blur import blur_samples, exposure_twist, motion_deltas
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.poses import pose_delta
from gausslite.mapping.shutter import readout_norm, row_time, shutter_bands
from tests._scenes import plane_frame

H, W = 40, 56
READOUT = 0.05  # seconds, first row to last


def rolling_shutter_frame(i: int, x: float, speed: float, t: float) -> "object":
    """Plane frame i of a camera at world x = ``x`` at its timestamp ``t``, sliding along x at ``speed`` m/s,
    taken with a rolling shutter: row v is the row of a global-shutter image taken at t + t(v)."""
    fr = plane_frame(i, x, H, W)
    rn = readout_norm(READOUT, fr.intrinsics.fy, H)
    rows = [plane_frame(i, x + speed * row_time(v + 0.5, fr.intrinsics.cy + 0.5, fr.intrinsics.fy, rn), H, W).rgb[v]
            for v in range(H)]
    return dataclasses.replace(fr, rgb=np.stack(rows), timestamp=t)


def test_row_times_are_those_of_the_scene_rows_in_crops_and_downscaled_views():
    rn = readout_norm(0.03, 500.0, 480)  # 30 ms over 480 rows
    assert row_time(240.0, 240.0, 500.0, rn) == 0.0
    assert row_time(480.0, 240.0, 500.0, rn) == pytest.approx(0.015)
    assert row_time(0.0, 240.0, 500.0, rn) == pytest.approx(-0.015)
    # a crop starting at row 100 (principal point 140) and the image at half size show the same rows
    assert row_time(50.0, 140.0, 500.0, rn) == pytest.approx(row_time(150.0, 240.0, 500.0, rn))
    assert row_time(75.0, 120.0, 250.0, rn) == pytest.approx(row_time(150.0, 240.0, 500.0, rn))


def test_bands_follow_the_motion_across_the_readout_and_cover_the_view():
    K = np.array([[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]])
    rn = readout_norm(0.02, 250.0, 240)
    assert shutter_bands(K, 320, 240, np.zeros(6), rn, 2.0, 6) == [(0, 240, 0.0)]
    # 1 rad/s yaw: 20 ms × 1 rad/s × 250 px = 5 px between the first and the last row → 3 bands of 2 px
    bands = shutter_bands(K, 320, 240, np.array([0.0, 1.0, 0, 0, 0, 0]), rn, 2.0, 6)
    assert [(a, b) for a, b, _ in bands] == [(0, 80), (80, 160), (160, 240)]
    times = [t for _, _, t in bands]
    assert times == sorted(times) and times[1] == pytest.approx(0.0) and times[0] == pytest.approx(-times[2])
    assert len(shutter_bands(K, 320, 240, np.array([0.0, 10.0, 0, 0, 0, 0]), rn, 2.0, 6)) == 6  # capped
    # a crop of the bottom half covers half the readout: fewer bands, later times
    Kc = K.copy()
    Kc[1, 2] -= 120
    crop = shutter_bands(Kc, 320, 120, np.array([0.0, 1.0, 0, 0, 0, 0]), rn, 2.0, 6)
    assert len(crop) == 2 and all(t > 0 for _, _, t in crop)


def _mapper(rs: float, one_pass: bool = True) -> Mapper:
    cfg = MapperConfig(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=40, backend="warp", seed=0,
                       sensor={"rolling_shutter_s": rs, "rs_px_per_band": 0.5, "rs_max_bands": 8},
                       performance={"bands_in_one_pass": one_pass})
    cfg.densify.enabled = False
    return Mapper(cfg)


@pytest.mark.parametrize("one_pass", [True, False])
def test_render_view_stacks_bands_rendered_from_their_readout_poses(one_pass):
    m = _mapper(READOUT, one_pass)
    slow = [rolling_shutter_frame(i, 0.005 * i, 0.05, i * 0.1) for i in range(3)]
    for fr in slow:
        m.map_frame(fr)
    assert m.sensor.rs_norm == pytest.approx(readout_norm(READOUT, 50.0, H))
    # a fast frame: 2 m/s sideways, measured from the previous sensor pose 0.1 s before
    m.sensor.blur[3] = exposure_twist(plane_frame(2, -0.19, H, W).c2w, 0.2, plane_frame(3, 0.01, H, W).c2w, 0.3,
                               m.cfg.sensor.blur_exposure_s)
    fr = plane_frame(3, 0.01, H, W)
    K = torch.from_numpy(fr.intrinsics.K).float()
    c2w = torch.from_numpy(fr.c2w)
    vel = m.sensor.blur[3] / m.cfg.sensor.blur_exposure_s
    bands = shutter_bands(fr.intrinsics.K, W, H, vel, m.sensor.rs_norm, 0.5, 8)
    assert len(bands) == 7  # 10 cm over the readout: 3.3 px at blur_length_px's 1.5 m reference, 0.5 px per band
    if one_pass:  # edges on the 16-row tiles: 40 rows hold three bands
        bands = shutter_bands(fr.intrinsics.K, W, H, vel, m.sensor.rs_norm, 0.5, 8, align=16)
        assert [(y0, y1) for y0, y1, _ in bands] == [(0, 16), (16, 32), (32, 40)]
    with torch.no_grad():
        parts: list = []
        got = m.sensor.render_view(c2w, K, W, H, 3, None, parts=parts)
        assert len(parts) == 1  # one image (no blur)
        if one_pass:  # in one render of three bands
            assert len(parts[0]) == 1 and parts[0][0].n_bands == 3
        else:  # in 7 renders
            assert len(parts[0]) == 7
        # equal to the full render's rows; rendered one by one, up to the projection's EWA Jacobian, which is
        # clamped to 1.3× the rendered field of view (Kerbl et al. 2023), here a band's: Gaussians just above or
        # below a band get a slightly different footprint in it (≤ 7e-3 of colour measured, on a few edge pixels)
        for y0, y1, t in bands:
            full = m.sensor.rasterize(c2w, K, W, H, None, view_delta=pose_delta(torch.as_tensor(t * vel)))
            tol = 1e-5 if one_pass else 2e-2
            torch.testing.assert_close(got.color[y0:y1], full.color[y0:y1], atol=tol, rtol=0)
            torch.testing.assert_close(got.depth[y0:y1], full.depth[y0:y1], atol=tol, rtol=0)
            assert float((got.color[y0:y1] - full.color[y0:y1]).abs().mean()) < 2e-4
        sharp = m.sensor.rasterize(c2w, K, W, H, None)
        assert (got.color - sharp.color).abs().max() > 0.1  # the bottom rows see the plane 5 mm further on
    state = m.state_dict()
    m2 = Mapper(m.cfg)
    m2.load_state_dict(state)
    assert m2.sensor.rs_norm == m.sensor.rs_norm
    torch.testing.assert_close(m2.render_frame(fr).color, m.render_frame(fr).color)


def test_a_map_rendered_with_the_rolling_shutter_matches_a_fast_frame_taken_with_one():
    """Map the plane from slow frames (no skew), then score a frame taken while the camera slid at
    2 m/s with a 50 ms readout (10 cm of motion from the first row to the last, 2.5 px at 2 m): rendered
    band by band at the rows' readout poses it matches the image far better than a global-shutter render."""
    m = _mapper(READOUT)
    for i in range(3):
        m.map_frame(rolling_shutter_frame(i, 0.005 * i, 0.05, i * 0.1))
    m.optimize(n_iters=120)
    fast = rolling_shutter_frame(3, 0.01, 2.0, 0.3)
    sharp = score_view(m.render_frame(fast), fast).psnr  # frame 3 was not mapped: frame 2's (slow) motion
    m.sensor.blur[3] = exposure_twist(plane_frame(2, -0.19, H, W).c2w, 0.2, fast.c2w, 0.3, m.cfg.sensor.blur_exposure_s)
    rs = score_view(m.render_frame(fast), fast).psnr
    assert rs > sharp + 2.0, (rs, sharp)


def test_density_statistics_count_a_banded_view_once_per_gaussian():
    """With zero motion the rolling-shutter mapper renders one image and its statistics equal the global
    shutter's; a banded view sums a Gaussian's gradient over the bands before the norm (one count each)."""
    frames = [rolling_shutter_frame(i, 0.0, 0.0, i * 0.1) for i in range(2)]
    a, b = _mapper(0.0), _mapper(READOUT)
    for m in (a, b):
        m.cfg.densify.enabled = True
        m.cfg.densify.every = 1000  # accumulate, never act
        for fr in frames:
            m.map_frame(fr)
    torch.testing.assert_close(a.strategy.grad_accum, b.strategy.grad_accum)
    torch.testing.assert_close(a.strategy.grad_count, b.strategy.grad_count)
    # one banded view: counts rise by at most one per Gaussian
    m = b
    m.strategy.reset_stats()
    m.sensor.blur[1] = np.array([0.0, 0.0, 0.0, 0.02, 0.0, 0.0])  # 2 m/s over 10 ms
    kf = m.keyframes.load(1, m.device)
    m.step(kf, active_phase=False)
    assert m.strategy.grad_count.max() == 1 and m.strategy.grad_count.sum() > 0


def test_central_motion_estimate_gives_each_frame_the_motion_around_it():
    """``motion_estimate: central``: once frame i+1 arrives, frame i's twist is the mean of its backward and
    forward estimates, and the first frame gets the forward one (it had none); ``backward`` keeps each
    frame's own."""
    frames = [dataclasses.replace(plane_frame(i, x, H, W), timestamp=0.1 * i) for i, x in enumerate((0.0, 0.01, 0.03))]
    got = {}
    for est in ("backward", "central"):
        cfg = MapperConfig(mode="uniform", seeding={"seeds_per_frame": 200}, iters_per_frame=1, warmup_iters=1,
                           backend="warp", seed=0, sensor={"rolling_shutter_s": READOUT, "motion_estimate": est})
        m = Mapper(cfg)
        for fr in frames:
            m.map_frame(fr)
        got[est] = m.sensor.blur
    tau = MapperConfig().sensor.blur_exposure_s
    fwd01, fwd12 = 0.1 * tau, 0.2 * tau  # 1 cm and 2 cm in 0.1 s, over the exposure τ
    np.testing.assert_allclose(got["backward"][0][3], 0.0)
    np.testing.assert_allclose(got["backward"][1][3], fwd01, rtol=1e-9)
    np.testing.assert_allclose(got["central"][0][3], fwd01, rtol=1e-9)
    np.testing.assert_allclose(got["central"][1][3], 0.5 * (fwd01 + fwd12), rtol=1e-9)
    np.testing.assert_allclose(got["central"][2][3], fwd12, rtol=1e-9)  # the newest frame: backward until the next


def test_blur_samples_and_bands_in_one_pass_equal_their_renders_averaged():
    """Motion blur and rolling shutter together, in one render: every blur sample's band rows equal the full render
    from that band's pose in that sample, and the view is the samples' mean; the density statistics get one group."""
    cfg = MapperConfig(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=20, backend="warp", seed=0,
                       sensor={"rolling_shutter_s": READOUT, "rs_px_per_band": 0.5, "rs_max_bands": 8,
                               "motion_blur": True, "blur_exposure_s": 0.05, "blur_px_per_sample": 1.0,
                               "blur_max_samples": 3})
    m = Mapper(cfg)
    for i in range(3):
        m.map_frame(rolling_shutter_frame(i, 0.005 * i, 0.05, i * 0.1))
    m.sensor.blur[3] = exposure_twist(plane_frame(2, -0.19, H, W).c2w, 0.2, plane_frame(3, 0.01, H, W).c2w, 0.3,
                                      m.cfg.sensor.blur_exposure_s)
    fr = plane_frame(3, 0.01, H, W)
    K = torch.from_numpy(fr.intrinsics.K).float()
    c2w = torch.from_numpy(fr.c2w)
    xi_b = m.sensor.blur[3]
    n_blur = blur_samples(xi_b, float(K[0, 0]), W, H, 1.0, 3)
    bands = shutter_bands(fr.intrinsics.K, W, H, xi_b / m.cfg.sensor.blur_exposure_s, m.sensor.rs_norm, 0.5, 8,
                          align=16)
    assert n_blur == 3 and len(bands) == 3
    with torch.no_grad():
        parts: list = []
        got = m.sensor.render_view(c2w, K, W, H, 3, None, parts=parts)
        assert len(parts) == 1 and len(parts[0]) == 1 and parts[0][0].n_bands == n_blur * len(bands)
        samples = []
        for k in range(n_blur):
            rows = []
            for y0, y1, t in bands:
                delta = motion_deltas(xi_b, n_blur, t / m.cfg.sensor.blur_exposure_s)[k]
                rows.append(m.sensor.rasterize(c2w, K, W, H, None, view_delta=delta).color[y0:y1])
            samples.append(torch.cat(rows))
    # the one-pass render and the per-band renders sum in different orders (float32), so a Gaussian whose alpha lies
    # at the 1/255 cut may be drawn in one and skipped in the other: a pixel may differ by less than that cut (seen:
    # 3 of 6,720 values by up to 1.5e-4 on one CPU, none on another); every other value agrees to rounding
    diff = (got.color - torch.stack(samples).mean(0)).abs()
    assert float(diff.max()) < 1.0 / 255 and float((diff > 1e-5).float().mean()) < 1e-3
    assert (samples[0] - samples[-1]).abs().max() > 0.05  # the samples see different pixels
