"""Scene annotations of our own: oriented 3D boxes labelled from one click per object on a sequence's frames, and the
annotation sets shipped with GaussLite for the public sequences its results use (``docs/annotations.md``).

A labels file (``gausslite-labels/1``, JSON) names, for each object, one pixel on it in one frame (by the frame's file
name, which the public download and any subset of it share) and what kind of thing it is:

- ``object``: a thing that stands on a surface (a cup, a mouse, a plant). Its box is the cluster of points above the
  supporting plane around the click, gravity-aligned.
- ``surface``: a horizontal surface (a desk, a table top). Its box is the connected patch of the plane through the
  click, from ``thickness_m`` below the plane up to ``height_m`` above it, or down to the floor
  (``"thickness_m": "floor"``).

The points are the depth maps of the frames the file lists, back-projected at their poses and fused on a voxel grid.
:func:`label_scene` turns a labels file into ``objects.json`` and ``tasks.json`` (formats: ``docs/mapper.md``, Scene
annotations); ``gausslite annotate`` is its command line.

Planes are horizontal (the labels give the up axis): each is the peak of a height histogram. Clustering is Open3D's
DBSCAN; the box is OpenCV's minimum-area rectangle of the points seen from above, with their vertical extent.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from gausslite.datasets.annotations import OBJECTS_FORMAT, TASKS_FORMAT, load_annotations, parse_up_axis

log = logging.getLogger(__name__)

LABELS_FORMAT = "gausslite-labels/1"
#: the annotation sets shipped with the package, one folder each (``labels.json``, ``objects.json``, ``tasks.json``)
SHIPPED_DIR = Path(__file__).resolve().parent / "labels"
#: shipped set → (dataset layout, the sequence folder's name, or the end of it, as the public download names it)
SHIPPED = {
    "tum_fr1_rpy": ("tum", "rgbd_dataset_freiburg1_rpy"),
    "replica_room0": ("replica", "room0"),
}

__all__ = [
    "LABELS_FORMAT",
    "SHIPPED",
    "SHIPPED_DIR",
    "label_scene",
    "object_box",
    "resolve_annotations",
    "shipped_set_of",
    "surface_box",
    "write_annotations",
]


# ----------------------------------------------------------------------------------------------
# which annotations a sequence uses
# ----------------------------------------------------------------------------------------------
def shipped_set_of(seq_dir: Union[str, Path], layout: str) -> Optional[str]:
    """The shipped annotation set of a public sequence, recognised by its layout and folder name.

    Args:
        seq_dir: the sequence folder (TUM: the folder of ``rgb.txt``; Replica: the folder of ``traj.txt``).
        layout: its layout (``"tum"``, ``"replica"``, …; :func:`gausslite.datasets.detect_layout`).
    Returns:
        The set's name (a key of :data:`SHIPPED`), or None for a sequence GaussLite ships no annotations for.
    """
    name = Path(seq_dir).resolve().name
    for key, (kind, folder) in SHIPPED.items():
        if kind == layout and (name == folder or name.endswith("_" + folder)):
            return key
    return None


def resolve_annotations(seq_dir: Union[str, Path], layout: str, choice: Union[str, Path], current):
    """The annotations a dataset uses under an ``annotations`` choice.

    Args:
        seq_dir: the sequence folder. layout: its layout.
        choice: ``"auto"`` (the files beside the data, else the shipped set of a recognised public sequence, else
            none), ``"beside"`` (the files beside the data only), ``"shipped"`` (the shipped set; an error for a
            sequence without one), or a folder holding ``objects.json`` / ``tasks.json``.
        current: the annotations the loader found beside the data (``SceneAnnotations`` or None).
    Returns:
        ``SceneAnnotations`` or None.
    Raises:
        ValueError: ``"shipped"`` for a sequence GaussLite ships none for, or invalid files.
        FileNotFoundError: a folder without ``objects.json``.
    """
    if choice == "beside":
        return current
    key = shipped_set_of(seq_dir, layout)
    if choice == "auto":
        if current is not None or key is None:
            return current
        return load_annotations(SHIPPED_DIR / key)
    if choice == "shipped":
        if key is None:
            known = ", ".join(f"{k} ({v[0]} folder named {v[1]!r})" for k, v in SHIPPED.items())
            raise ValueError(f"{seq_dir}: GaussLite ships no annotations for this sequence (it ships: {known})")
        return load_annotations(SHIPPED_DIR / key)
    folder = Path(choice)
    if not (folder / "objects.json").is_file():
        raise FileNotFoundError(f"annotations {folder}: no objects.json in that folder")
    return load_annotations(folder)


# ----------------------------------------------------------------------------------------------
# points
# ----------------------------------------------------------------------------------------------
def _frame(dataset, name: str):
    """The dataset's frame named ``name`` (its file stem). Raises KeyError: a frame the dataset lacks."""
    try:
        return dataset[dataset.frame_names.index(name)]
    except ValueError:
        raise KeyError(f"frame {name!r} is not in {dataset.path}") from None


