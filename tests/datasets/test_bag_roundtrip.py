"""TUM fr1_rpy → ``gausslite export bag`` → bag loader: same images, depths, intrinsics and poses, and the
same mapping PSNR (a few frames at low resolution so the test stays a few seconds)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gausslite.cli import main
from gausslite.datasets import TUMDataset, load_dataset
from gausslite.datasets.bag import BagDataset
from gausslite.ros.export import TOPICS, export_bag

N_FRAMES = 10


@pytest.fixture(scope="module")
def tum_small(tum_rpy_dir):
    # undistorted + interpolated poses: the bag must carry the loader's output, not the raw files
    return load_dataset(tum_rpy_dir, downscale=4, max_frames=N_FRAMES, undistort=True, interpolate_poses=True)


def _assert_same(a, b, depth_atol=0.0):
    assert len(a) == len(b) == N_FRAMES
    assert b.intrinsics == a.intrinsics
    for fa, fb in zip(a, b):
        assert np.array_equal(fa.rgb, fb.rgb)
        assert np.abs(fa.depth - fb.depth).max() <= depth_atol
        assert np.abs(fa.c2w - fb.c2w).max() < 1e-6
        assert abs(fa.timestamp - fb.timestamp) < 1e-6


@pytest.mark.shared
@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_tum_round_trip_through_every_storage(tmp_path, tum_small, storage):
    out = tmp_path / ("tum.bag" if storage == "ros1" else "tum")
    summary = export_bag(tum_small, out, storage=storage)
    assert summary["frames"] == N_FRAMES and summary["topics"] == TOPICS
    bag = load_dataset(out)
    assert isinstance(bag, BagDataset) and bag.pose_topic == "tf" and bag.world_frame == "map"
    _assert_same(tum_small, bag)
    # the PoseStamped topic gives the same poses
    via_topic = load_dataset(out, bag={"pose_topic": TOPICS["pose"]})
    for fa, fb in zip(tum_small, via_topic):
        assert np.abs(fa.c2w - fb.c2w).max() < 1e-6


@pytest.mark.shared
def test_tum_round_trip_16uc1_and_annotations(tmp_path, tum_small):
    out = tmp_path / "mm"
    summary = export_bag(tum_small, out, depth_encoding="16UC1")
    bag = load_dataset(out)
    _assert_same(tum_small, bag, depth_atol=0.0005 + 1e-6)  # millimetres, rounded
    if tum_small.annotations is not None:
        assert summary["annotations"] and bag.annotations is not None
        assert [o.id for o in bag.annotations.objects] == [o.id for o in tum_small.annotations.objects]
    with pytest.raises(FileExistsError):
        export_bag(tum_small, out)


@pytest.mark.shared
def test_export_bag_cli_and_mapping_gives_the_same_psnr(tmp_path, tum_rpy_dir):
    out = tmp_path / "cli_bag"
    args = ["--downscale", "4", "--max-frames", "3"]
    assert main(["export", "bag", "--dataset", str(tum_rpy_dir), "--out", str(out), *args]) == 0
    assert main(["export", "bag", "--dataset", str(tum_rpy_dir), "--out", str(out), *args]) == 2  # exists
    tum = load_dataset(tum_rpy_dir, downscale=4, max_frames=3, undistort=True, interpolate_poses=True,
                       align_depth_time=True)  # the hand-held profile, as export bag applies it
    assert isinstance(tum, TUMDataset)
    fast = ["--iters", "4", "--seeds-per-frame", "300", "--set", "final_iters=0", "--set", "warmup_iters=1",
            "--set", "final_iters_per_keyframe=0",
            "--backend", "warp", "--no-progress"]
    metrics = {}
    for name, ds in (("folder", tum_rpy_dir), ("bag", out)):
        rc = main(["map", "--dataset", str(ds), "--max-frames", "3", *fast, "--out", str(tmp_path / name),
                   *([] if name == "bag" else ["--downscale", "4"])])
        assert rc == 0
        metrics[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    assert metrics["bag"]["n_frames"] == metrics["folder"]["n_frames"] == 3
    # The bag's poses differ from the folder's by ~1e-16 (quaternion round trip). The mapper is chaotic in
    # them (a 1e-15 pose perturbation moves PSNR by ~0.1 dB after 20 iterations/frame, bench/bag.py, retired:
    # docs/history.md#bag), so
    # the direct comparison is close but not exact at these few iterations ...
    assert metrics["bag"]["psnr"] == pytest.approx(metrics["folder"]["psnr"], abs=1e-3)
    assert metrics["bag"]["depth_l1"] == pytest.approx(metrics["folder"]["depth_l1"], rel=1e-3)
    # ... and exact once the folder carries the bag's poses: images, depths and intrinsics map identically
    from gausslite.config import load_mapper_config
    from gausslite.mapping.profiles import profile_for_layout
    from gausslite.pipeline import run_mapping

    bag = load_dataset(out)
    tum.poses = np.stack([bag[i].c2w for i in range(len(bag))])
    cfg = load_mapper_config(None, ["final_iters=0", "warmup_iters=1", "final_iters_per_keyframe=0"], iters_per_frame=4,
                             seeding={"seeds_per_frame": 300}, defaults=dict(profile_for_layout("bag").mapper),
                             backend="warp", mode="uniform")  # as `map` of the bag
    _, m = run_mapping(tum, cfg, progress=False)
    assert m["psnr"] == metrics["bag"]["psnr"] and m["n_gaussians"] == metrics["bag"]["n_gaussians"]
