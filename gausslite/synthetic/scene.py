"""Procedural description of the default synthetic room: geometry, materials, labels and tasks.

World frame: metres, up axis +z, floor at z = 0. The room spans ``x in [-3, 3]``, ``y in [-2.5, 2.5]``,
``z in [0, 2.6]``. Every object is a union of primitives (oriented boxes and cylinders) that are
axis-aligned in the object's own gravity-aligned frame, so the object's annotation box (its
oriented bounding box, rotated only about +z) is exact. Small objects resting on a surface have
their annotation box bottom raised :data:`SUPPORT_CLEARANCE_M` above the surface, like the real
annotations, so the supporting surface is not in their mask.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from gausslite.synthetic.textures import Material

#: Version string written to ``scene.json``; bump when the generated content changes.
GENERATOR_VERSION = "gausslite-synthetic/1.0"
#: Gap between a supporting surface and the bottom of a resting object's annotation box (metres).
SUPPORT_CLEARANCE_M = 0.022
#: ``mask_margin_m`` written for every object (metres).
MASK_MARGIN_M = 0.02

# Room surface ids used in the object-id buffer (object ids are >= 1).
FLOOR_ID, CEILING_ID = -1, -2
WALL_XMIN_ID, WALL_XMAX_ID, WALL_YMIN_ID, WALL_YMAX_ID = -3, -4, -5, -6


def rot_z(yaw: float) -> np.ndarray:
    """(3, 3) float64 rotation about +z by ``yaw`` radians (columns = rotated x, y, z axes)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)


@dataclass(frozen=True)
class Primitive:
    """A solid primitive in world coordinates.

    Attributes:
        shape: ``"box"`` or ``"cylinder"`` (the cylinder axis is the third local axis).
        center: (3,) float64 world centre (metres).
        half: (3,) float64 half extents along the local axes (metres); for a cylinder
            ``(radius, radius, half_height)``.
        rotation: (3, 3) float64 local-to-world rotation (columns = local axes in world).
        material: surface material.
        object_id: id of the owning object (>= 1).
        uv_offset: (2,) offset added to the texture coordinates (metres), decorrelates patterns.
    """

    shape: str
    center: np.ndarray
    half: np.ndarray
    rotation: np.ndarray
    material: Material
    object_id: int
    uv_offset: Tuple[float, float] = (0.0, 0.0)


@dataclass
class SceneObject:
    """A labelled object: primitives plus its annotation box.

    Attributes:
        id: object id (>= 1), also its value in the renderer's id buffer.
        label, synonyms, notes: names and description written to ``objects.json``.
        center: (3,) float64 annotation box centre (world, metres).
        size: (3,) float64 full box extent along its axes (metres).
        rotation: (3, 3) float64 box-to-world rotation (rotation about +z only).
        hull_center, hull_half: (3,) the unclipped bounding box of all primitives (same rotation),
            used by the ray caster for culling.
        primitives: the object's primitives.
        obstacle: furniture standing on the floor (gets the synonym "obstacle").
    """

    id: int
    label: str
    synonyms: List[str]
    notes: str
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    hull_center: np.ndarray
    hull_half: np.ndarray
    primitives: List[Primitive]
    obstacle: bool = False

    def to_json(self) -> dict:
        """The ``objects.json`` entry (floats rounded to 1e-6)."""

        def r(a: np.ndarray) -> list:
            return (np.round(np.asarray(a, dtype=np.float64), 6) + 0.0).tolist()

        return {
            "id": int(self.id), "label": self.label, "synonyms": list(self.synonyms),
            "center": r(self.center), "size": r(self.size), "rotation": r(self.rotation),
            "mask_margin_m": MASK_MARGIN_M, "notes": self.notes,
        }