def fused_cloud(dataset, frame_names: Sequence[str], *, pixel_stride: int = 2, voxel_m: float = 0.01,
                max_depth_m: float = 4.0):
    """The depth of the named frames, back-projected at their poses and fused on a voxel grid.

    Args:
        dataset: a posed RGB-D dataset (``frame_names``, ``__getitem__`` giving frames with ``depth`` (H, W) float32
            metres, ``c2w`` (4, 4) camera-to-world, ``intrinsics``).
        frame_names: the frames to fuse, by file name (stem).
        pixel_stride: every ``pixel_stride``-th pixel in each direction. voxel_m: the grid's cell, metres.
        max_depth_m: depth beyond this is dropped (metres).
    Returns:
        ``open3d.geometry.PointCloud`` in the world frame, metres.
    Raises:
        KeyError: a frame name the dataset lacks.
    """
    import open3d as o3d

    from gausslite.camera import backproject

    pts: List[np.ndarray] = []
    for name in frame_names:
        fr = _frame(dataset, name)
        depth = np.where((fr.depth > 0) & (fr.depth < max_depth_m), fr.depth, 0.0).astype(np.float32)
        world = backproject(depth, fr.intrinsics, fr.c2w)
        world = world[::pixel_stride, ::pixel_stride].reshape(-1, 3)
        valid = depth[::pixel_stride, ::pixel_stride].reshape(-1) > 0
        pts.append(world[valid])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts).astype(np.float64)))
    return cloud.voxel_down_sample(voxel_m)


def click_point(dataset, frame_name: str, uv: Sequence[float], window: int = 2) -> np.ndarray:
    """The world point under a pixel: the median depth of a small window around it, back-projected at the pose.

    Args:
        frame_name: the frame (file stem). uv: (u, v) pixel, full-resolution image coordinates.
        window: half-size of the window, pixels.
    Returns:
        (3,) float64 world point, metres.
    Raises:
        KeyError: unknown frame. ValueError: the pixel is outside the image or has no valid depth around it.
    """
    from gausslite.camera import backproject

    fr = _frame(dataset, frame_name)
    u, v = int(round(uv[0])), int(round(uv[1]))
    h, w = fr.depth.shape
    if not (0 <= u < w and 0 <= v < h):
        raise ValueError(f"pixel {uv} is outside frame {frame_name!r} ({w}x{h})")
    patch = fr.depth[max(v - window, 0):v + window + 1, max(u - window, 0):u + window + 1]
    patch = patch[patch > 0]
    if patch.size == 0:
        raise ValueError(f"pixel {uv} of frame {frame_name!r} has no valid depth")
    depth = np.zeros(fr.depth.shape, dtype=np.float64)
    depth[v, u] = np.median(patch)
    return backproject(depth, fr.intrinsics, np.asarray(fr.c2w, dtype=np.float64))[v, u]


def _up_frame(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is ``up`` (world → up-frame coordinates: ``points @ R``)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, up)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up], axis=1)


def _box(points: np.ndarray, up: np.ndarray, z_lo: float, z_hi: float) -> Dict[str, Any]:
    """A gravity-aligned box: the minimum-area rectangle of the points seen from above, from height ``z_lo`` to
    ``z_hi`` (metres along ``up``). Returns ``center``, ``size``, ``rotation`` (world); the box's first axis is its
    longer horizontal side, pointing to +x of the up frame (:func:`_up_frame`), so one box has one description."""
    import cv2

    R = _up_frame(up)
    local = points @ R
    (cx, cy), (sx, sy), ang = cv2.minAreaRect(local[:, :2].astype(np.float32))
    t = np.deg2rad(ang)
    a1, a2 = np.array([np.cos(t), np.sin(t)]), np.array([-np.sin(t), np.cos(t)])
    if sy > sx:
        sx, sy, a1, a2 = sy, sx, a2, -a1
    if a1[0] < 0 or (a1[0] == 0 and a1[1] < 0):
        a1, a2 = -a1, -a2
    rz = np.array([[a1[0], a2[0], 0.0], [a1[1], a2[1], 0.0], [0.0, 0.0, 1.0]])
    center = R @ np.array([cx, cy, (z_lo + z_hi) / 2.0])
    return {"center": center, "size": np.array([sx, sy, z_hi - z_lo]), "rotation": R @ rz}


