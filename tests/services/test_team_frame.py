"""The team's world frame (docs/team.md): a robot whose poses and annotations are given in a map frame of its own,
rotated 30° about z and shifted by about a metre, lands its pushed subset, its keyframes and its Finish scores in the
team's world frame when it is given ``T_world_map`` (the agent setting ``agent.frame.T_world_map`` for a replayed
dataset, the ``StartMission`` option for streamed frames), and lands them elsewhere without it."""

from __future__ import annotations

import json
import math
import shutil

import grpc
import numpy as np
import pytest
from pydantic import ValidationError

from gausslite.camera import backproject
from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.datasets.annotations import load_annotations
from gausslite.fusion.vote import voxel_keys, voxel_vote
from gausslite.mission.team_frame import annotations_to_world, frame_to_world, parse_T_world_map, rigid_transform
from gausslite.synthetic import make_scene
from gausslite.wire.decode import assemble
from gausslite_rpc import agent_pb2
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.frames import encode_frame, validate_frame
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions
from tests._waits import WORK_S

# every_frame ingest, tiny images, few iterations: five missions of six frames run in seconds
TINY = ["agent.ingest=every_frame", "agent.push.every=100", "mapper.budget_clock=work", "agent.push.backoff_s=0.1", "agent.push.max_backoff_s=0.5",
        "agent.scoring.protocols=[sensor]", "agent.share.finetune_iters=10", "agent.share.worker=thread",
        "agent.refine_views.min_roi_px=4",
        "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200"]
TASK = "synth-find-chair"
#: robot B's map frame in the world frame: 30° about z, 1.2 m / -0.7 m / 0.1 m away
T_WORLD_MAP = rigid_transform([1.2, -0.7, 0.1], [0.0, 0.0, math.sin(math.radians(15)), math.cos(math.radians(15))])
VOXEL = 0.10


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """``(world, moved)``: the synthetic scene, and robot B's sequence and annotations in its own map frame."""
    world = tmp_path_factory.mktemp("world")
    make_scene(world, seed=0, width=64, height=48, frames=6, progress=False)
    moved = tmp_path_factory.mktemp("moved")
    T_map_world = np.linalg.inv(T_WORLD_MAP)
    (moved / "agent_b").mkdir()
    shutil.copytree(world / "agent_b" / "results", moved / "agent_b" / "results")
    poses = np.loadtxt(world / "agent_b" / "traj.txt").reshape(-1, 4, 4)
    np.savetxt(moved / "agent_b" / "traj.txt", (T_map_world @ poses).reshape(-1, 16))
    objects = json.loads((world / "objects.json").read_text())
    R, t = T_map_world[:3, :3], T_map_world[:3, 3]
    for o in objects["objects"]:
        o["center"] = (R @ np.asarray(o["center"]) + t).tolist()
        o["rotation"] = (R @ np.asarray(o["rotation"])).tolist()
    (moved / "objects.json").write_text(json.dumps(objects))
    for name in ("tasks.json", "cam_params.json"):
        shutil.copy(world / name, moved / name)
    return world, moved


def test_the_setting_is_a_rigid_4x4_and_bad_ones_name_the_field():
    cfg = load_config(None, [f"agent.frame.T_world_map={T_WORLD_MAP.tolist()}"]).agent
    assert np.allclose(cfg.frame.matrix(), T_WORLD_MAP, atol=1e-12)
    assert load_config().agent.frame.matrix() is None  # default: the robot's map frame is the world frame
    bad = {"scaled": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
           "mirrored": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]],
           "last row": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]],
           "3x3": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    for why, m in bad.items():
        with pytest.raises(ValidationError, match=r"agent\.frame\.T_world_map") as e:
            load_config(None, [f"agent.frame.T_world_map={m}"])
        assert ("4 x 4" if why == "3x3" else "T_world_map:") in str(e.value), why
    # the session option's form: 16 row-major numbers, same checks
    assert np.allclose(parse_T_world_map(T_WORLD_MAP.reshape(-1)), T_WORLD_MAP)
    assert parse_T_world_map([]) is None
    with pytest.raises(ValueError, match="16 numbers"):
        parse_T_world_map([1.0] * 12)