class ObjectBuilder:
    """Accumulates primitives in an object's local frame (origin ``pos``, rotated by ``yaw`` about +z).

    Local coordinates are metres; primitives are axis-aligned in the local frame.
    """

    def __init__(self, object_id: int, pos: Sequence[float], yaw: float) -> None:
        self.id = int(object_id)
        self.pos = np.asarray(pos, dtype=np.float64)
        self.R = rot_z(yaw)
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.prims: List[Primitive] = []

    def _add(self, shape: str, c: np.ndarray, half: np.ndarray, mat: Material) -> None:
        ext = half.copy()
        self.lo = np.minimum(self.lo, c - ext)
        self.hi = np.maximum(self.hi, c + ext)
        off = (float(len(self.prims)) * 0.37 + self.id * 1.13, float(len(self.prims)) * 0.21)
        self.prims.append(Primitive(shape, self.pos + self.R @ c, half, self.R.copy(), mat, self.id, off))

    def box(self, center: Sequence[float], size: Sequence[float], mat: Material) -> None:
        """Add a box with local ``center`` and full ``size`` (metres)."""
        self._add("box", np.asarray(center, float), 0.5 * np.asarray(size, float), mat)

    def cylinder(self, base: Sequence[float], radius: float, height: float, mat: Material) -> None:
        """Add a vertical cylinder whose bottom-cap centre is ``base`` (local, metres)."""
        b = np.asarray(base, float)
        self._add("cylinder", b + [0.0, 0.0, 0.5 * height], np.array([radius, radius, 0.5 * height]), mat)

    def build(self, label: str, synonyms: Sequence[str], notes: str, obstacle: bool = False,
              clearance: float = 0.0) -> SceneObject:
        """Finish the object. ``clearance`` (metres) raises the annotation box bottom above the
        local z of the lowest primitive (for objects resting on a surface)."""
        lo = self.lo.copy()
        lo[2] += clearance
        c_box = 0.5 * (lo + self.hi)
        c_hull = 0.5 * (self.lo + self.hi)
        syn = list(synonyms) + (["obstacle"] if obstacle and "obstacle" not in synonyms else [])
        return SceneObject(
            id=self.id, label=label, synonyms=syn, notes=notes,
            center=self.pos + self.R @ c_box, size=self.hi - lo, rotation=self.R.copy(),
            hull_center=self.pos + self.R @ c_hull, hull_half=0.5 * (self.hi - self.lo) + 1e-4,
            primitives=list(self.prims), obstacle=obstacle,
        )


@dataclass(frozen=True)
class Decal:
    """A framed rectangle (poster, painting, rug) drawn on a room surface.

    Attributes:
        surface_id: room surface id (``FLOOR_ID``, ``WALL_*_ID`` ...).
        u0, u1, v0, v1: extent in that surface's (u, v) coordinates (metres).
        material: decal material.
        frame_color: RGB of a 2.5 cm border, or None for no border.
    """

    surface_id: int
    u0: float
    u1: float
    v0: float
    v1: float
    material: Material
    frame_color: Optional[Tuple[float, float, float]] = None


@dataclass
class Room:
    """Axis-aligned room shell seen from inside.

    Attributes:
        lo, hi: (3,) float64 room corners (metres).
        materials: surface id -> material.
        decals: decals drawn on the surfaces.
        baseboard: (height m, RGB) skirting band at the bottom of the walls.
    """

    lo: np.ndarray
    hi: np.ndarray
    materials: Dict[int, Material]
    decals: List[Decal] = field(default_factory=list)
    baseboard: Tuple[float, Tuple[float, float, float]] = (0.08, (0.93, 0.92, 0.88))


@dataclass
class Task:
    """A task with its expected graph and ground-truth ROI object ids (``tasks.json`` entry)."""

    id: str
    text: str
    targets: List[str]
    anchors: List[str]
    relations: List[Tuple[str, str, str]]  # (predicate, target, anchor)
    roi_object_ids: List[int]

    def to_json(self) -> dict:
        """The ``tasks.json`` entry."""
        return {
            "id": self.id, "text": self.text,
            "graph": {
                "targets": list(self.targets), "anchors": list(self.anchors),
                "relations": [{"predicate": p, "target": t, "anchor": a} for p, t, a in self.relations],
            },
            "roi_object_ids": [int(i) for i in self.roi_object_ids],
        }


@dataclass
class Scene:
    """The whole synthetic scene.

    Attributes:
        seed: generator seed.
        room: the room shell.
        objects: labelled objects (ids 1..N).
        tasks: tasks over the objects.
        light: (3,) float64 point light position (metres) for Lambertian shading.
        ambient: ambient term in [0, 1]; shading = ambient + (1 - ambient) * max(0, n.l).
    """

    seed: int
    room: Room
    objects: List[SceneObject]
    tasks: List[Task]
    light: np.ndarray
    ambient: float = 0.42

    def object(self, object_id: int) -> SceneObject:
        """The object with ``object_id``. Raises KeyError when absent."""
        for o in self.objects:
            if o.id == object_id:
                return o
        raise KeyError(f"no object with id {object_id}")

    def objects_json(self) -> dict:
        """``objects.json`` content (format ``gausslite-objects/1``)."""
        return {"format": "gausslite-objects/1", "frame": "world", "units": "m", "up_axis": "+z",
                "objects": [o.to_json() for o in self.objects]}

    def tasks_json(self) -> dict:
        """``tasks.json`` content (format ``gausslite-tasks/1``)."""
        return {"format": "gausslite-tasks/1", "tasks": [t.to_json() for t in self.tasks]}


