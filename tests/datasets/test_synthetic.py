"""Tests of the procedural synthetic scene (gausslite.synthetic) and the make-scene CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gausslite.camera import Intrinsics, backproject, check_rigid
from gausslite.synthetic import (
    AGENTS, DEPTH_SCALE, FLOOR_ID, WALL_XMIN_ID, WALL_YMAX_ID, Material, build_default_scene, default_intrinsics,
    look_at, make_scene, make_trajectories, mask_rule, quantize_depth, render,
)
from gausslite.synthetic.textures import box_wave

W, H, N = 64, 48, 6
SEED = 3


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "scene"
    summary = make_scene(out, seed=SEED, width=W, height=H, frames=N, progress=False)
    assert summary["out_dir"] == str(out)
    return out


def _read_json(p: Path) -> dict:
    return json.loads(p.read_text())


def _read_agent(d: Path, i: int):
    rgb = cv2.imread(str(d / "results" / f"frame{i:06d}.jpg"), cv2.IMREAD_COLOR)
    depth = cv2.imread(str(d / "results" / f"depth{i:06d}.png"), cv2.IMREAD_UNCHANGED)
    return rgb, depth


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_and_formats(scene_dir: Path) -> None:
    cam = _read_json(scene_dir / "cam_params.json")["camera"]
    assert (cam["w"], cam["h"], cam["scale"]) == (W, H, 6553.5)
    assert cam["fx"] > 0 and cam["fy"] > 0
    objs = _read_json(scene_dir / "objects.json")
    tasks = _read_json(scene_dir / "tasks.json")
    assert objs["format"] == "gausslite-objects/1" and objs["up_axis"] == "+z"
    assert tasks["format"] == "gausslite-tasks/1"
    assert len(objs["objects"]) >= 9 and len(tasks["tasks"]) >= 5
    summary = _read_json(scene_dir / "scene.json")
    assert summary["seed"] == SEED and summary["frames_per_agent"] == N
    assert (summary["width"], summary["height"]) == (W, H)
    for agent in AGENTS:
        d = scene_dir / agent
        traj = np.loadtxt(d / "traj.txt")
        assert traj.shape == (N, 16)
        for row in traj:
            check_rigid(row.reshape(4, 4))
        for i in range(N):
            rgb, depth = _read_agent(d, i)
            assert rgb is not None and rgb.shape == (H, W, 3)
            assert depth is not None and depth.dtype == np.uint16 and depth.shape == (H, W)
            assert rgb.std() > 20  # textured, not blank
        assert not (d / "results" / f"frame{N:06d}.jpg").exists()
        assert set(summary["roi_fraction_mean"][agent]) == {t["id"] for t in tasks["tasks"]}


def test_deterministic_bytes(scene_dir: Path, tmp_path: Path) -> None:
    make_scene(tmp_path / "again", seed=SEED, width=W, height=H, frames=N, progress=False)
    a, b = _files(scene_dir), _files(tmp_path / "again")
    assert a.keys() == b.keys() and len(a) == 4 + 2 * (1 + 2 * N)
    for k in a:
        assert a[k] == b[k], f"{k} differs between two runs with the same seed"
    make_scene(tmp_path / "other", seed=SEED + 1, width=W, height=H, frames=N, progress=False)
    c = _files(tmp_path / "other")
    assert c["agent_a/results/frame000000.jpg"] != a["agent_a/results/frame000000.jpg"]


def test_robots_rendered_in_processes_write_the_same_bytes_as_in_threads(scene_dir: Path, tmp_path: Path,
                                                                        monkeypatch) -> None:
    """Above ``PROCESS_PIXELS`` each robot renders in a Python process of its own; the files are the threads' byte for
    byte (each robot's noise stream is its own), with sensor noise too, and the progress bar counts every frame."""
    import gausslite.synthetic.writer as writer

    threads_noisy = tmp_path / "threads_noisy"
    make_scene(threads_noisy, seed=SEED, width=W, height=H, frames=N, progress=False, sensor_noise="realistic")
    counted = []
    real_tqdm = writer.tqdm

    def counting_tqdm(*a, **k):
        bar = real_tqdm(*a, **k)
        update = bar.update
        bar.update = lambda n=1: (counted.append(n), update(n))[1]
        return bar

    monkeypatch.setattr(writer, "PROCESS_PIXELS", 1)
    monkeypatch.setattr(writer, "tqdm", counting_tqdm)
    if (writer.os.cpu_count() or 1) < 2:
        monkeypatch.setattr(writer.os, "cpu_count", lambda: 2)
    calls = []
    real = writer._render_in_processes
    monkeypatch.setattr(writer, "_render_in_processes", lambda jobs, bar: calls.append(len(jobs)) or real(jobs, bar))
    summary = make_scene(tmp_path / "procs", seed=SEED, width=W, height=H, frames=N, progress=False)
    assert calls == [2] and sum(counted) == 2 * N
    assert _files(tmp_path / "procs") == _files(scene_dir)
    assert summary["roi_fraction"] == _read_json(scene_dir / "scene.json")["roi_fraction_mean"]
    make_scene(tmp_path / "procs_noisy", seed=SEED, width=W, height=H, frames=N, progress=False,
               sensor_noise="realistic")
    assert calls == [2, 2] and _files(tmp_path / "procs_noisy") == _files(threads_noisy)


def test_a_failed_rendering_process_is_an_error_naming_the_robot(tmp_path: Path, monkeypatch) -> None:
    import gausslite.synthetic.writer as writer

    job = (str(tmp_path / "x"), "agent_a", SEED, N, "no_such_trajectory", default_intrinsics(W, H), "none", 30.0)
    with pytest.raises(RuntimeError, match=r"rendering agent_a failed \(exit 1\).*no_such_trajectory"):
        writer._render_in_processes([job], writer.tqdm(disable=True))


def test_the_texture_hash_is_the_64_bit_formula_modulo_2_32() -> None:
    """hash2 in uint32 arithmetic equals its 64-bit statement (every product and sum taken modulo 2**32), for
    negative and large lattice coordinates alike."""
    from gausslite.synthetic.textures import hash2

    def hash64(ix, iy, seed):
        x = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263
             + (seed % 1000003) * 1442695041) & 0xFFFFFFFF
        x = ((x ^ (x >> 13)) * 1274126177) & 0xFFFFFFFF
        x = ((x ^ (x >> 16)) * 2246822519) & 0xFFFFFFFF
        return (x ^ (x >> 15)).astype(np.float64) / 4294967296.0

    rng = np.random.default_rng(0)
    for seed in (0, 7, 7919 * 3 + 11, 123456789):
        ix = np.concatenate([rng.integers(-2**30, 2**30, 20000), [-2**30, -1, 0, 1, 2**30 - 1]])
        iy = np.concatenate([rng.integers(-2**30, 2**30, 20000), [2**30 - 1, 0, -1, 1, -2**30]])
        h = hash2(ix, iy, seed)
        assert h.dtype == np.float64 and np.array_equal(h, hash64(ix, iy, seed))
        assert h.min() >= 0.0 and h.max() < 1.0