def test_poses_and_boxes_move_together(scenes):
    """A frame and the annotations of the moved scene, moved back by T_world_map, are the world scene's: the same
    pose, the same ROI pixels (which is why the task region stays on its objects)."""
    world, moved = scenes
    ref, mv = load_dataset(world / "agent_b")[2], load_dataset(moved / "agent_b")[2]
    assert np.abs(mv.c2w - ref.c2w).max() > 0.5  # the map frame is not the world frame
    back = frame_to_world(mv, T_WORLD_MAP)
    assert np.allclose(back.c2w, ref.c2w, atol=1e-9)
    pending = frame_to_world(validate_frame(encode_frame(mv)), T_WORLD_MAP)  # a streamed, not yet decoded frame
    assert np.allclose(pending.c2w, ref.c2w, atol=1e-9) and np.allclose(pending.materialize().c2w, ref.c2w, atol=1e-9)
    ann_w, ann_m = load_annotations(world), load_annotations(moved)
    roi = ann_w.roi_mask(TASK, ref.depth, ref.c2w, ref.intrinsics)
    assert roi.sum() > 20
    assert np.array_equal(annotations_to_world(ann_m, T_WORLD_MAP).roi_mask(TASK, mv.depth, back.c2w, mv.intrinsics),
                          roi)
    # a frame moved without its boxes (or the other way round) loses its task region
    assert (ann_m.roi_mask(TASK, mv.depth, back.c2w, mv.intrinsics) & roi).sum() < 0.2 * roi.sum()


def test_a_checkpoint_resumes_only_in_the_world_frame_it_was_mapped_in(scenes, tmp_path):
    from gausslite.mission import AgentRuntime

    world, moved = scenes
    ds = load_dataset(moved / "agent_b")
    graph = {"targets": ["chair"], "anchors": [], "relations": []}
    cfgs = [load_config(None, TINY + [f"agent.frame.T_world_map={T.tolist()}"]).agent
            for T in (T_WORLD_MAP, np.linalg.inv(T_WORLD_MAP))]
    rt = AgentRuntime("b", "Find the chair", graph, cfgs[0], relevance_fn=lambda fr: None, mission_id="m1",
                      checkpoint_dir=tmp_path / "m1")
    try:
        rt.submit(ds[0])
        rt.wait_mapped(WORK_S)
        rt.save_checkpoint()
        # the map is in the world frame: about where the world scene's first frame back-projects its depth
        ref = load_dataset(world / "agent_b")[0]
        seen = backproject(ref.depth, ref.intrinsics, ref.c2w)[ref.depth > 0]
        assert np.linalg.norm(rt.mapper.gmap.means.detach().cpu().numpy().mean(0) - seen.mean(0)) < 0.1
    finally:
        rt.close()
    with pytest.raises(ValueError, match="another world frame"):
        AgentRuntime.launch("b", "Find the chair", graph, cfgs[1], relevance_fn=lambda fr: None, mission_id="m1",
                            checkpoint_dir=tmp_path / "m1")


def _subset(fusion, agent: str):
    version = fusion.store.latest_complete()[agent]
    return assemble(fusion.store.chunk_data(agent, version))[0]


