"""Scene annotations: labelled 3D boxes (``objects.json``) and tasks with ROI objects (``tasks.json``).

File format: ``docs/mapper.md`` ("Scene annotations"). Boxes are oriented boxes in the
world frame of the dataset poses, in metres: ``center`` (3,), full extents ``size`` (3,) along the box
axes, and ``rotation`` (3, 3) whose columns are the box axes in world coordinates (box-local -> world).
A world point ``p`` lies in a box when ``|R^T (p - c)| <= size / 2 + margin`` on all three axes.

Mask rule (same source): a pixel is in an object's mask when its back-projected depth point (world
frame, pinhole intrinsics, camera-to-world pose, no undistortion) lies inside the object's box enlarged
by ``mask_margin_m`` on every side; pixels with invalid depth (0) are never in a mask. A task's ROI
mask is the union of the masks of its ``roi_object_ids``.

Files are looked up in the sequence folder first, then its parent (each file independently).
"""

from __future__ import annotations

import itertools
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple, Union

import numpy as np

from gausslite.camera import Intrinsics

__all__ = [
    "SceneObject",
    "Task",
    "SceneAnnotations",
    "OBJECTS_FORMAT",
    "TASKS_FORMAT",
    "parse_up_axis",
    "find_annotation_files",
    "load_annotations",
    "parse_objects",
    "parse_tasks",
    "task_roi",
]

OBJECTS_FORMAT = "gausslite-objects/1"
TASKS_FORMAT = "gausslite-tasks/1"
_ROT_ATOL = 1e-3


@dataclass(eq=False)
class SceneObject:
    """One labelled oriented 3D box in the world frame.

    Attributes:
        id: integer object id (unique within the scene).
        label: main name, e.g. ``"potted plant"``.
        synonyms: other names a query phrase may match.
        center: (3,) float64 box centre, world frame, metres.
        size: (3,) float64 full extents along the box axes, metres (>= 0).
        rotation: (3, 3) float64 proper rotation; columns are the box axes in world coordinates.
        mask_margin_m: margin (metres, >= 0) added on every side when building masks.
        notes: free text telling instances with the same label apart.
    """

    id: int
    label: str
    synonyms: Tuple[str, ...]
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    mask_margin_m: float = 0.0
    notes: str = ""

    def contains(self, points: np.ndarray, margin: Optional[float] = None) -> np.ndarray:
        """Which world points lie inside the box enlarged by ``margin`` on every side.

        Args:
            points: (..., 3) world points, metres.
            margin: metres; defaults to ``mask_margin_m``.

        Returns:
            (...) bool array.
        """
        m = self.mask_margin_m if margin is None else float(margin)
        local = (np.asarray(points, dtype=np.float64) - self.center) @ self.rotation
        return np.all(np.abs(local) <= self.size / 2.0 + m, axis=-1)


@dataclass(eq=False)
class Task:
    """A natural-language task with its expected graph and ground-truth ROI objects.

    Attributes:
        id: task id, e.g. ``"room0-pick-plant"``.
        text: the task sentence.
        graph: expected parser output ``{"targets": [...], "anchors": [...], "relations": [...]}``
            (rules in ``docs/mapper.md``, "Task graphs"), kept as parsed JSON.
        roi_object_ids: ids of the objects whose mask union is the task's ground-truth ROI.
    """

    id: str
    text: str
    graph: Dict[str, Any]
    roi_object_ids: Tuple[int, ...]