def _jitter_color(rng: np.random.Generator, rgb: Sequence[float], dh: float = 0.03, dv: float = 0.08) -> Tuple[float, float, float]:
    h, s, v = colorsys.rgb_to_hsv(*[float(x) for x in rgb])
    h = (h + rng.uniform(-dh, dh)) % 1.0
    v = float(np.clip(v * (1.0 + rng.uniform(-dv, dv)), 0.0, 1.0))
    return tuple(float(x) for x in colorsys.hsv_to_rgb(h, s, v))  # type: ignore[return-value]


def _room_shell(jc, tex_seed) -> Room:
    """The room's walls, floor and ceiling with their decals (``jc``: seeded colour jitter, ``tex_seed``: seeded
    texture seed; both draw from the scene's generator, so the call order is part of the scene)."""
    room = Room(
        lo=np.array([-3.0, -2.5, 0.0]), hi=np.array([3.0, 2.5, 2.6]),
        materials={
            FLOOR_ID: Material("planks", jc((0.62, 0.45, 0.29)), jc((0.40, 0.27, 0.16)), 0.16, tex_seed()),
            CEILING_ID: Material("tiles", (0.93, 0.93, 0.90), (0.70, 0.70, 0.68), 0.6, tex_seed()),
            WALL_XMIN_ID: Material("diamond", jc((0.82, 0.78, 0.66)), jc((0.66, 0.70, 0.62)), 0.09, tex_seed()),
            WALL_XMAX_ID: Material("diamond", jc((0.74, 0.80, 0.84)), jc((0.60, 0.66, 0.74)), 0.11, tex_seed()),
            WALL_YMIN_ID: Material("noise", jc((0.85, 0.83, 0.78)), jc((0.70, 0.68, 0.62)), 0.3, tex_seed()),
            WALL_YMAX_ID: Material("stripes", jc((0.86, 0.80, 0.70)), jc((0.72, 0.55, 0.45)), 0.12, tex_seed()),
        },
    )
    room.decals.extend([
        Decal(FLOOR_ID, -1.3, 1.3, -0.5, 1.5,
              Material("checker", jc((0.55, 0.16, 0.14)), jc((0.90, 0.80, 0.58)), 0.09, tex_seed()), (0.2, 0.12, 0.1)),
        Decal(WALL_YMAX_ID, -2.0, -0.6, 0.95, 1.85,
              Material("text", (0.96, 0.95, 0.90), (0.08, 0.08, 0.12), 0.07, tex_seed()), (0.15, 0.12, 0.10)),
        Decal(WALL_XMAX_ID, -1.4, 0.2, 0.95, 1.95,
              Material("painting", jc((0.20, 0.45, 0.75)), jc((0.95, 0.70, 0.20)), 0.25, tex_seed()), (0.35, 0.25, 0.12)),
        Decal(WALL_XMIN_ID, -1.8, -0.3, 0.9, 1.75,
              Material("text", (0.97, 0.97, 0.97), (0.10, 0.20, 0.55), 0.08, tex_seed()), (0.6, 0.6, 0.62)),
        Decal(WALL_XMIN_ID, 0.4, 2.2, 2.0, 2.4,
              Material("checker", jc((0.20, 0.30, 0.25)), jc((0.85, 0.85, 0.80)), 0.05, tex_seed()), (0.1, 0.1, 0.1)),
    ])
    return room