def _voxels(means: np.ndarray) -> set:
    return {tuple(v) for v in voxel_keys(means, VOXEL)}


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a),) distance from each row of ``a`` to its nearest row of ``b`` (metres)."""
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(1)


def _run(name, fusion, cfg, task_text, *, dataset="", annotations="", frames=(), T_option=None, roots=()):
    """One mission of agent ``name`` to the end (replayed or streamed); returns its Finish summary."""
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id=name, fusion_address=fusion.address,
                                                          data_roots=tuple(map(str, roots)), config=cfg))
    try:
        with AgentClient(ag.address) as c:
            c.wait_ready(10)
            m = c.start_mission(task_text, dataset_path=str(dataset), annotations_path=str(annotations),
                                T_world_map=T_option)
            if frames:
                assert c.stream_frames(m.mission_id, frames, timeout_s=60).frames_received == len(frames)
            s = c.finish(m.mission_id, timeout_s=WORK_S)
    finally:
        ag.stop(0)
    assert s.final_push_ok and s.status.state == agent_pb2.MISSION_STATE_FINISHED, s.status.last_error
    return s


def test_a_robot_in_its_own_map_frame_lands_in_the_world_frame_with_its_transform(scenes, tmp_path):
    from gausslite_services.fusion_server.server import serve as serve_fusion

    world, moved = scenes
    fusion = serve_fusion(ServerOptions(port=0), load_config(None, ["fusion.team_map.enabled=false"]).fusion,
                          data_dir=str(tmp_path / "fusion"))
    base = load_config(None, TINY).agent
    with_T = load_config(None, TINY + [f"agent.frame.T_world_map={T_WORLD_MAP.tolist()}"]).agent
    # the streamed robot's own setting is wrong (the inverse): the mission's option overrides it
    wrong = load_config(None, TINY + [f"agent.frame.T_world_map={np.linalg.inv(T_WORLD_MAP).tolist()}"]).agent
    text = load_annotations(world).task_by_id(TASK).text
    roots = (world, moved)
    try:
        summaries = {
            "reference": _run("reference", fusion, base, text, dataset=world / "agent_b", roots=roots),
            "setting": _run("setting", fusion, with_T, text, dataset=moved / "agent_b", roots=roots),
            "unaligned": _run("unaligned", fusion, base, text, dataset=moved / "agent_b", roots=roots),
            # streamed frames (no sensor profile, unlike a replay): compared with a streamed reference
            "reference_live": _run("reference_live", fusion, base, text, annotations=world, roots=roots,
                                   frames=list(load_dataset(world / "agent_b"))),
            "option": _run("option", fusion, wrong, text, annotations=moved, roots=roots,
                           frames=list(load_dataset(moved / "agent_b")), T_option=T_WORLD_MAP),
        }
        ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="bad", annotations_path=str(moved), config=base))
        try:
            with AgentClient(ag.address) as c:
                for bad in (T_WORLD_MAP[:3], np.diag([2.0, 1.0, 1.0, 1.0])):
                    with pytest.raises(grpc.RpcError) as e:
                        c.start_mission(text, T_world_map=bad)
                    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "T_world_map" in e.value.details()
        finally:
            ag.stop(0)
        subsets = {name: _subset(fusion, name) for name in summaries}
        poses = {name: {k.frame_id: k.c2w for k in fusion.store.keyframe_poses(name)} for name in summaries}
        against = {"setting": "reference", "unaligned": "reference", "option": "reference_live"}
        for name, r in against.items():  # the figures docs/team.md quotes (pytest -s)
            g, ref = subsets[name], subsets[r]
            vox, ref_vox = _voxels(g.means), _voxels(ref.means)
            print(f"{name} against {r}: {len(g)} / {len(ref)} Gaussians, centroids "
                  f"{np.linalg.norm(g.means.mean(0) - ref.means.mean(0)):.2e} m apart, nearest median / max "
                  f"{np.median(_nearest(g.means, ref.means)):.2e} / {_nearest(g.means, ref.means).max():.2e} m, voxels {len(vox & ref_vox)}/{len(vox | ref_vox)} "
                  f"in common, keyframes {len(poses[name])} (poses differ by "
                  f"{[float(np.abs(c2w - poses[r][f]).max().round(6)) for f, c2w in poses[name].items() if f in poses[r]]}"
                  f"), ROI PSNR {summaries[name].roi_psnr:.2f} / "
                  f"{summaries[r].roi_psnr:.2f} dB")
        for name in ("setting", "option"):  # given its transform: the reference run's subset, keyframes and scores
            r = against[name]
            g, ref = subsets[name], subsets[r]
            ref_vox = _voxels(ref.means)
            assert 0.8 * len(ref) <= len(g) <= 1.25 * len(ref), (name, len(g), len(ref))
            assert np.linalg.norm(g.means.mean(0) - ref.means.mean(0)) < 0.005, name
            assert np.median(_nearest(g.means, ref.means)) < 0.002, name
            vox = _voxels(g.means)
            assert len(vox & ref_vox) >= 0.9 * len(vox | ref_vox), name
            shared = set(poses[name]) & set(poses[r])
            assert len(shared) >= 2, name
            for fid in shared:  # the refinement views the fusion server holds are posed in the world frame
                assert np.allclose(poses[name][fid], poses[r][fid], atol=1e-5), (name, fid)
            # the agent's own Finish scores its map against the annotations moved with it
            assert summaries[name].has_roi_psnr and abs(summaries[name].roi_psnr - summaries[r].roi_psnr) < 0.2, name
        s, r = summaries["setting"], summaries["reference"]
        assert s.has_roi_psnr_all_frames and abs(s.roi_psnr_all_frames - r.roi_psnr_all_frames) < 0.2
        # without it, the same robot's subset lies in its map frame: a metre and more away, no voxel in common
        ref = subsets["reference"]
        ref_vox = _voxels(ref.means)
        g = subsets["unaligned"]
        assert np.linalg.norm(g.means.mean(0) - ref.means.mean(0)) > 0.5
        assert np.median(_nearest(g.means, ref.means)) > 0.2
        assert len(_voxels(g.means) & ref_vox) < 0.1 * len(ref_vox)
        # what the vote makes of it: aligned, every voxel is contested and the team map holds the chair once; unaligned,
        # no voxel is contested and the team map holds two chairs 1.4 m apart
        fused, rep = voxel_vote({"reference": ref, "setting": subsets["setting"]}, VOXEL)
        fused_u, rep_u = voxel_vote({"reference": ref, "unaligned": g}, VOXEL)
        print(f"vote aligned: {rep.contested_voxels}/{rep.voxels} voxels contested, {len(fused)} rows; unaligned: "
              f"{rep_u.contested_voxels}/{rep_u.voxels} contested, {len(fused_u)} rows")
        assert rep.contested_voxels == rep.voxels and len(fused) == len(ref)
        assert rep_u.contested_voxels == 0 and len(fused_u) == len(ref) + len(g)
        for fid, c2w in poses["unaligned"].items():
            if fid in poses["reference"]:
                assert np.abs(c2w[:3, 3] - poses["reference"][fid][:3, 3]).max() > 0.3
    finally:
        fusion.stop(0)