def test_one_robot_is_written_as_it_is_in_the_two_robot_scene(scene_dir: Path, tmp_path: Path) -> None:
    """``agents`` writes only the named robots, each byte for byte as in the two-robot scene (its own noise stream
    and trajectory), with the same scene files apart from the robots ``scene.json`` lists; a bad name is refused."""
    for noise in ("none", "realistic"):
        if noise == "none":
            both = _files(scene_dir)
        else:
            make_scene(tmp_path / "both", seed=SEED, width=W, height=H, frames=N, progress=False, sensor_noise=noise)
            both = _files(tmp_path / "both")
        out = tmp_path / f"b_only_{noise}"
        summary = make_scene(out, seed=SEED, width=W, height=H, frames=N, progress=False, sensor_noise=noise,
                             agents=("agent_b",))
        one = _files(out)
        assert not (out / "agent_a").exists() and list(summary["agents"]) == ["agent_b"]
        assert {k for k in one if k.startswith("agent_b/")} == {k for k in both if k.startswith("agent_b/")}
        for k in one:
            if k != "scene.json":
                assert one[k] == both[k], f"{k} differs from the two-robot scene's ({noise})"
        doc = _read_json(out / "scene.json")
        assert doc["agents"] == ["agent_b"] and list(doc["roi_fraction_mean"]) == ["agent_b"]
    for bad in ((), ("agent_c",)):
        with pytest.raises(ValueError, match="agents must name"):
            make_scene(tmp_path / "bad", seed=SEED, width=W, height=H, frames=N, progress=False, agents=bad)


