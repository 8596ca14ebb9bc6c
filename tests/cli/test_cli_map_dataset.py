"""``gausslite map``/``ablate`` dataset flags: TUM undistortion and pose interpolation."""

import argparse

import numpy as np
import pytest

from gausslite.cli.cmd_map import add_mapping_args, resolve_dataset
from gausslite.datasets.tum import TUMDataset


def _args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_mapping_args(p)
    return p.parse_args(list(argv))


def test_tum_flags_reach_the_loader(tum_rpy_dir, tmp_path, capsys):
    plain = resolve_dataset(_args("--dataset", str(tum_rpy_dir), "--max-frames", "2", "--downscale", "2",
                                  "--no-undistort", "--no-interpolate-poses"), tmp_path)
    args = _args("--dataset", str(tum_rpy_dir), "--max-frames", "2", "--downscale", "2")
    ds = resolve_dataset(args, tmp_path)  # the hand-held profile: both on by default
    assert "profile: handheld" in capsys.readouterr().out
    assert args.profile.name == "handheld"
    assert isinstance(ds, TUMDataset) and ds.undistort and not plain.undistort
    explicit = resolve_dataset(_args("--dataset", str(tum_rpy_dir), "--max-frames", "2", "--downscale", "2",
                                     "--undistort", "--interpolate-poses"), tmp_path)
    assert explicit.undistort and np.array_equal(explicit.poses, ds.poses)
    # the undistorted camera is the alpha=0 optimal pinhole: zoomed in, every pixel has a source
    assert ds.intrinsics.fx > plain.intrinsics.fx
    f = ds[0]
    assert f.rgb.shape == plain[0].rgb.shape
    assert (f.rgb.reshape(-1, 3).max(axis=1) > 0).mean() > 0.999
    # interpolated poses differ from the nearest groundtruth sample, but by well under a centimetre
    d = np.abs(ds.poses[:, :3, 3] - plain.poses[:, :3, 3]).max()
    assert 0 < d < 0.01


def test_tum_flags_rejected_for_other_layouts(room0_dir, tmp_path):
    with pytest.raises(ValueError, match="TUM sequences only"):
        resolve_dataset(_args("--dataset", str(room0_dir), "--max-frames", "1", "--undistort"), tmp_path)


def test_profile_defaults_sit_below_config_and_set(tum_rpy_dir, room0_dir, tmp_path):
    from gausslite.cli.cmd_map import config_from_args

    args = _args("--dataset", str(tum_rpy_dir), "--max-frames", "1")
    resolve_dataset(args, tmp_path)
    assert config_from_args(args).final_iters_per_keyframe == 20.0  # hand-held profile
    args = _args("--dataset", str(tum_rpy_dir), "--max-frames", "1", "--set", "final_iters_per_keyframe=0")
    resolve_dataset(args, tmp_path)
    assert config_from_args(args).final_iters_per_keyframe == 0.0  # --set wins
    args = _args("--dataset", str(room0_dir), "--max-frames", "1")
    resolve_dataset(args, tmp_path)
    assert args.profile.name == "rendered" and config_from_args(args).final_iters_per_keyframe == 5.0  # short pass
    args = _args("--dataset", str(room0_dir), "--max-frames", "1", "--set", "final_iters_per_keyframe=0")
    resolve_dataset(args, tmp_path)
    assert config_from_args(args).final_iters_per_keyframe == 0.0  # opt out