@dataclass(eq=False)
class SceneAnnotations:
    """All annotations of one scene.

    Attributes:
        objects: list of ``SceneObject``.
        tasks: list of ``Task`` (empty when there is no ``tasks.json``).
        up_axis: (3,) float64 unit vector, world direction that points up.
        objects_path, tasks_path: the files read (None when built in memory / absent).
    """

    objects: List[SceneObject]
    tasks: List[Task]
    up_axis: np.ndarray
    objects_path: Optional[Path] = None
    tasks_path: Optional[Path] = None
    _obj_index: Dict[int, SceneObject] = field(default_factory=dict, init=False, repr=False)
    _task_index: Dict[str, Task] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.up_axis = parse_up_axis(self.up_axis)
        self._obj_index = {}
        for o in self.objects:
            if o.id in self._obj_index:
                raise ValueError(f"duplicate object id {o.id}")
            self._obj_index[o.id] = o
        self._task_index = {}
        for t in self.tasks:
            if t.id in self._task_index:
                raise ValueError(f"duplicate task id {t.id!r}")
            missing = [i for i in t.roi_object_ids if i not in self._obj_index]
            if missing:
                raise ValueError(f"task {t.id!r}: roi_object_ids {missing} are not object ids")
            self._task_index[t.id] = t

    def object_by_id(self, object_id: int) -> SceneObject:
        """The object with id ``object_id``.

        Raises:
            KeyError: unknown id (the message lists the available ids).
        """
        try:
            return self._obj_index[int(object_id)]
        except (KeyError, TypeError, ValueError):
            raise KeyError(f"no object with id {object_id!r}; available ids: {sorted(self._obj_index)}") from None

    def task_by_id(self, task_id: str) -> Task:
        """The task with id ``task_id``.

        Raises:
            KeyError: unknown id (the message lists the available ids).
        """
        try:
            return self._task_index[task_id]
        except (KeyError, TypeError):
            raise KeyError(f"no task with id {task_id!r}; available ids: {sorted(self._task_index)}") from None

    @staticmethod
    def box_corners(obj: SceneObject, enlarged: bool = False) -> np.ndarray:
        """The 8 corners of an object's box in world coordinates.

        Args:
            obj: the object.
            enlarged: include ``mask_margin_m`` on every side.

        Returns:
            (8, 3) float64, metres. Corner ``k`` has local signs ``itertools.product((-1, 1), repeat=3)[k]``
            along the box axes (x slowest, z fastest).
        """
        half = obj.size / 2.0 + (obj.mask_margin_m if enlarged else 0.0)
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
        return obj.center + (signs * half) @ obj.rotation.T

    def object_mask(
        self,
        object_ids: Union[int, Iterable[int]],
        depth: np.ndarray,
        c2w: np.ndarray,
        intrinsics: Intrinsics,
    ) -> np.ndarray:
        """Pixels whose back-projected depth lies in any of the given objects' enlarged boxes.

        Args:
            object_ids: an id or iterable of ids (empty -> all False).
            depth: (H, W) depth in metres along camera z, 0 = invalid (non-finite also invalid).
            c2w: (4, 4) camera-to-world pose (OpenCV camera axes).
            intrinsics: pinhole intrinsics of size W x H (no undistortion is applied).

        Returns:
            (H, W) bool mask; invalid depth is never in it.

        Raises:
            KeyError: unknown object id. ValueError: depth size differs from the intrinsics or bad pose shape.
        """
        ids = [object_ids] if isinstance(object_ids, (int, np.integer)) else list(object_ids)
        objs = [self.object_by_id(i) for i in ids]
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.shape != (intrinsics.height, intrinsics.width):
            raise ValueError(
                f"depth shape {depth.shape} does not match intrinsics {intrinsics.width}x{intrinsics.height}"
            )
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape != (4, 4):
            raise ValueError(f"c2w must be 4x4, got {c2w.shape}")
        H, W = depth.shape
        fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        mask = np.zeros((H, W), dtype=bool)
        valid = np.isfinite(depth) & (depth > 0)
        Rwc, twc = c2w[:3, :3], c2w[:3, 3]
        for o in objs:
            # box-local coordinates of a camera point: R_o^T (R_wc p_c + t_wc - c_o) = A p_c + b
            A = o.rotation.T @ Rwc
            b = o.rotation.T @ (twc - o.center)
            half = o.size / 2.0 + o.mask_margin_m
            # Pixel window: when the enlarged box is entirely in front of the camera, every pixel whose
            # point lies in the box projects inside the bounding rectangle of the projected corners
            # (the projection of a convex set in z > 0 is the hull of its projected corners).
            u0, u1, v0, v1 = 0, W - 1, 0, H - 1
            corners_c = (self.box_corners(o, enlarged=True) - twc) @ Rwc  # (8, 3) camera frame
            if np.all(corners_c[:, 2] > 1e-9):
                uu = fx * corners_c[:, 0] / corners_c[:, 2] + cx
                vv = fy * corners_c[:, 1] / corners_c[:, 2] + cy
                u0 = max(u0, int(np.floor(uu.min())) - 1)
                u1 = min(u1, int(np.ceil(uu.max())) + 1)
                v0 = max(v0, int(np.floor(vv.min())) - 1)
                v1 = min(v1, int(np.ceil(vv.max())) + 1)
                if u0 > u1 or v0 > v1:
                    continue
            z = np.where(valid[v0 : v1 + 1, u0 : u1 + 1], depth[v0 : v1 + 1, u0 : u1 + 1], 0.0).astype(np.float64)
            x = ((np.arange(u0, u1 + 1, dtype=np.float64) - cx) / fx)[None, :] * z
            y = ((np.arange(v0, v1 + 1, dtype=np.float64) - cy) / fy)[:, None] * z
            inside = valid[v0 : v1 + 1, u0 : u1 + 1].copy()
            for k in range(3):
                inside &= np.abs(A[k, 0] * x + A[k, 1] * y + A[k, 2] * z + b[k]) <= half[k]
            mask[v0 : v1 + 1, u0 : u1 + 1] |= inside
        return mask

    def roi_mask(self, task_id: str, depth: np.ndarray, c2w: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
        """Ground-truth ROI of a task: union of the masks of its ``roi_object_ids``.

        Args and returns as :meth:`object_mask` ((H, W) bool).

        Raises:
            KeyError: unknown task id.
        """
        return self.object_mask(self.task_by_id(task_id).roi_object_ids, depth, c2w, intrinsics)



def task_roi(annotations, task_id: str) -> Callable[[Any], np.ndarray]:
    """The ground-truth ROI of a task as a function of a frame, the form the scorers and the ``gt`` relevance source
    take: ``frame`` (a dataset ``Frame``: ``depth`` (H, W) float32 metres, ``c2w`` (4, 4) camera-to-world,
    ``intrinsics``) → (H, W) bool, ``annotations.roi_mask`` of that view (:meth:`SceneAnnotations.roi_mask`, or any
    object with that method).

    Raises:
        KeyError (when called): unknown task id.
    """
    return lambda fr: annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics)