def _horizontal_plane(points: np.ndarray, up: np.ndarray, dist_m: float) -> Optional[Tuple[float, np.ndarray]]:
    """The most populated horizontal plane of ``points``: the peak of their height histogram (bins of ``dist_m``
    along ``up``), refined to the median height of the points within ``dist_m`` of it. With gravity known, a
    horizontal plane is one height, and the histogram finds it deterministically (RANSAC over three-point samples
    would not). Returns (height along ``up``, inlier mask), or None for fewer than 50 points."""
    if len(points) < 50:
        return None
    h = points @ up
    edges = np.arange(h.min(), h.max() + dist_m, dist_m)
    counts, edges = np.histogram(h, bins=edges if len(edges) > 1 else 1)
    k = int(np.argmax(counts))
    peak = 0.5 * (edges[k] + edges[k + 1])
    height = float(np.median(h[np.abs(h - peak) < dist_m]))
    return height, np.abs(h - height) < dist_m


def _cluster_at(points: np.ndarray, seed_xyz: np.ndarray, eps_m: float, min_points: int = 8) -> np.ndarray:
    """The DBSCAN cluster of ``points`` holding the point nearest ``seed_xyz`` (bool mask)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    labels = np.asarray(pc.cluster_dbscan(eps=eps_m, min_points=min_points))
    near = int(np.argmin(np.linalg.norm(points - seed_xyz, axis=1)))
    if labels[near] < 0:
        return np.zeros(len(points), dtype=bool)
    return labels == labels[near]


def object_box(points: np.ndarray, seed_xyz: np.ndarray, up: np.ndarray, *, radius_m: float = 0.4,
               plane_dist_m: float = 0.012, eps_m: float = 0.02) -> Dict[str, Any]:
    """The box of a thing standing on a surface, from one point on it.

    Within ``radius_m`` of ``seed_xyz`` seen from above, the supporting plane is the most populated horizontal plane
    in the metre below the seed (:func:`_horizontal_plane`); the points above it are clustered (DBSCAN, ``eps_m``) and the cluster holding the seed is boxed,
    gravity-aligned, down to the plane.

    Args:
        points: (N, 3) float64 world points, metres. seed_xyz: (3,) a point on the object. up: (3,) unit up axis.
    Returns:
        ``{"center", "size", "rotation"}`` (world, metres).
    Raises:
        ValueError: no supporting plane below the seed, or no cluster at it.
    """
    offset = points - seed_xyz
    flat = offset - np.outer(offset @ up, up)
    near = points[np.linalg.norm(flat, axis=1) < radius_m]
    h_seed = float(seed_xyz @ up)
    below = near[(near @ up < h_seed - plane_dist_m) & (near @ up > h_seed - 1.0)]
    plane = _horizontal_plane(below, up, plane_dist_m)
    if plane is None:
        raise ValueError(f"no horizontal plane below the point {np.round(seed_xyz, 3).tolist()}")
    h_plane = plane[0]
    above = near[near @ up > h_plane + plane_dist_m]
    mask = _cluster_at(above, seed_xyz, eps_m)
    if mask.sum() < 8:
        raise ValueError(f"no cluster of points above the plane at {np.round(seed_xyz, 3).tolist()}")
    obj = above[mask]
    return _box(obj, up, h_plane, float(np.max(obj @ up)))


def surface_box(points: np.ndarray, seed_xyz: np.ndarray, up: np.ndarray, *, radius_m: float = 1.5,
                plane_dist_m: float = 0.015, eps_m: float = 0.04, thickness_m: Union[float, str] = 0.05,
                height_m: float = 0.0) -> Dict[str, Any]:
    """The box of a horizontal surface, from one point on it.

    The plane is the horizontal plane (:func:`_horizontal_plane`) of the points within ``radius_m`` of the seed and
    within ``3 plane_dist_m`` of its height;
    its inliers are clustered (DBSCAN, ``eps_m``) and the patch holding the seed is boxed, from ``thickness_m`` below
    the plane (``"floor"``: down to the floor, the 1st percentile of the heights of ``points``) to ``height_m`` above.

    Args:
        points: (N, 3) float64 world points, metres. seed_xyz: (3,) a point on the surface. up: (3,) unit up axis.
    Returns:
        ``{"center", "size", "rotation"}`` (world, metres).
    Raises:
        ValueError: no horizontal plane through the seed.
    """
    near = points[np.linalg.norm(points - seed_xyz, axis=1) < radius_m]
    h_seed = float(seed_xyz @ up)
    band = near[np.abs(near @ up - h_seed) < 3 * plane_dist_m]
    plane = _horizontal_plane(band, up, plane_dist_m)
    if plane is None or abs(plane[0] - h_seed) > 3 * plane_dist_m:
        raise ValueError(f"no horizontal plane through the point {np.round(seed_xyz, 3).tolist()}")
    patch = band[plane[1]]
    mask = _cluster_at(patch, seed_xyz, eps_m)
    if mask.sum() < 8:
        raise ValueError(f"no patch of the plane at {np.round(seed_xyz, 3).tolist()}")
    h = plane[0]
    lo = float(np.percentile(points @ up, 1.0)) if thickness_m == "floor" else h - float(thickness_m)
    return _box(patch[mask], up, lo, h + float(height_m))


# ----------------------------------------------------------------------------------------------
# a labels file → objects.json, tasks.json
# ----------------------------------------------------------------------------------------------
def _read_labels(path: Path) -> dict:
    """A labels file, checked (raises ValueError naming the file and the entry)."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e})") from None
    if not isinstance(d, dict) or d.get("format") != LABELS_FORMAT:
        raise ValueError(f"{path}: format must be {LABELS_FORMAT!r}")
    for k in ("up_axis", "fuse_frames", "objects", "tasks"):
        if k not in d:
            raise ValueError(f"{path}: missing {k!r}")
    for o in d["objects"]:
        for k in ("id", "label", "kind", "click"):
            if k not in o:
                raise ValueError(f"{path}: object {o.get('id', '?')}: missing {k!r}")
        if o["kind"] not in ("object", "surface"):
            raise ValueError(f"{path}: object {o['id']}: kind must be 'object' or 'surface', not {o['kind']!r}")
        c = o["click"]
        if not (isinstance(c, dict) and isinstance(c.get("frame"), str) and len(c.get("uv", ())) == 2):
            raise ValueError(f"{path}: object {o['id']}: click must be {{\"frame\": name, \"uv\": [u, v]}}")
    return d