def test_handheld_profile_refines_poses_from_the_sensor_pose(tum_rpy_dir, room0_dir, tmp_path):
    """Hand-held data maps with pose refinement started from the sensor's pose (TUM fr1/rpy: +1.4 dB over
    3 seeds, docs/results.md "Pose refinement"); rendered data keeps exact poses; ``--set`` still wins."""
    from gausslite.cli.cmd_map import config_from_args

    args = _args("--dataset", str(tum_rpy_dir), "--max-frames", "1")
    resolve_dataset(args, tmp_path)
    cfg = config_from_args(args)
    assert cfg.pose.refine is True and cfg.pose.init == "identity" and cfg.sensor.exposure_comp is True
    args = _args("--dataset", str(tum_rpy_dir), "--max-frames", "1", "--set", "pose.refine=false")
    resolve_dataset(args, tmp_path)
    assert config_from_args(args).pose.refine is False and config_from_args(args).sensor.exposure_comp is True
    args = _args("--dataset", str(room0_dir), "--max-frames", "1")
    resolve_dataset(args, tmp_path)
    assert config_from_args(args).pose.refine is False and config_from_args(args).sensor.exposure_comp is False
    assert config_from_args(args).sensor.motion_blur is False  # rendered data: no blur model
    assert config_from_args(args).sensor.rolling_shutter_s == 0.0  # nor a rolling shutter


def test_with_profile_fills_only_the_fields_the_config_left_unset():
    from gausslite.config import load_mapper_config
    from gausslite.mapping.config import MapperConfig
    from gausslite.mapping.profiles import HANDHELD, RENDERED, with_profile

    cfg = load_mapper_config(None, ["iters_per_frame=17"], mode="gausslite")
    out = with_profile(cfg, HANDHELD)
    assert out.pose.refine is True and out.final_iters_per_keyframe == 20.0 and out.lambda_depth == 0.3
    assert out.sensor.exposure_comp is True and out.sensor.motion_blur is True and out.sensor.rolling_shutter_s == 0.02
    assert out.iters_per_frame == 17 and out.mode == "gausslite"  # what the config set survives
    rendered = with_profile(cfg, RENDERED)
    assert rendered.final_iters_per_keyframe == 5.0 and rendered.pose.refine is False  # a short final pass only
    assert rendered.iters_per_frame == 17 and rendered.mode == "gausslite"
    explicit = load_mapper_config(None, ["pose.refine=false", "final_iters_per_keyframe=0"])
    kept = with_profile(explicit, HANDHELD)
    assert kept.pose.refine is False and kept.final_iters_per_keyframe == 0.0  # set explicitly: kept
    assert with_profile(MapperConfig(), HANDHELD).pose.refine is True


def _run_map(argv, monkeypatch, tmp_path):
    """``gausslite map ARGV`` up to the mapping itself (stubbed): returns (exit code, the task it mapped for)."""
    import gausslite.pipeline
    from gausslite.cli.cmd_map import register

    seen = {}

    def fake_run_mapping(ds, cfg, *, task_id=None, **kw):
        seen.update(mode=cfg.mode, task_id=task_id)
        return None, {}

    monkeypatch.setattr(gausslite.pipeline, "run_mapping", fake_run_mapping)
    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    args = p.parse_args(["map", *argv, "--out", str(tmp_path / "out"), "--no-progress"])
    return args.func(args), seen


def test_map_warns_when_it_maps_uniformly(room0_dir, tmp_path, monkeypatch, caplog):
    import logging

    caplog.set_level(logging.WARNING, logger="gausslite.map")
    rc, seen = _run_map(["--dataset", str(room0_dir), "--max-frames", "1"], monkeypatch, tmp_path)
    assert rc == 0 and seen == {"mode": "uniform", "task_id": None}
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "no task given: mapping uniformly" in msg
    assert "--mode gausslite" in msg and "--task-id" in msg and "objects.json" in msg and "--task \"" in msg
    assert "--onnx-detector" in msg and "serve agent" not in msg  # map grounds task words itself
    caplog.clear()
    rc, seen = _run_map(["--dataset", str(room0_dir), "--max-frames", "1", "--task-id", "room0-pick-plant"],
                        monkeypatch, tmp_path)
    assert rc == 0 and seen["mode"] == "uniform"
    assert "only scores the map" in " ".join(r.getMessage() for r in caplog.records)
    caplog.clear()  # task-conditioned: no warning
    rc, seen = _run_map(["--dataset", str(room0_dir), "--max-frames", "1", "--mode", "gausslite"], monkeypatch,
                        tmp_path)
    assert rc == 0 and seen["mode"] == "gausslite" and seen["task_id"]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