# ----------------------------------------------------------------------------------------------
# parsing
# ----------------------------------------------------------------------------------------------
_AXIS_RE = re.compile(r"^\s*([+-]?)\s*([xyz])\s*$", re.IGNORECASE)


def parse_up_axis(value: Any) -> np.ndarray:
    """Parse an up axis given as ``"+z"`` / ``"-y"`` style (sign optional, case-insensitive) or a 3-vector.

    Returns:
        (3,) float64 unit vector (vectors are normalised).

    Raises:
        ValueError: unknown string, wrong length, non-finite or (near-)zero vector.
    """
    if isinstance(value, str):
        m = _AXIS_RE.match(value)
        if not m:
            raise ValueError(f"up_axis {value!r} is not one of '+x', '-x', '+y', '-y', '+z', '-z' or a 3-vector")
        v = np.zeros(3)
        v["xyz".index(m.group(2).lower())] = -1.0 if m.group(1) == "-" else 1.0
        return v
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"up_axis {value!r} is neither an axis string nor a 3-vector") from None
    if v.shape != (3,):
        raise ValueError(f"up_axis must have 3 components, got {value!r}")
    n = float(np.linalg.norm(v)) if np.all(np.isfinite(v)) else float("nan")
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError(f"up_axis must be a finite non-zero vector, got {value!r}")
    return v / n


def _read_json(path: Path) -> Any:
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON (line {e.lineno}): {e.msg}") from None