def _desk(jc, tex_seed, desk_pos: np.ndarray, desk_yaw: float, top_z: float) -> Tuple[SceneObject, Material]:
    """Object 1, the desk (label "desk", synonym "table") at ``desk_pos`` (m, world), yawed ``desk_yaw`` (rad), its
    top at ``top_z`` (m). Returns the desk and its leg metal, which the door and the trash can reuse."""
    wood_top = Material("wood", jc((0.70, 0.50, 0.30)), jc((0.50, 0.32, 0.18)), 0.025, tex_seed())
    metal = Material("brushed", (0.55, 0.56, 0.58), (0.80, 0.81, 0.83), 0.05, tex_seed())
    drawer = Material("fabric", jc((0.88, 0.88, 0.84)), jc((0.70, 0.70, 0.66)), 0.012, tex_seed())
    b = ObjectBuilder(1, desk_pos, desk_yaw)
    b.box([0.0, 0.0, top_z - 0.015], [1.4, 0.7, 0.03], wood_top)
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.box([sx * 0.65, sy * 0.3, 0.36], [0.05, 0.05, 0.72], metal)
    b.box([0.42, 0.0, 0.595], [0.42, 0.6, 0.25], drawer)
    b.box([0.42, -0.305, 0.595], [0.16, 0.012, 0.03], metal)  # drawer handle
    b.box([-0.1, 0.32, 0.52], [1.1, 0.02, 0.36], wood_top)  # modesty panel
    desk = b.build("desk", ["table", "work table", "writing desk", "office desk"],
                   "wooden desk with metal legs and a drawer unit in the middle of the room", obstacle=True)
    return desk, metal


def _desk_items(rng: np.random.Generator, jc, tex_seed, on_desk, desk_yaw: float) -> List[SceneObject]:
    """Objects 2 (mug), 3 (box) and 4 (book) on the desk (``on_desk``: desk-local xy → world point on its top),
    their placement and yaw jittered by ``rng``."""
    objs: List[SceneObject] = []
    j = rng.uniform(-0.04, 0.04, size=(3, 2))
    b = ObjectBuilder(2, on_desk([-0.38 + j[0, 0], 0.08 + j[0, 1]]), desk_yaw + rng.uniform(0, 2 * np.pi))
    mug = Material("stripes", jc((0.85, 0.20, 0.18)), (0.95, 0.93, 0.88), 0.018, tex_seed())
    b.cylinder([0.0, 0.0, 0.0], 0.045, 0.10, mug)
    b.box([0.056, 0.0, 0.05], [0.03, 0.012, 0.06], mug)
    b.cylinder([0.0, 0.0, 0.094], 0.039, 0.007, Material("noise", (0.25, 0.14, 0.08), (0.12, 0.06, 0.03), 0.02, tex_seed()))
    objs.append(b.build("mug", ["cup", "coffee mug", "object"], "red striped coffee mug on the left of the desk",
                        clearance=SUPPORT_CLEARANCE_M))

    b = ObjectBuilder(3, on_desk([0.02 + j[1, 0], -0.1 + j[1, 1]]), desk_yaw + np.deg2rad(25.0 + rng.uniform(-8, 8)))
    carton = Material("checker", jc((0.78, 0.62, 0.38)), jc((0.25, 0.40, 0.70)), 0.02, tex_seed())
    b.box([0.0, 0.0, 0.045], [0.16, 0.12, 0.09], carton)
    b.box([0.0, 0.0, 0.0455], [0.163, 0.03, 0.091], Material("brushed", (0.75, 0.70, 0.55), (0.85, 0.80, 0.65), 0.05, tex_seed()))
    objs.append(b.build("box", ["small box", "carton", "package", "object"],
                        "small printed cardboard box with a tape band in the middle of the desk",
                        clearance=SUPPORT_CLEARANCE_M))

    b = ObjectBuilder(4, on_desk([0.36 + j[2, 0], 0.12 + j[2, 1]]), desk_yaw + np.deg2rad(-15.0 + rng.uniform(-8, 8)))
    b.box([0.0, 0.0, 0.018], [0.24, 0.17, 0.036], Material("text", jc((0.30, 0.55, 0.35)), (0.95, 0.92, 0.60), 0.02, tex_seed()))
    b.box([0.0, 0.0, 0.0375], [0.18, 0.11, 0.003], Material("text", (0.96, 0.95, 0.90), (0.1, 0.1, 0.1), 0.012, tex_seed()))
    objs.append(b.build("book", ["notebook", "object"], "green hardcover book with a paper label, on the right of the desk",
                        clearance=SUPPORT_CLEARANCE_M))
    return objs