def test_written_depth_matches_raycast(scene_dir: Path) -> None:
    """The PNG depth is the quantised ray-cast depth at the traj.txt pose, valid everywhere."""
    scene = build_default_scene(SEED)
    intr = default_intrinsics(W, H)
    for agent in AGENTS:
        traj = np.loadtxt(scene_dir / agent / "traj.txt").reshape(-1, 4, 4)
        for i in (0, N - 1):
            _, depth = _read_agent(scene_dir / agent, i)
            assert (depth > 0).mean() == 1.0
            r = render(scene, intr, traj[i])
            assert np.array_equal(quantize_depth(r.depth), depth)


def test_depth_lands_on_intended_surfaces() -> None:
    scene = build_default_scene(SEED)
    # a camera looking down at an empty patch of floor: the centre pixel's depth is the distance
    intr = Intrinsics(fx=32.0, fy=32.0, cx=32.0, cy=24.0, width=65, height=49)
    eye, target = np.array([2.0, -1.8, 1.2]), np.array([2.0, -1.0, 0.0])
    r = render(scene, intr, look_at(eye, target))
    assert r.ids[24, 32] == FLOOR_ID
    assert r.depth[24, 32] == pytest.approx(np.linalg.norm(target - eye), abs=1e-9)
    # every floor / wall pixel of a full view back-projects onto its plane (through the PNG quantisation)
    intr = default_intrinsics(96, 72)
    pose = make_trajectories(5, SEED)["agent_b"][2]
    r = render(scene, intr, pose)
    pts = backproject(quantize_depth(r.depth) / DEPTH_SCALE, intr, pose)
    for sid, axis, value in ((FLOOR_ID, 2, 0.0), (WALL_YMAX_ID, 1, 2.5), (WALL_XMIN_ID, 0, -3.0)):
        sel = r.ids == sid
        assert sel.sum() > 20, f"surface {sid} not visible"
        assert np.abs(pts[sel][:, axis] - value).max() < 2e-3
    assert (r.depth > 0.3).all() and (r.depth < 8.0).all()


def test_object_boxes_match_id_buffer() -> None:
    """Pixels whose back-projected depth lies inside an object's box are that object's pixels, and
    the object's pixels are in its mask (box enlarged by mask_margin_m)."""
    scene = build_default_scene(SEED)
    objs = {o["id"]: o for o in scene.objects_json()["objects"]}
    intr = default_intrinsics(160, 120)
    trajs = make_trajectories(4, SEED)
    small = {2: "mug", 3: "box", 4: "book"}
    furniture = {5: "chair", 7: "door", 8: "trash can"}
    tested = {**small, **furniture}
    inside_hits = {k: 0 for k in tested}
    inside_total = {k: 0 for k in tested}
    id_in_mask = {k: 0 for k in tested}
    id_total = {k: 0 for k in tested}
    for agent in AGENTS:
        for pose in trajs[agent]:
            r = render(scene, intr, pose)
            dm = quantize_depth(r.depth) / DEPTH_SCALE
            pts = backproject(dm, intr, pose)
            valid = dm > 0
            for oid in tested:
                full = mask_rule(pts, valid, objs[oid])
                if oid in small:  # the full mask rule: nothing but the object (the desk top stays out)
                    inside = full
                else:  # a tight box, off the floor and the wall the furniture touches
                    inside = mask_rule(pts, valid, dict(objs[oid], mask_margin_m=0.002))
                    inside &= (pts[..., 2] > 0.01) & (pts[..., 1] < 2.495)
                inside_total[oid] += int(inside.sum())
                inside_hits[oid] += int((r.ids[inside] == oid).sum())
                own = r.ids == oid
                id_total[oid] += int(own.sum())
                id_in_mask[oid] += int(full[own].sum())
    for oid, name in tested.items():
        assert inside_total[oid] > 10, f"{name}: box never visible"
        assert inside_hits[oid] / inside_total[oid] > 0.99, f"{name}: box contains other surfaces"
        assert id_in_mask[oid] / id_total[oid] > 0.95, f"{name}: object pixels outside its mask"
    # small objects' boxes float 1.5-2.5 cm above the desk top, so the desk is not in their mask
    desk = objs[1]
    desk_top = desk["center"][2] + desk["size"][2] / 2
    for oid in (2, 3, 4):
        bottom = objs[oid]["center"][2] - objs[oid]["size"][2] / 2
        assert 0.015 <= bottom - desk_top <= 0.025


