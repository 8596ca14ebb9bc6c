"""bench.map_tracking: its variants, its summary over seeds (paired differences to ``off``) and its table."""

import pytest

from bench.map_tracking import VARIANTS, mapper_config, parse_variant, summarise, table


def test_variants_parse_by_name_and_by_fields():
    assert parse_variant("off") == ("off", {})
    assert parse_variant("track40_w80") == ("track40_w80", {"track_iters": 40, "track_width": 80})
    assert parse_variant("fast=track_iters=10;track_width=80") == ("fast", {"track_iters": 10, "track_width": 80})
    with pytest.raises(ValueError):
        parse_variant("nope")
    with pytest.raises(ValueError):
        parse_variant("x=track_iters")
    cfg = mapper_config("gausslite", 2, VARIANTS["track20"], {"final_iters_per_keyframe": 0})
    assert cfg.pose.track_iters == 20 and cfg.pose.refine and cfg.seed == 2 and cfg.final_iters_per_keyframe == 0


def _run(variant, seed, roi, ate):
    return {"source": "odometry", "mode": "uniform", "variant": variant, "seed": seed, "roi_psnr": roi, "psnr": 20.0,
            "ate_final_cm": ate, "ate_placed_cm": ate, "ate_input_cm": 3.0, "track_iters_mean": 0.0,
            "track_trans_cm_mean": 0.0, "track_rot_deg_mean": 0.0}


def test_summary_pairs_each_seed_with_its_run_without_placement():
    runs = [_run("off", 0, 20.0, 3.0), _run("off", 1, 22.0, 3.2),
            _run("track40", 0, 21.0, 2.0), _run("track40", 1, 22.5, 2.4)]
    rows = {r["variant"]: r for r in summarise(runs)}
    assert rows["track40"]["roi_psnr"] == pytest.approx(21.75)
    assert rows["track40"]["roi_psnr_minus_off"] == pytest.approx(0.75)
    assert rows["track40"]["roi_psnr_minus_off_std"] == pytest.approx(0.25)
    assert rows["track40"]["ate_final_cm_minus_off"] == pytest.approx(-0.9)
    assert rows["off"]["roi_psnr_minus_off"] is None
    md = table(summarise(runs))
    assert "| odometry | uniform | track40 | 2 |" in md and "0.75 ± 0.25" in md