def _vec(v: Any, shape: Tuple[int, ...], what: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numeric with shape {shape}, got {v!r}") from None
    if a.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has NaN or infinite entries")
    return a


def _parse_object(d: Any, k: int) -> SceneObject:
    if not isinstance(d, dict):
        raise ValueError(f"objects[{k}] must be an object, got {type(d).__name__}")
    missing = [key for key in ("id", "label", "center", "size", "rotation") if key not in d]
    if missing:
        raise ValueError(f"objects[{k}] is missing keys {missing}")
    oid = d["id"]
    if isinstance(oid, bool) or not isinstance(oid, int):
        raise ValueError(f"objects[{k}]: id must be an integer, got {oid!r}")
    where = f"object id {oid}"
    if not isinstance(d["label"], str) or not d["label"].strip():
        raise ValueError(f"{where}: label must be a non-empty string")
    syn = d.get("synonyms", [])
    if not isinstance(syn, list) or not all(isinstance(s, str) for s in syn):
        raise ValueError(f"{where}: synonyms must be a list of strings")
    center = _vec(d["center"], (3,), f"{where}: center")
    size = _vec(d["size"], (3,), f"{where}: size")
    if np.any(size < 0):
        raise ValueError(f"{where}: size must be >= 0 on every axis, got {size.tolist()}")
    R = _vec(d["rotation"], (3, 3), f"{where}: rotation")
    if not np.allclose(R.T @ R, np.eye(3), atol=_ROT_ATOL) or abs(np.linalg.det(R) - 1.0) > _ROT_ATOL:
        raise ValueError(f"{where}: rotation is not orthonormal with determinant +1 (atol {_ROT_ATOL})")
    margin = d.get("mask_margin_m", 0.0)
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not math.isfinite(margin) or margin < 0:
        raise ValueError(f"{where}: mask_margin_m must be a finite number >= 0, got {margin!r}")
    notes = d.get("notes", "")
    if not isinstance(notes, str):
        raise ValueError(f"{where}: notes must be a string")
    return SceneObject(oid, d["label"], tuple(syn), center, size, R, float(margin), notes)


def parse_objects(path: Path) -> Tuple[List[SceneObject], np.ndarray]:
    """Parse and validate an ``objects.json`` file.

    Required top-level keys: ``format`` (== ``"gausslite-objects/1"``), ``up_axis``, ``objects``;
    ``frame`` must be ``"world"`` and ``units`` ``"m"`` when present. Required object keys: ``id`` (int),
    ``label``, ``center`` (3), ``size`` (3, >= 0), ``rotation`` (3x3 proper rotation, atol 1e-3);
    optional ``synonyms`` (default []), ``mask_margin_m`` (default 0, >= 0), ``notes`` (default "").

    Returns:
        (objects, up_axis as a (3,) float64 unit vector).

    Raises:
        FileNotFoundError: missing file. ValueError: any violation; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"objects file not found: {path}")
    data = _read_json(path)
    try:
        if not isinstance(data, dict):
            raise ValueError("top level must be a JSON object")
        missing = [k for k in ("format", "up_axis", "objects") if k not in data]
        if missing:
            raise ValueError(f"missing keys {missing}")
        if data["format"] != OBJECTS_FORMAT:
            raise ValueError(f"unknown format {data['format']!r} (expected {OBJECTS_FORMAT!r})")
        if "frame" in data and data["frame"] != "world":
            raise ValueError(f"frame must be 'world', got {data['frame']!r}")
        if "units" in data and data["units"] != "m":
            raise ValueError(f"units must be 'm', got {data['units']!r}")
        if not isinstance(data["objects"], list):
            raise ValueError("'objects' must be a list")
        objects = [_parse_object(d, k) for k, d in enumerate(data["objects"])]
        ids = [o.id for o in objects]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicate object ids {dup}")
        up = parse_up_axis(data["up_axis"])
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    return objects, up


def parse_tasks(path: Path, object_ids: Optional[Iterable[int]] = None) -> List[Task]:
    """Parse and validate a ``tasks.json`` file.

    Required: top-level ``format`` (== ``"gausslite-tasks/1"``) and ``tasks`` (list); each task needs
    ``id`` (str), ``text`` (str), ``graph`` (dict) and ``roi_object_ids`` (list of ints).

    Args:
        path: the file.
        object_ids: known object ids; when given, every ROI id must be among them.

    Raises:
        FileNotFoundError: missing file. ValueError: any violation, including ROI ids that are not
        object ids and duplicate task ids; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"tasks file not found: {path}")
    data = _read_json(path)
    known = None if object_ids is None else set(object_ids)
    tasks: List[Task] = []
    try:
        if not isinstance(data, dict):
            raise ValueError("top level must be a JSON object")
        missing = [k for k in ("format", "tasks") if k not in data]
        if missing:
            raise ValueError(f"missing keys {missing}")
        if data["format"] != TASKS_FORMAT:
            raise ValueError(f"unknown format {data['format']!r} (expected {TASKS_FORMAT!r})")
        if not isinstance(data["tasks"], list):
            raise ValueError("'tasks' must be a list")
        seen = set()
        for k, d in enumerate(data["tasks"]):
            if not isinstance(d, dict):
                raise ValueError(f"tasks[{k}] must be an object")
            miss = [key for key in ("id", "text", "graph", "roi_object_ids") if key not in d]
            if miss:
                raise ValueError(f"tasks[{k}] is missing keys {miss}")
            tid = d["id"]
            if not isinstance(tid, str) or not tid:
                raise ValueError(f"tasks[{k}]: id must be a non-empty string")
            if tid in seen:
                raise ValueError(f"duplicate task id {tid!r}")
            seen.add(tid)
            if not isinstance(d["text"], str):
                raise ValueError(f"task {tid!r}: text must be a string")
            if not isinstance(d["graph"], dict):
                raise ValueError(f"task {tid!r}: graph must be an object")
            roi = d["roi_object_ids"]
            if not isinstance(roi, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in roi):
                raise ValueError(f"task {tid!r}: roi_object_ids must be a list of integers")
            if known is not None:
                bad = [i for i in roi if i not in known]
                if bad:
                    raise ValueError(f"task {tid!r}: roi_object_ids {bad} do not exist (object ids: {sorted(known)})")
            tasks.append(Task(tid, d["text"], d["graph"], tuple(roi)))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    return tasks