def test_tasks_roi_visible_and_summary(scene_dir: Path) -> None:
    summary = _read_json(scene_dir / "scene.json")
    tasks = _read_json(scene_dir / "tasks.json")["tasks"]
    objs = {o["id"]: o for o in _read_json(scene_dir / "objects.json")["objects"]}
    intr = default_intrinsics(W, H)
    for agent in AGENTS:
        for t in tasks:
            assert summary["roi_nonempty_frame_fraction"][agent][t["id"]] >= 0.8, (agent, t["id"])
            assert 0.005 < summary["roi_fraction_mean"][agent][t["id"]] < 0.35, (agent, t["id"])
    # recompute one agent's ROI fractions from the files with the mask rule
    traj = np.loadtxt(scene_dir / "agent_b" / "traj.txt").reshape(-1, 4, 4)
    fr = {t["id"]: 0.0 for t in tasks}
    for i in range(N):
        _, depth = _read_agent(scene_dir / "agent_b", i)
        dm = depth.astype(np.float64) / DEPTH_SCALE
        pts = backproject(dm, intr, traj[i])
        for t in tasks:
            m = np.zeros(dm.shape, bool)
            for oid in t["roi_object_ids"]:
                m |= mask_rule(pts, dm > 0, objs[oid])
            fr[t["id"]] += m.mean() / N
    for k, v in fr.items():
        assert v == pytest.approx(summary["roi_fraction_mean"]["agent_b"][k], abs=2e-6)


def test_task_graphs_follow_rules(scene_dir: Path) -> None:
    tasks = _read_json(scene_dir / "tasks.json")["tasks"]
    objs = {o["id"]: o for o in _read_json(scene_dir / "objects.json")["objects"]}
    determiners = {"the", "a", "an", "all", "every", "any", "this"}
    for t in tasks:
        g = t["graph"]
        phrases = g["targets"] + g["anchors"]
        assert g["targets"] and not set(g["targets"]) & set(g["anchors"])
        for ph in phrases:
            assert ph == ph.lower().strip() and ph
            assert not set(ph.split()) & determiners
            assert not ph.endswith("s"), f"plural phrase {ph!r}"
            names = [n for oid in t["roi_object_ids"] for n in [objs[oid]["label"]] + objs[oid]["synonyms"]]
            assert ph in names, f"{t['id']}: {ph!r} matches no ROI object label/synonym"
        for rel in g["relations"]:
            assert rel["predicate"] in ("near", "on")
            assert rel["target"] in g["targets"] and rel["anchor"] in g["anchors"]
        assert "unsupported" not in g
        assert all(oid in objs for oid in t["roi_object_ids"])
    by_id = {t["id"]: t for t in tasks}
    texts = {t["text"] for t in tasks}
    assert {"Prepare to pick up the object on the desk", "Identify the chair closest to the table",
            "Locate all obstacles in the scene and find a path to the door"} <= texts
    # the "closest chair" ROI is the chair nearest to the desk
    chairs = [o for o in objs.values() if o["label"] == "chair"]
    desk = next(o for o in objs.values() if o["label"] == "desk")
    near = min(chairs, key=lambda o: np.linalg.norm(np.subtract(o["center"], desk["center"])[:2]))
    assert set(by_id["synth-find-chair"]["roi_object_ids"]) == {near["id"], desk["id"]}
    # navigation ROI = every obstacle + the door
    obstacles = {o["id"] for o in objs.values() if "obstacle" in o["synonyms"]}
    door = {o["id"] for o in objs.values() if o["label"] == "door"}
    assert len(obstacles) >= 5 and set(by_id["synth-nav-door"]["roi_object_ids"]) == obstacles | door


