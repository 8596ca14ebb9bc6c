"""bench.detail_live compares two bench.realtime results, without and with the task region's own resolution."""

from __future__ import annotations

import pytest

import bench.detail_live as dl


def _result(gain, ci, uniform, gausslite, overrides=(), iters=(10.0, 12.0), size=(160, 120)):
    novel = {"gain": gain, "gain_ci": ci, "uniform": {"roi_psnr": uniform, "runs": 3},
             "gausslite": {"roi_psnr": gausslite, "runs": 3}}
    runs = [{"scene": "tum_fr1_rpy", "mode": "gausslite", "iters_per_keyframe": it, "roi_iters": 70, "keyframes": 10,
             "mission": {"mapping_size": list(size)}} for it in iters]
    return {"settings": {"overrides": list(overrides)}, "runs": runs,
            "scenes": {"tum_fr1_rpy": {"budgets": {"0.25": {"protocols": {"novel": novel}}}}}}


def test_the_detail_gain_is_the_difference_of_the_two_gains_with_both_intervals():
    off = _result(0.5, [0.0, 1.0], 20.0, 20.5)
    on = _result(1.5, [1.0, 2.0], 20.1, 21.6, ["mapper.detail.enabled=true"], iters=(8.0, 9.0))
    v = dl.compare(off, on)["tum_fr1_rpy"]
    assert v["on_minus_off"]["mean"] == pytest.approx(1.0)
    half = (0.5 ** 2 + 0.5 ** 2) ** 0.5
    assert v["on_minus_off"]["ci"] == pytest.approx([1.0 - half, 1.0 + half])
    assert v["on"]["gausslite"]["iters_per_keyframe"] == pytest.approx(8.5)
    assert v["on"]["gausslite"]["mapping_sizes"] == ["160×120"]
    row = dl.table({"b0.25": {"tum_fr1_rpy": v}}).splitlines()[-1]
    assert row.startswith("| b0.25 | tum_fr1_rpy | 20.00 / 20.10 | 20.50 / 21.60 |") and row.endswith("| +1.00 [+0.29, +1.71] |")


def test_a_second_result_without_the_detail_layer_is_refused():
    with pytest.raises(ValueError, match="detail.enabled"):
        dl.compare(_result(0.5, None, 20.0, 20.5), _result(1.5, None, 20.0, 21.5))