def label_scene(dataset, labels_path: Union[str, Path], progress: bool = True) -> Tuple[dict, dict]:
    """``objects.json`` and ``tasks.json`` of a sequence from a labels file (format: the module's docstring).

    Args:
        dataset: the sequence, full resolution, with its poses (:func:`gausslite.datasets.load_dataset`).
        labels_path: the labels file (``gausslite-labels/1``).
        progress: a progress bar over the objects.
    Returns:
        ``(objects_json, tasks_json)``, the ``gausslite-objects/1`` and ``gausslite-tasks/1`` documents.
    Raises:
        ValueError: an invalid labels file, a click without depth, or an object the method cannot box (the message
            names it). KeyError: a frame the sequence lacks.
    """
    from tqdm import tqdm

    d = _read_labels(Path(labels_path))
    up = parse_up_axis(d["up_axis"])
    cloud = np.asarray(fused_cloud(dataset, d["fuse_frames"], pixel_stride=int(d.get("pixel_stride", 2)),
                                   voxel_m=float(d.get("voxel_m", 0.01))).points)
    objects = []
    for o in tqdm(d["objects"], desc="objects", disable=not progress):
        seed = click_point(dataset, o["click"]["frame"], o["click"]["uv"])
        opts = {k: o[k] for k in ("radius_m", "eps_m", "plane_dist_m", "thickness_m", "height_m") if k in o}
        try:
            box = (object_box if o["kind"] == "object" else surface_box)(cloud, seed, up, **opts)
        except ValueError as e:
            raise ValueError(f"object {o['id']} ({o['label']}): {e}") from None
        objects.append({"id": int(o["id"]), "label": o["label"], "synonyms": list(o.get("synonyms", [])),
                        "center": np.round(box["center"], 4).tolist(), "size": np.round(box["size"], 4).tolist(),
                        "rotation": np.round(box["rotation"], 6).tolist(),
                        "mask_margin_m": float(o.get("mask_margin_m", 0.02)), "notes": o.get("notes", "")})
        log.info("object %s (%s): size %s m", o["id"], o["label"], np.round(box["size"], 3).tolist())
    objects_json = {"format": OBJECTS_FORMAT, "frame": "world", "units": "m", "up_axis": d["up_axis"],
                    "objects": objects}
    return objects_json, {"format": TASKS_FORMAT, "tasks": d["tasks"]}


def write_annotations(out: Union[str, Path], objects_json: dict, tasks_json: dict) -> Tuple[Path, Path]:
    """Write ``objects.json`` and ``tasks.json`` into the folder ``out`` (made if missing), then read them back with
    the loader's checks. Returns their paths. Raises ValueError: documents the loader rejects."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = out / "objects.json", out / "tasks.json"
    for p, doc in zip(paths, (objects_json, tasks_json)):
        p.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    load_annotations(out)
    return paths