def test_trajectories_differ_smooth_and_free() -> None:
    trajs = make_trajectories(30, SEED)
    a, b = trajs["agent_a"][:, :3, 3], trajs["agent_b"][:, :3, 3]
    assert np.linalg.norm(a[:, None] - b[None], axis=-1).min() > 1.0
    scene = build_default_scene(SEED)
    for agent, T in trajs.items():
        pos = T[:, :3, 3]
        steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        assert steps.max() < 0.15 and steps.min() > 0.0
        fwd = T[:, :3, 2]
        assert np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1, 1))).max() < 5.0
        assert np.all(pos > scene.room.lo + 0.3) and np.all(pos < scene.room.hi - 0.3)
        for o in scene.objects:
            local = (pos - o.center) @ o.rotation
            assert not np.any(np.all(np.abs(local) <= o.size / 2 + 0.2, axis=1)), f"{agent} inside {o.label}"
    with pytest.raises(ValueError):
        make_trajectories(1)


def test_textures_filtering_and_validation() -> None:
    x = np.linspace(0.0, 1.0, 101) + 0.0123
    hard = box_wave(x, 0.1, 0.3, np.full_like(x, 1e-9))
    assert set(np.unique(np.round(hard, 6))) <= {0.0, 1.0} and 0.2 < hard.mean() < 0.4
    blurred = box_wave(x, 0.1, 0.3, np.full_like(x, 1.0))  # footprint = 10 periods -> mean
    assert np.allclose(blurred, 0.3, atol=1e-9)
    with pytest.raises(ValueError):
        Material("marble", (1.0, 1.0, 1.0))
    with pytest.raises(ValueError):
        Material("solid", (1.0, 1.0, 1.0), scale=0.0)
    with pytest.raises(ValueError):
        default_intrinsics(8, 8)


def test_cli_make_scene(tmp_path: Path) -> None:
    from gausslite.cli import main

    out = tmp_path / "cli"
    assert main(["make-scene", "--out", str(out), "--seed", "5", "--width", "32", "--height", "24",
                 "--frames", "2", "--quiet"]) == 0
    assert (out / "agent_b" / "results" / "depth000001.png").exists()
    assert (out / "agent_a" / "results" / "frame000001.jpg").exists()
    assert _read_json(out / "scene.json")["seed"] == 5
    assert np.loadtxt(out / "agent_a" / "traj.txt").shape == (2, 16)
    assert main(["make-scene", "--out", str(tmp_path / "bad"), "--frames", "1", "--quiet"]) == 2
    one = tmp_path / "one"
    assert main(["make-scene", "--out", str(one), "--width", "32", "--height", "24", "--frames", "2",
                 "--agents", "agent_a", "--quiet"]) == 0
    assert (one / "agent_a" / "traj.txt").is_file() and not (one / "agent_b").exists()


def test_rotation_angle_of_single_and_batched_rotations_and_poses():
    from scipy.spatial.transform import Rotation

    from gausslite.camera import rotation_angle

    angles = np.array([0.0, 0.3, 1.2, np.pi - 1e-9, np.pi])
    R = Rotation.from_rotvec(angles[:, None] * np.array([[0.6, 0.0, 0.8]])).as_matrix()
    np.testing.assert_allclose(rotation_angle(R), angles, atol=2e-7)  # arccos is flat at 0 and π
    poses = np.tile(np.eye(4), (2, 5, 1, 1))
    poses[:, :, :3, :3] = R
    assert rotation_angle(poses).shape == (2, 5)
    np.testing.assert_allclose(rotation_angle(poses)[1], angles, atol=2e-7)
    assert float(rotation_angle(R[2].astype(np.float32))) == pytest.approx(1.2, abs=1e-6)
    assert float(rotation_angle(np.eye(3) * (1 + 1e-12))) == 0.0  # rounding above 1 is clipped, never NaN
