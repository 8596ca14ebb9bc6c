"""bench.roi_share: the share of the image each task's ground-truth region takes, per frame, summarised."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import roi_share as rs


def test_the_share_is_the_mask_over_the_image_for_every_task(tmp_path):
    """On a tiny synthetic scene: each task's figures are the per-frame ROI masks' means summarised (the same masks
    the scorers use), a task seen in no frame has share 0, and the command writes its table."""
    from gausslite.datasets import task_roi
    from gausslite.datasets.annotations import load_annotations
    from gausslite.datasets.loader import load_dataset
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=6, width=64, height=48, trajectory="circle", progress=False)
    seq = tmp_path / "scene" / "agent_a"
    got = rs.roi_share(seq, downscale=1, stride=2)
    ann, ds = load_annotations(seq), load_dataset(seq)
    assert got["frames"] == 3 and set(got["tasks"]) == {t.id for t in ann.tasks}
    for t in ann.tasks:
        s = [float(np.mean(task_roi(ann, t.id)(ds[i]))) for i in (0, 2, 4)]
        row = got["tasks"][t.id]
        assert row["mean"] == pytest.approx(np.mean(s)) and row["median"] == pytest.approx(np.median(s))
        assert row["seen"] == pytest.approx(np.mean([x > 0 for x in s])) and 0 <= row["mean"] <= row["p90"] + 1e-12
    assert any(r["mean"] > 0 for r in got["tasks"].values())  # the scene's tasks are in view
    with pytest.raises(ValueError):
        rs.roi_share(seq, stride=0)
    with pytest.raises(FileNotFoundError):
        rs.roi_share(tmp_path)  # no annotations there
    out = tmp_path / "share.json"
    assert rs.main(["--datasets", str(seq), "--downscale", "1", "--stride", "2", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    (row,) = res["datasets"].values()
    assert row["frames"] == 3 and row["tasks"]["synth-pick-object"]["mean"] == pytest.approx(
        got["tasks"]["synth-pick-object"]["mean"])
    md = out.with_suffix(".md").read_text()
    assert md.startswith("# bench.roi_share") and "| synth-pick-object |" in md
    with pytest.raises(SystemExit):
        rs.main(["--datasets", str(tmp_path / "absent"), "--out", str(out)])
