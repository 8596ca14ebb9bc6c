"""Annotations of our own (gausslite.datasets.labelling): boxes from one click on synthetic point clouds, the choice
of annotations a dataset loads, the labels file's checks, and the shipped sets regenerated from the shared copies of
their sequences by ``gausslite annotate``, byte for byte."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gausslite.cli import main as cli_main
from gausslite.datasets import load_dataset
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.labelling import (SHIPPED, SHIPPED_DIR, label_scene, object_box, resolve_annotations,
                                          shipped_set_of, surface_box)

UP = np.array([0.0, 0.0, 1.0])


def _rect_points(center, size, yaw, z, step=0.01):
    """Points on a horizontal rectangle (a table top) at height z, rotated by yaw about +z."""
    u, v = np.meshgrid(np.arange(-size[0] / 2, size[0] / 2 + 1e-9, step), np.arange(-size[1] / 2, size[1] / 2 + 1e-9, step))
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = center[0] + c * u - s * v, center[1] + s * u + c * v
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def _box_surface_points(center, size, yaw, step=0.01):
    """Points on the sides and top of an upright box standing at center[2] (its base)."""
    pts = [_rect_points(center[:2], size[:2], yaw, center[2] + size[2])]
    for h in np.arange(center[2], center[2] + size[2], step):
        ring = _rect_points(center[:2], size[:2], yaw, h)
        local = ring[:, :2] - center[:2]
        c, s = np.cos(-yaw), np.sin(-yaw)
        lu, lv = c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]
        edge = (np.abs(np.abs(lu) - size[0] / 2) < step / 2) | (np.abs(np.abs(lv) - size[1] / 2) < step / 2)
        pts.append(ring[edge])
    return np.concatenate(pts)


@pytest.fixture(scope="module")
def desk_scene():
    """A floor at z 0, a desk top at 0.75 m (1.2 × 0.8 m, yawed 20°), a box (0.20 × 0.10 × 0.15 m, yawed 35°) on it
    and a second box 10 cm beside it."""
    floor = _rect_points((0.0, 0.0), (3.0, 3.0), 0.0, 0.0, step=0.03)
    desk = _rect_points((0.0, 0.0), (1.2, 0.8), np.deg2rad(20), 0.75)
    cup = _box_surface_points(np.array([0.1, 0.05, 0.75]), (0.20, 0.10, 0.15), np.deg2rad(35))
    other = _box_surface_points(np.array([-0.25, -0.15, 0.75]), (0.08, 0.08, 0.25), 0.0)
    return np.concatenate([floor, desk, cup, other])


def test_an_object_is_the_cluster_above_its_support(desk_scene):
    box = object_box(desk_scene, np.array([0.1, 0.05, 0.9]), UP, radius_m=0.3)
    np.testing.assert_allclose(box["size"], [0.20, 0.10, 0.15], atol=0.015)
    np.testing.assert_allclose(box["center"], [0.1, 0.05, 0.825], atol=0.01)
    # its first axis is the longer side, at the box's yaw (35°, up to the sign)
    axis = box["rotation"][:, 0]
    assert abs(abs(np.dot(axis, [np.cos(np.deg2rad(35)), np.sin(np.deg2rad(35)), 0.0])) - 1.0) < 1e-3
    np.testing.assert_allclose(box["rotation"].T @ box["rotation"], np.eye(3), atol=1e-9)
    assert np.linalg.det(box["rotation"]) == pytest.approx(1.0)


def test_a_surface_is_its_plane_patch_down_to_the_floor_when_asked(desk_scene):
    seed = np.array([0.4, -0.2, 0.75])
    top = surface_box(desk_scene, seed, UP, thickness_m=0.05, height_m=0.02)
    np.testing.assert_allclose(sorted(top["size"][:2]), [0.8, 1.2], atol=0.02)
    assert top["size"][2] == pytest.approx(0.07, abs=1e-6)
    assert top["center"][2] == pytest.approx(0.75 - 0.05 + 0.035, abs=1e-3)
    whole = surface_box(desk_scene, seed, UP, thickness_m="floor")
    assert whole["size"][2] == pytest.approx(0.75, abs=0.01)


def test_no_support_or_no_plane_is_an_error(desk_scene):
    with pytest.raises(ValueError, match="no horizontal plane below"):
        object_box(desk_scene[desk_scene[:, 2] > 0.7], np.array([5.0, 5.0, 5.0]), UP)
    with pytest.raises(ValueError, match="no horizontal plane through"):
        surface_box(desk_scene, np.array([0.0, 0.0, 0.4]), UP)


def test_which_annotations_a_sequence_loads(tmp_path):
    beside = object()
    seq = tmp_path / "rgbd_dataset_freiburg1_rpy"
    other = tmp_path / "my_office"
    assert shipped_set_of(seq, "tum") == "tum_fr1_rpy"
    assert shipped_set_of(tmp_path / "TUM_rgbd_dataset_freiburg1_rpy", "tum") == "tum_fr1_rpy"
    assert shipped_set_of(tmp_path / "room0", "replica") == "replica_room0"
    assert shipped_set_of(tmp_path / "room0", "tum") is None and shipped_set_of(other, "tum") is None
    # auto: the files beside the data first, else the shipped set of a recognised sequence, else none
    assert resolve_annotations(seq, "tum", "auto", beside) is beside
    shipped = resolve_annotations(seq, "tum", "auto", None)
    assert shipped.objects_path == SHIPPED_DIR / "tum_fr1_rpy" / "objects.json"
    assert resolve_annotations(other, "tum", "auto", None) is None
    assert resolve_annotations(seq, "tum", "beside", None) is None
    assert resolve_annotations(seq, "tum", "shipped", beside).objects_path == shipped.objects_path
    with pytest.raises(ValueError, match="ships no annotations"):
        resolve_annotations(other, "tum", "shipped", beside)
    with pytest.raises(FileNotFoundError, match="no objects.json"):
        resolve_annotations(seq, "tum", tmp_path, beside)
    folder = tmp_path / "mine"
    folder.mkdir()
    for name in ("objects.json", "tasks.json"):
        (folder / name).write_text((SHIPPED_DIR / "replica_room0" / name).read_text())
    assert resolve_annotations(seq, "tum", folder, beside).objects_path == folder / "objects.json"


@pytest.mark.parametrize("key,tasks", [
    ("tum_fr1_rpy", {"tum-pick-cup", "tum-find-mouse", "tum-reach-keyboard"}),
    ("replica_room0", {"room0-pick-plant", "room0-find-ottoman", "room0-map-ottomans"})])
def test_the_shipped_sets_load_with_the_benchmarks_tasks(key, tasks):
    ann = load_annotations(SHIPPED_DIR / key)
    assert {t.id for t in ann.tasks} == tasks
    for t in ann.tasks:
        for i in t.roi_object_ids:
            assert ann.object_by_id(i).size.min() > 0.03
    labels = json.loads((SHIPPED_DIR / key / "labels.json").read_text())
    assert labels["tasks"] == json.loads((SHIPPED_DIR / key / "tasks.json").read_text())["tasks"]


def test_a_bad_labels_file_names_what_is_wrong(tmp_path):
    good = json.loads((SHIPPED_DIR / "replica_room0" / "labels.json").read_text())
    cases = [({**good, "format": "x"}, "format must be"),
             ({k: v for k, v in good.items() if k != "fuse_frames"}, "missing 'fuse_frames'"),
             ({**good, "objects": [{**good["objects"][0], "kind": "blob"}]}, "kind must be"),
             ({**good, "objects": [{**good["objects"][0], "click": {"frame": 3}}]}, "click must be")]
    for doc, msg in cases:
        p = tmp_path / "labels.json"
        p.write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=msg):
            label_scene(None, p)
    assert cli_main(["annotate", "--dataset", str(tmp_path / "none"), "--labels", str(p), "--out",
                     str(tmp_path / "o")]) == 2


@pytest.mark.shared
@pytest.mark.parametrize("key", sorted(SHIPPED))
def test_the_shipped_sets_are_what_annotate_makes_of_their_labels(key, tmp_path, room0_dir, tum_rpy_dir, capsys):
    """The docs' command (docs/annotations.md) on the shared copy of each sequence writes the shipped files."""
    data = {"tum_fr1_rpy": tum_rpy_dir, "replica_room0": room0_dir.parent}[key]
    assert cli_main(["annotate", "--dataset", str(data), "--labels", key, "--out", str(tmp_path)]) == 0
    assert "wrote" in capsys.readouterr().out
    for name in ("objects.json", "tasks.json"):
        assert (tmp_path / name).read_text() == (SHIPPED_DIR / key / name).read_text(), name
    # every click lies on its object: the box, enlarged by its mask margin, holds the clicked pixel's depth point
    ds = load_dataset(data, annotations="shipped", progress=False)
    labels = json.loads((SHIPPED_DIR / key / "labels.json").read_text())
    for o in labels["objects"]:
        fr = ds[ds.frame_names.index(o["click"]["frame"])]
        u, v = o["click"]["uv"]
        mask = ds.annotations.object_mask(o["id"], fr.depth, fr.c2w, fr.intrinsics)
        assert mask[int(v), int(u)], o["label"]
