"""Scene annotations (objects.json / tasks.json): parsing, validation, lookup and masks."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gausslite.camera import Intrinsics, backproject
from gausslite.datasets import SceneAnnotations, SceneObject, load_annotations, parse_up_axis, task_roi
from gausslite.datasets.annotations import find_annotation_files


def _rotz(a: float) -> list:
    return [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]


OBJECTS = {
    "format": "gausslite-objects/1",
    "frame": "world",
    "units": "m",
    "up_axis": "+z",
    "objects": [
        {"id": 1, "label": "cup", "synonyms": ["mug"], "center": [0.0, 0.0, 2.0], "size": [0.4, 0.2, 0.3],
         "rotation": _rotz(0.3), "mask_margin_m": 0.02, "notes": "white cup"},
        {"id": 2, "label": "table", "synonyms": [], "center": [0.5, 0.3, 3.0], "size": [1.0, 0.5, 0.4],
         "rotation": _rotz(0.0), "mask_margin_m": 0.0, "notes": ""},
    ],
}
TASKS = {
    "format": "gausslite-tasks/1",
    "tasks": [
        {"id": "pick-cup", "text": "Pick up the cup on the table",
         "graph": {"targets": ["cup"], "anchors": ["table"],
                   "relations": [{"predicate": "on", "target": "cup", "anchor": "table"}]},
         "roi_object_ids": [1, 2]},
        {"id": "find-cup", "text": "Find the cup", "graph": {"targets": ["cup"], "anchors": [], "relations": []},
         "roi_object_ids": [1]},
    ],
}


def write(folder: Path, objects=OBJECTS, tasks=TASKS) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    if objects is not None:
        (folder / "objects.json").write_text(json.dumps(objects))
    if tasks is not None:
        (folder / "tasks.json").write_text(json.dumps(tasks))
    return folder


# ------------------------------------------------------------------------------------------------
# real annotation files
# ------------------------------------------------------------------------------------------------
@pytest.mark.shared
def test_room0_annotations(room0_dir):
    ann = load_annotations(room0_dir)
    assert ann.objects_path == room0_dir.parent / "objects.json"
    assert len(ann.objects) == 12 and len(ann.tasks) == 5
    np.testing.assert_array_equal(ann.up_axis, [0.0, 0.0, 1.0])
    plant, table = ann.object_by_id(1), ann.object_by_id(2)
    assert plant.label == "potted plant" and "plant" in plant.synonyms and plant.mask_margin_m == 0.02
    t = ann.task_by_id("room0-pick-plant")
    assert t.roi_object_ids == (1, 2) and t.graph["relations"][0]["predicate"] == "on"
    # README relation sanity check: plant centre 0.40 m above the side table centre, 0.15 m horizontally
    d = plant.center - table.center
    assert d @ ann.up_axis == pytest.approx(0.40, abs=0.005)
    assert np.linalg.norm(d - (d @ ann.up_axis) * ann.up_axis) == pytest.approx(0.15, abs=0.005)
    # README: books' centre 0.22 m from the lantern's
    assert np.linalg.norm(ann.object_by_id(12).center - ann.object_by_id(5).center) == pytest.approx(0.22, abs=0.005)


@pytest.mark.shared
def test_tum_annotations(tum_rpy_dir):
    ann = load_annotations(tum_rpy_dir)
    assert len(ann.objects) == 10 and len(ann.tasks) == 5
    assert {o.label for o in ann.objects} >= {"keyboard", "monitor", "cup", "desk"}
    assert ann.task_by_id("tum-pick-gamepad").roi_object_ids == (8,)
    # README: the mouse's centre is 0.29 m from the keyboard's
    assert np.linalg.norm(ann.object_by_id(4).center - ann.object_by_id(1).center) == pytest.approx(0.29, abs=0.005)


# ------------------------------------------------------------------------------------------------
# lookup and parsing
# ------------------------------------------------------------------------------------------------
def test_lookup_sequence_folder_first_then_parent(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    assert load_annotations(seq) is None
    write(tmp_path)
    assert find_annotation_files(seq) == (tmp_path / "objects.json", tmp_path / "tasks.json")
    own = copy.deepcopy(OBJECTS)
    own["objects"][0]["label"] = "mug"
    write(seq, objects=own, tasks=None)
    ann = load_annotations(seq)
    assert ann.objects_path == seq / "objects.json" and ann.tasks_path == tmp_path / "tasks.json"
    assert ann.object_by_id(1).label == "mug"


def test_objects_only_and_tasks_only(tmp_path):
    ann = load_annotations(write(tmp_path / "a", tasks=None))
    assert ann.tasks == [] and len(ann.objects) == 2
    with pytest.raises(ValueError, match=r"tasks.json.*no objects.json"):
        load_annotations(write(tmp_path / "b", objects=None))


def test_parsed_values(tmp_path):
    ann = load_annotations(write(tmp_path))
    cup = ann.object_by_id(1)
    assert isinstance(cup, SceneObject) and cup.synonyms == ("mug",) and cup.notes == "white cup"
    assert cup.center.dtype == np.float64 and cup.rotation.shape == (3, 3)
    np.testing.assert_allclose(cup.size, [0.4, 0.2, 0.3])
    assert ann.task_by_id("pick-cup").text.startswith("Pick")
    with pytest.raises(KeyError, match=r"available ids: \[1, 2\]"):
        ann.object_by_id(7)
    with pytest.raises(KeyError, match=r"available ids: \['find-cup', 'pick-cup'\]"):
        ann.task_by_id("nope")


@pytest.mark.parametrize(
    "value, expected",
    [
        ("+z", [0, 0, 1]),
        ("-y", [0, -1, 0]),
        ("X", [1, 0, 0]),
        (" -z ", [0, 0, -1]),
        ([0, 0, 2.0], [0, 0, 1]),
        ([1.0, 1.0, 0.0], [math.sqrt(0.5), math.sqrt(0.5), 0]),
        ([0.006, -0.03, 1.0], np.array([0.006, -0.03, 1.0]) / np.linalg.norm([0.006, -0.03, 1.0])),
    ],
)
def test_up_axis_forms(value, expected):
    v = parse_up_axis(value)
    assert v.dtype == np.float64 and v.shape == (3,)
    np.testing.assert_allclose(v, expected, atol=1e-12)
    assert np.linalg.norm(v) == pytest.approx(1.0)


@pytest.mark.parametrize("value", ["up", "+w", "++z", "", [0, 0, 0], [float("nan"), 0, 1], [1, 2], [[0, 0, 1]],
                                   ["a", "b", "c"], None, [float("inf"), 0, 0]])
def test_up_axis_rejected(value):
    with pytest.raises(ValueError, match="up_axis"):
        parse_up_axis(value)


def test_up_axis_vector_in_file(tmp_path):
    obj = copy.deepcopy(OBJECTS)
    obj["up_axis"] = [0.0, 0.0, -3.0]
    ann = load_annotations(write(tmp_path, objects=obj))
    np.testing.assert_array_equal(ann.up_axis, [0, 0, -1])


def _bad_objects(mutate):
    obj = copy.deepcopy(OBJECTS)
    mutate(obj)
    return obj


def _bad_tasks(mutate):
    t = copy.deepcopy(TASKS)
    mutate(t)
    return t


BAD_OBJECTS = {
    "unknown format": (lambda o: o.update(format="gausslite-objects/2"), "unknown format"),
    "missing objects key": (lambda o: o.pop("objects"), r"missing keys \['objects'\]"),
    "missing up_axis": (lambda o: o.pop("up_axis"), r"missing keys \['up_axis'\]"),
    "bad up_axis": (lambda o: o.update(up_axis=[0, 0, 0]), "up_axis"),
    "frame": (lambda o: o.update(frame="camera"), "frame must be 'world'"),
    "units": (lambda o: o.update(units="mm"), "units must be 'm'"),
    "missing object key": (lambda o: o["objects"][1].pop("size"), r"objects\[1\] is missing keys \['size'\]"),
    "non-orthonormal": (lambda o: o["objects"][0].update(rotation=[[1, 0.1, 0], [0, 1, 0], [0, 0, 1]]), "not orthonormal"),
    "reflection": (lambda o: o["objects"][0].update(rotation=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "determinant"),
    "negative size": (lambda o: o["objects"][0].update(size=[0.1, -0.2, 0.1]), "size must be >= 0"),
    "nan center": (lambda o: o["objects"][0].update(center=[0, float("nan"), 0]), "center has NaN"),
    "short center": (lambda o: o["objects"][0].update(center=[0, 0]), "center must have shape"),
    "negative margin": (lambda o: o["objects"][0].update(mask_margin_m=-0.1), "mask_margin_m"),
    "string id": (lambda o: o["objects"][0].update(id="1"), "id must be an integer"),
    "duplicate id": (lambda o: o["objects"][1].update(id=1), "duplicate object ids"),
    "synonyms": (lambda o: o["objects"][0].update(synonyms="mug"), "synonyms"),
    "not a list": (lambda o: o.update(objects={}), "must be a list"),
}


@pytest.mark.parametrize("case", sorted(BAD_OBJECTS))
def test_invalid_objects_file(tmp_path, case):
    mutate, match = BAD_OBJECTS[case]
    folder = write(tmp_path, objects=_bad_objects(mutate))
    with pytest.raises(ValueError, match=match) as ei:
        load_annotations(folder)
    assert str(folder / "objects.json") in str(ei.value)


BAD_TASKS = {
    "unknown format": (lambda t: t.update(format="tasks/1"), "unknown format"),
    "missing tasks": (lambda t: t.pop("tasks"), r"missing keys \['tasks'\]"),
    "missing task key": (lambda t: t["tasks"][0].pop("graph"), r"tasks\[0\] is missing keys \['graph'\]"),
    "roi id missing": (lambda t: t["tasks"][1].update(roi_object_ids=[1, 9]), r"roi_object_ids \[9\] do not exist"),
    "roi not ints": (lambda t: t["tasks"][1].update(roi_object_ids=["1"]), "list of integers"),
    "graph not dict": (lambda t: t["tasks"][0].update(graph=[]), "graph must be an object"),
    "duplicate task": (lambda t: t["tasks"][1].update(id="pick-cup"), "duplicate task id"),
}


@pytest.mark.parametrize("case", sorted(BAD_TASKS))
def test_invalid_tasks_file(tmp_path, case):
    mutate, match = BAD_TASKS[case]
    folder = write(tmp_path, tasks=_bad_tasks(mutate))
    with pytest.raises(ValueError, match=match) as ei:
        load_annotations(folder)
    assert str(folder / "tasks.json") in str(ei.value)


def test_invalid_json(tmp_path):
    folder = write(tmp_path)
    (folder / "objects.json").write_text('{"format": ')
    with pytest.raises(ValueError, match=r"objects.json: invalid JSON \(line 1\)"):
        load_annotations(folder)


# ------------------------------------------------------------------------------------------------
# geometry and masks
# ------------------------------------------------------------------------------------------------
def test_box_corners(tmp_path):
    ann = load_annotations(write(tmp_path))
    table = ann.object_by_id(2)
    c = ann.box_corners(table)
    assert c.shape == (8, 3) and c.dtype == np.float64
    np.testing.assert_allclose(c.min(0), [0.0, 0.05, 2.8])
    np.testing.assert_allclose(c.max(0), [1.0, 0.55, 3.2])
    np.testing.assert_allclose(c[0], [0.0, 0.05, 2.8])  # (-,-,-) first
    np.testing.assert_allclose(c[7], [1.0, 0.55, 3.2])  # (+,+,+) last
    cup = ann.object_by_id(1)
    cc = ann.box_corners(cup)
    np.testing.assert_allclose(cc.mean(0), cup.center, atol=1e-12)
    local = (cc - cup.center) @ cup.rotation
    np.testing.assert_allclose(np.abs(local), np.tile(cup.size / 2, (8, 1)))
    ce = ann.box_corners(cup, enlarged=True)
    np.testing.assert_allclose(np.abs((ce - cup.center) @ cup.rotation), np.tile(cup.size / 2 + 0.02, (8, 1)))


def _reference_mask(ann, ids, depth, c2w, intr):
    """Brute force: back-project every pixel with camera.backproject and test every enlarged box."""
    valid = np.isfinite(depth) & (depth > 0)
    pts = backproject(np.where(valid, depth, 0), intr, c2w)
    m = np.zeros(depth.shape, bool)
    for i in ids:
        m |= ann.object_by_id(i).contains(pts)
    return m & valid


def test_object_mask_plane_analytic(tmp_path):
    # camera at the origin looking along +z; fronto-parallel plane at z = 2 through the cup centre
    obj = copy.deepcopy(OBJECTS)
    obj["objects"][0]["rotation"] = _rotz(0.0)
    ann = load_annotations(write(tmp_path, objects=obj))
    intr = Intrinsics(100.0, 100.0, 49.5, 39.5, 100, 80)
    depth = np.full((80, 100), 2.0, np.float32)
    m = ann.object_mask([1], depth, np.eye(4), intr)
    u = np.arange(100)
    v = np.arange(80)
    x = (u - 49.5) / 100 * 2
    y = (v - 39.5) / 100 * 2
    expected = (np.abs(y)[:, None] <= 0.1 + 0.02) & (np.abs(x)[None, :] <= 0.2 + 0.02)
    np.testing.assert_array_equal(m, expected)
    # invalid depth is never in a mask
    depth[40, 50] = 0
    depth[41, 50] = np.nan
    m2 = ann.object_mask(1, depth, np.eye(4), intr)
    assert not m2[40, 50] and not m2[41, 50] and m2[39, 50]
    assert not ann.object_mask([], depth, np.eye(4), intr).any()
    with pytest.raises(KeyError):
        ann.object_mask([5], depth, np.eye(4), intr)
    with pytest.raises(ValueError, match="does not match intrinsics"):
        ann.object_mask([1], depth[:-1], np.eye(4), intr)


@pytest.mark.parametrize("seed", range(6))
def test_object_mask_matches_bruteforce(tmp_path, seed):
    rng = np.random.default_rng(seed)
    ann = load_annotations(write(tmp_path))
    intr = Intrinsics(60.0, 62.0, 31.7, 23.2, 64, 48)
    # random camera around the objects (some boxes partly behind the camera or out of view)
    a, b = rng.uniform(-np.pi, np.pi, 2)
    R = np.array(_rotz(a)) @ np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    c2w = np.eye(4)
    c2w[:3, :3] = R
    c2w[:3, 3] = rng.uniform(-0.5, 0.5, 3) + [0.2, 0.1, 2.4]
    depth = rng.uniform(0.05, 2.0, (48, 64)).astype(np.float32)
    depth[rng.random((48, 64)) < 0.1] = 0
    for ids in ([1], [2], [1, 2]):
        np.testing.assert_array_equal(
            ann.object_mask(ids, depth, c2w, intr), _reference_mask(ann, ids, depth, c2w, intr)
        )
    # and looking straight at the boxes from the origin, with depths that hit them
    depth2 = rng.uniform(1.5, 3.5, (48, 64)).astype(np.float32)
    m = ann.object_mask([1, 2], depth2, np.eye(4), intr)
    np.testing.assert_array_equal(m, _reference_mask(ann, [1, 2], depth2, np.eye(4), intr))
    assert m.any()


def test_roi_mask_is_union(tmp_path):
    ann = load_annotations(write(tmp_path))
    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    depth = np.random.default_rng(3).uniform(1.5, 3.5, (48, 64)).astype(np.float32)
    roi = ann.roi_mask("pick-cup", depth, np.eye(4), intr)
    union = ann.object_mask([1], depth, np.eye(4), intr) | ann.object_mask([2], depth, np.eye(4), intr)
    np.testing.assert_array_equal(roi, union)
    assert roi.dtype == bool and roi.shape == (48, 64)
    with pytest.raises(KeyError, match="available ids"):
        ann.roi_mask("nope", depth, np.eye(4), intr)
    # the same ROI as a function of a frame (the scorers' and the gt relevance source's form)
    from types import SimpleNamespace

    fr = SimpleNamespace(depth=depth, c2w=np.eye(4), intrinsics=intr)
    np.testing.assert_array_equal(task_roi(ann, "pick-cup")(fr), roi)
    with pytest.raises(KeyError, match="available ids"):
        task_roi(ann, "nope")(fr)


def test_in_memory_construction_validates():
    o = SceneObject(1, "a", (), np.zeros(3), np.ones(3), np.eye(3))
    SceneAnnotations([o], [], "+z")
    with pytest.raises(ValueError, match="duplicate object id"):
        SceneAnnotations([o, o], [], "+z")