def _chairs(rng: np.random.Generator, jc, tex_seed, desk_pos: np.ndarray, desk_yaw: float) -> List[SceneObject]:
    """Objects 5 (blue chair at the desk's left end, the one closest to the table) and 6 (yellow chair near the
    right wall), their yaw jittered by ``rng``."""

    def chair(oid: int, pos: Sequence[float], yaw: float, seat_c: Tuple[float, float, float]) -> ObjectBuilder:
        cb = ObjectBuilder(oid, pos, yaw)
        legs = Material("wood", jc((0.45, 0.30, 0.18)), jc((0.30, 0.19, 0.10)), 0.012, tex_seed())
        seat = Material("fabric", jc(seat_c), tuple(0.6 * np.asarray(seat_c)), 0.008, tex_seed())
        cb.box([0.0, 0.0, 0.45], [0.45, 0.45, 0.04], seat)
        for sx in (-1, 1):
            for sy in (-1, 1):
                cb.box([sx * 0.195, sy * 0.195, 0.215], [0.04, 0.04, 0.43], legs)
            cb.box([-0.205, sx * 0.195, 0.695], [0.04, 0.04, 0.45], legs)
        cb.box([-0.205, 0.0, 0.79], [0.03, 0.35, 0.22], seat)
        return cb

    near_local = rot_z(desk_yaw) @ np.array([-0.98, 0.05, 0.0])
    b = chair(5, desk_pos + near_local, desk_yaw + np.deg2rad(rng.uniform(-6, 6)), (0.20, 0.35, 0.65))
    near = b.build("chair", ["seat", "desk chair", "wooden chair"],
                   "blue chair at the left end of the desk, the chair closest to the table", obstacle=True)
    b = chair(6, [2.2, 1.55, 0.0], np.deg2rad(200.0 + rng.uniform(-8, 8)), (0.75, 0.55, 0.15))
    far = b.build("chair", ["seat", "wooden chair"],
                  "yellow chair near the right wall, about 2 m from the desk", obstacle=True)
    return [near, far]


def _door_and_trash_can(jc, tex_seed, metal: Material) -> List[SceneObject]:
    """Objects 7 (door in the +y wall) and 8 (trash can next to it); ``metal``: the desk's leg metal (handle, rim)."""
    b = ObjectBuilder(7, [1.3, 2.5, 0.0], 0.0)
    panel = Material("wood", jc((0.55, 0.36, 0.22)), jc((0.38, 0.23, 0.13)), 0.03, tex_seed())
    frame_m = Material("solid", (0.92, 0.91, 0.87), scale=0.2, seed=tex_seed())
    b.box([0.0, -0.02, 1.0], [0.86, 0.04, 2.0], panel)
    b.box([-0.46, -0.03, 1.03], [0.06, 0.06, 2.06], frame_m)
    b.box([0.46, -0.03, 1.03], [0.06, 0.06, 2.06], frame_m)
    b.box([0.0, -0.03, 2.03], [0.98, 0.06, 0.06], frame_m)
    b.box([0.31, -0.065, 1.0], [0.13, 0.05, 0.025], metal)
    b.box([0.0, -0.045, 1.45], [0.5, 0.01, 0.6], Material("text", (0.95, 0.95, 0.95), (0.6, 0.1, 0.1), 0.07, tex_seed()))
    door = b.build("door", ["doorway", "entrance", "exit"],
                   "wooden door with a white frame in the wall opposite the cameras")

    b = ObjectBuilder(8, [0.45, 2.22, 0.0], 0.0)
    can = Material("stripes", jc((0.25, 0.45, 0.30)), jc((0.15, 0.30, 0.20)), 0.03, tex_seed())
    b.cylinder([0.0, 0.0, 0.0], 0.16, 0.41, can)
    b.cylinder([0.0, 0.0, 0.41], 0.17, 0.03, metal)
    b.cylinder([0.0, 0.0, 0.44], 0.14, 0.004, Material("noise", (0.15, 0.15, 0.15), (0.4, 0.4, 0.38), 0.03, tex_seed()))
    trash = b.build("trash can", ["bin", "trash bin", "waste basket", "garbage can", "dustbin"],
                    "green cylindrical trash can beside the door", obstacle=True)
    return [door, trash]


