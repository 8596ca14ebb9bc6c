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


def test_tum_flags_reach_the_loader(tum_rpy_dir, tmp_path):
    plain = resolve_dataset(_args("--dataset", str(tum_rpy_dir), "--max-frames", "2", "--downscale", "2"), tmp_path)
    ds = resolve_dataset(_args("--dataset", str(tum_rpy_dir), "--max-frames", "2", "--downscale", "2",
                               "--undistort", "--interpolate-poses"), tmp_path)
    assert isinstance(ds, TUMDataset) and ds.undistort and not plain.undistort
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