def find_annotation_files(seq_dir: Union[str, Path]) -> Tuple[Optional[Path], Optional[Path]]:
    """Locate ``objects.json`` and ``tasks.json``: the sequence folder first, then its parent.

    Returns:
        ``(objects_path or None, tasks_path or None)``, each found independently.
    """
    seq = Path(seq_dir)
    found: List[Optional[Path]] = []
    for fname in ("objects.json", "tasks.json"):
        hit = None
        for d in (seq, seq.parent):
            if (d / fname).is_file():
                hit = d / fname
                break
        found.append(hit)
    return found[0], found[1]


def load_annotations(seq_dir: Union[str, Path]) -> Optional[SceneAnnotations]:
    """Load the annotations of a sequence folder (see :func:`find_annotation_files`).

    Returns:
        ``SceneAnnotations`` or None when neither file exists. With only ``objects.json`` the task list
        is empty.

    Raises:
        ValueError: invalid files (message names the file), or a ``tasks.json`` without an
        ``objects.json`` (its ROI ids cannot exist).
    """
    obj_path, task_path = find_annotation_files(seq_dir)
    if obj_path is None and task_path is None:
        return None
    if obj_path is None:
        raise ValueError(f"{task_path}: tasks.json found but no objects.json beside it or in the sequence folder")
    objects, up = parse_objects(obj_path)
    tasks = parse_tasks(task_path, [o.id for o in objects]) if task_path is not None else []
    return SceneAnnotations(objects, tasks, up, objects_path=obj_path, tasks_path=task_path)
