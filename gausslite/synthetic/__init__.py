"""Procedural synthetic two-robot RGB-D scene with exact object boxes and tasks.

``make_scene(out_dir, seed=0, width=320, height=240, frames=30)`` renders the default room (desk with
a mug, a box and a book, two chairs, a door, a trash can and shelves) from two robot trajectories
and writes it in the Replica / NICE-SLAM layout with ``objects.json``, ``tasks.json`` and
``scene.json``. The pieces are public for tests and tools: :func:`build_default_scene` (geometry,
labels, tasks), :func:`render` (numpy ray caster: colour, depth, object-id buffer, normals),
:func:`make_trajectories` (camera poses: arcs, a circle around the room, a hand-held walk), :func:`mask_rule` (the
annotation mask rule) and the optional sensor error model (:mod:`gausslite.synthetic.sensor`:
``make_scene(..., sensor_noise="realistic")``, or ``"tum"``: the Kinect v1 of TUM RGB-D fr1 as measured, with the
structured-light depth effects of :mod:`gausslite.synthetic.kinect`).
"""

from gausslite.synthetic.raycast import RenderResult, camera_rays, render
from gausslite.synthetic.scene import (
    CEILING_ID, FLOOR_ID, GENERATOR_VERSION, MASK_MARGIN_M, SUPPORT_CLEARANCE_M, WALL_XMAX_ID, WALL_XMIN_ID,
    WALL_YMAX_ID, WALL_YMIN_ID, Decal, ObjectBuilder, Primitive, Room, Scene, SceneObject, Task,
    build_default_scene, rot_z,
)
from gausslite.synthetic.textures import Material, shade_material
from gausslite.synthetic.sensor import (
    SENSOR_NOISE, TUM_FR1, SensorErrorModel, pose_at, sensor_intrinsics, sensor_model,
)
from gausslite.synthetic.trajectories import AGENTS, TRAJECTORIES, WALK_FPS, WALK_PATH_M, look_at, make_trajectories
from gausslite.synthetic.writer import DEPTH_SCALE, default_intrinsics, make_scene, mask_rule, quantize_depth

__all__ = [
    "AGENTS", "CEILING_ID", "DEPTH_SCALE", "Decal", "FLOOR_ID", "GENERATOR_VERSION", "MASK_MARGIN_M", "Material",
    "ObjectBuilder", "Primitive", "RenderResult", "Room", "SENSOR_NOISE", "SUPPORT_CLEARANCE_M", "Scene",
    "SceneObject", "SensorErrorModel", "TRAJECTORIES", "TUM_FR1", "Task", "WALK_FPS", "WALK_PATH_M",
    "WALL_XMAX_ID", "WALL_XMIN_ID", "WALL_YMAX_ID", "WALL_YMIN_ID", "build_default_scene", "camera_rays",
    "default_intrinsics", "look_at", "make_scene", "make_trajectories", "mask_rule", "pose_at", "quantize_depth",
    "render", "rot_z", "sensor_intrinsics", "sensor_model", "shade_material",
]
