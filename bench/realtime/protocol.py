"""The real-time benchmark's scoring protocol: which frames a mission may see (:func:`training_frames`) and which it
never saw (:func:`novel_ids`), a finished map scored over every frame of the sequence under each scoring protocol
(:func:`score`, :func:`map_scores`; docs/realtime.md#scoring-protocols), the leak guard of the withheld frames
(:func:`check_withheld`), and a saved map scored after every mission ran (:func:`score_deferred`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import cv2
import torch

from gausslite.datasets import task_roi
from gausslite.datasets.subset import EstimatedPoses, ScaledFrames
from gausslite.evaluation import WITHHELD_PROTOCOLS, FrameSubset, score_live_map, side_by_side, withheld_indices
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper

from bench.realtime.scenes import SCENES, Preloaded, load_scene

#: the tracked protocol: Adam steps per frame, and every how many frames of the sequence it scores
TRACK_ITERS = 30
TRACK_STRIDE = 5


def training_frames(job: dict, ds):
    """The frames the mission of ``job`` may see: ``ds`` without every ``job["novel_every"]``-th frame (the
    ``novel`` protocol's withheld frames, :func:`gausslite.evaluation.withheld_indices`), or ``ds`` itself when
    nothing is withheld (``novel_every`` 0)."""
    k = int(job.get("novel_every") or 0)
    return FrameSubset(ds, withheld_indices(len(ds), k)) if k else ds


def novel_ids(job: dict, ds) -> Optional[list[int]]:
    """Frame ids of the frames ``job``'s mission never saw (None when nothing is withheld)."""
    k = int(job.get("novel_every") or 0)
    return [int(ds[i].frame_id) for i in withheld_indices(len(ds), k)] if k else None


def score(mapper, ds, ann, task: str, protocols=("sensor",), track_iters: int = TRACK_ITERS,
          track_stride: int = TRACK_STRIDE, keyframe_ids=None, novel=None, record: Optional[dict] = None,
          predicted: Optional[dict] = None, poses: Optional[dict] = None) -> dict:
    """ROI PSNR, PSNR and SSIM (means; ROI over frames that show the ROI) of the map under each scoring protocol
    (:func:`gausslite.evaluation.score_live_map`: ``sensor``, ``keyframes``, ``tracked``, and ``novel`` (at the pose
    the map predicts) and ``novel-tracked`` over the frame ids ``novel`` withheld from the mission), the same for
    every mode. The top-level figures are the ``sensor`` protocol's (every frame at the sensor's pose);
    ``protocols`` holds each protocol's, with each frame's figures. ``record`` / ``predicted``: filled with the
    views the tracked / ``novel`` frames were scored at (frame id → ``TrackedView``). ``poses``: frame id → (4, 4)
    c2w the mission's odometry estimated (``--pose-source odometry``): every protocol starts from those instead of
    the given poses, the ROI stays the given poses', frames without an estimate are not scored
    (:class:`gausslite.datasets.subset.EstimatedPoses`)."""
    protocols = tuple(dict.fromkeys(("sensor", *protocols)))
    if novel is None:
        protocols = tuple(p for p in protocols if p not in WITHHELD_PROTOCOLS)
    roi = task_roi(ann, task)
    if poses is not None:
        ds = EstimatedPoses(ds, poses)
        roi = ds.roi_fn(ann, task)
    frames = [ds[i] for i in range(len(ds))]
    res = score_live_map(mapper, frames, roi, protocols,
                         track_iters=track_iters, track_stride=track_stride, keyframe_ids=keyframe_ids,
                         novel_ids=novel, record=record, predicted=predicted)
    sensor = res["sensor"]
    return {"roi_psnr": sensor["roi_psnr"], "psnr": sensor["psnr"], "ssim": sensor["ssim"],
            "frames_scored": sensor["frames_scored"], "protocols": res}


def save_render(mapper, ds, ann, task: str, path: Path) -> None:
    """A side-by-side PNG (render | ground truth | ROI overlay) of the frame whose ROI is largest."""
    best, best_n = 0, -1
    for i in range(0, len(ds), max(1, len(ds) // 30)):
        fr = ds[i]
        n = int(ann.roi_mask(task, fr.depth, fr.c2w, fr.intrinsics).sum())
        if n > best_n:
            best, best_n = i, n
    fr = ds[best]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), side_by_side(mapper.render_frame(fr), fr, ann.roi_mask(task, fr.depth, fr.c2w,
                                                                                  fr.intrinsics)))


def check_withheld(novel, keyframe_ids, roi_view_ids=()) -> None:
    """The leak guard of the withheld protocols: no frame scored as novel was a training view of the map.

    Args:
        novel: frame ids withheld from the mission (None: nothing withheld).
        keyframe_ids: frame ids of the map's keyframes (a saved map's own record: a map rebuilt from its state has
            no per-keyframe statistics of its own to check).
        roi_view_ids: frame ids of its stored ROI views.
    Raises:
        ValueError: a withheld frame among them (the mission saw it: the novel figures would not be novel).
    """
    if not novel:
        return
    trained = {int(i) for i in keyframe_ids or ()} | {int(i) for i in roi_view_ids or ()}
    leaked = sorted({int(i) for i in novel} & trained)
    if leaked:
        raise ValueError(f"withheld frames {leaked[:5]} were training views of the map (keyframes or ROI views): "
                         f"not novel")


def map_scores(job: dict, mapper, ds, ann, task_id: str, fp_per_kf: float, keyframe_ids) -> dict:
    """The scores of a finished map under ``job["protocols"]``, its render (``job["render_dir"]``) and, with
    ``job["final_pass"]``, the scores after the profile's final pass (which changes ``mapper``). Scored at the
    resolution the mission mapped at (``job["mapping_downscale"]``, agent.resolution) or, with ``job["score_at"]``
    ``"scene"``, at the resolution of ``ds`` itself (the scene's); the result records which (``"score_at"``) and the
    size, ``"scored_size"`` [width, height] in pixels.

    Raises:
        ValueError: a withheld frame among ``keyframe_ids`` or the map's ROI views (:func:`check_withheld`)."""
    basis = job.get("score_at") or "mapping"
    f = float(job.get("mapping_downscale") or 1.0) if basis == "mapping" else 1.0
    if f != 1:
        ds = ScaledFrames(ds, f)
    novel = novel_ids(job, ds)
    check_withheld(novel, keyframe_ids, mapper.roi_views.frame_ids)
    size = ds[0].intrinsics
    res = {"score_at": basis, "scored_size": [int(size.width), int(size.height)]}
    res |= score(mapper, ds, ann, task_id, job.get("protocols", ("sensor",)), job.get("track_iters", TRACK_ITERS),
                 job.get("track_stride", TRACK_STRIDE), keyframe_ids, novel, poses=job.get("estimated_poses"))
    if job.get("render_dir"):
        save_render(mapper, ds, ann, task_id, Path(job["render_dir"]) / f"{job['scene']}_{job['mode']}.png")
    if job.get("final_pass") and fp_per_kf:
        mapper.cfg = mapper.cfg.model_copy(update={"final_iters_per_keyframe": fp_per_kf})
        res["final_iters"] = mapper.finalize()
        res.update({f"final_{k}": v for k, v in score(mapper, ds, ann, task_id).items()
                    if k not in ("frames_scored", "protocols")})
    return res


def score_deferred(res: dict) -> dict:
    """Score a mission whose map :func:`run_one` saved (its run result, with ``state_path`` and ``score_job``):
    rebuild the mapper from its state and configuration and add the scores to the result (the state file is
    removed)."""
    job = res["score_job"]
    t0 = time.perf_counter()
    saved = torch.load(res["state_path"], weights_only=False)
    mapper = Mapper(MapperConfig.model_validate(saved["cfg"]))
    mapper.load_state_dict(saved["state"])
    ds, _ = load_scene(job.get("spec") or SCENES[job["scene"]], Path(job["path"]))
    ds = Preloaded(ds)
    out = {k: v for k, v in res.items() if k not in ("state_path", "fp_per_kf", "score_job")}
    job = {**job, "estimated_poses": saved.get("estimated_poses")}
    out.update(map_scores(job, mapper, ds, ds.annotations, job["task"], res["fp_per_kf"], saved["keyframe_ids"]))
    out["score_s"] = time.perf_counter() - t0  # loading, every protocol, the render (and a final pass, if asked)
    Path(res["state_path"]).unlink(missing_ok=True)
    return out