def _shelf(rng: np.random.Generator, jc, tex_seed) -> SceneObject:
    """Object 9, the bookshelf against the -x wall, its lower three shelves filled with books whose widths,
    heights, depths and colours ``rng`` draws."""
    b = ObjectBuilder(9, [-2.83, 1.3, 0.0], np.deg2rad(90.0))  # local -y faces +x (into the room)
    board = Material("wood", jc((0.78, 0.66, 0.48)), jc((0.60, 0.48, 0.32)), 0.02, tex_seed())
    W, D, Hs = 1.0, 0.34, 1.8
    for sx in (-1, 1):
        b.box([sx * (W / 2 - 0.01), 0.0, Hs / 2], [0.02, D, Hs], board)
    b.box([0.0, D / 2 - 0.005, Hs / 2], [W - 0.04, 0.01, Hs], Material("noise", (0.55, 0.47, 0.35), (0.45, 0.37, 0.26), 0.1, tex_seed()))
    levels = [0.0, 0.44, 0.88, 1.32, 1.78]
    for z in levels:
        b.box([0.0, 0.0, z + 0.01], [W - 0.04, D - 0.01, 0.02], board)
    for z in levels[:3]:
        x = -W / 2 + 0.04
        while True:
            wbk = float(rng.uniform(0.025, 0.06))
            if x + wbk > W / 2 - 0.06:
                break
            hb = float(rng.uniform(0.18, 0.34))
            db = float(rng.uniform(0.18, 0.26))
            col = colorsys.hsv_to_rgb(float(rng.uniform(0, 1)), float(rng.uniform(0.4, 0.8)), float(rng.uniform(0.35, 0.85)))
            kind = "text" if rng.uniform() < 0.5 else "stripes"
            mat = Material(kind, tuple(col), (0.95, 0.9, 0.7), 0.012, tex_seed())
            b.box([x + wbk / 2, -D / 2 + 0.01 + db / 2, z + 0.02 + hb / 2], [wbk, db, hb], mat)
            x += wbk + float(rng.uniform(0.0, 0.012))
    return b.build("shelf", ["shelves", "bookshelf", "bookcase", "shelving unit"],
                   "wooden bookshelf with books on its lower three shelves against the left wall", obstacle=True)


def _default_tasks(objs: List[SceneObject]) -> List[Task]:
    """The default scene's six tasks over ``objs`` (ids 1–9 as :func:`build_default_scene` numbers them)."""
    obstacles = [o.id for o in objs if o.obstacle]
    return [
        Task("synth-pick-object", "Prepare to pick up the object on the desk", ["object"], ["desk"],
             [("on", "object", "desk")], [2, 3, 4, 1]),
        Task("synth-pick-mug", "Prepare to pick up the mug on the desk", ["mug"], ["desk"],
             [("on", "mug", "desk")], [2, 1]),
        Task("synth-find-chair", "Identify the chair closest to the table", ["chair"], ["table"],
             [("near", "chair", "table")], [5, 1]),
        Task("synth-nav-door", "Locate all obstacles in the scene and find a path to the door", ["obstacle", "door"], [],
             [], sorted(obstacles) + [7]),
        Task("synth-map-chairs", "Map the chairs", ["chair"], [], [], [5, 6]),
        Task("synth-find-trash", "Find the trash can next to the door", ["trash can"], ["door"],
             [("near", "trash can", "door")], [8, 7]),
    ]


def build_default_scene(seed: int = 0) -> Scene:
    """Build the default room for ``seed``.

    The layout (desk in the middle, chairs, door and trash can on the +y wall, shelves on the -x
    wall) is fixed; the seed jitters colours, texture seeds, small-object placement on the desk,
    chair yaw and the books on the shelves by small amounts, so every task stays valid. The parts are
    built in a fixed order from one generator, so equal seeds give identical scenes.

    Args:
        seed: any integer; equal seeds give identical scenes.

    Returns:
        The :class:`Scene` (9 objects, 6 tasks).
    """
    rng = np.random.default_rng(int(seed))
    tex_seed = lambda: int(rng.integers(0, 2**20))  # noqa: E731
    jc = lambda c: _jitter_color(rng, c)  # noqa: E731

    room = _room_shell(jc, tex_seed)
    desk_pos, desk_yaw, top_z = np.array([-0.2, 0.55, 0.0]), np.deg2rad(8.0), 0.75
    desk, metal = _desk(jc, tex_seed, desk_pos, desk_yaw, top_z)
    Rd = rot_z(desk_yaw)

    def on_desk(local_xy: Sequence[float]) -> np.ndarray:
        return desk_pos + Rd @ np.array([local_xy[0], local_xy[1], top_z])

    objs: List[SceneObject] = [desk]
    objs += _desk_items(rng, jc, tex_seed, on_desk, desk_yaw)
    objs += _chairs(rng, jc, tex_seed, desk_pos, desk_yaw)
    objs += _door_and_trash_can(jc, tex_seed, metal)
    objs.append(_shelf(rng, jc, tex_seed))
    return Scene(seed=int(seed), room=room, objects=objs, tasks=_default_tasks(objs), light=np.array([0.4, 0.2, 2.35]))
