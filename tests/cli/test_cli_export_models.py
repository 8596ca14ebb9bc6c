"""``gausslite export models`` on random-weight real architectures (a saved tiny Grounding DINO checkpoint
folder and ultralytics' yolov8n-seg.yaml), and its messages when files are missing or a hub id is offline."""

from __future__ import annotations

import numpy as np
import yaml

from gausslite.cli import main
from tests._real_models import DET_SIZE, SEG_IMGSZ, need


def test_export_models_writes_what_the_agent_loads(exported_models):
    rc, out = exported_models["rc"], exported_models["out"]
    assert rc == 0, exported_models["err"]
    assert sorted(p.name for p in out.iterdir()) == ["agent-onnx.yaml", "detector.onnx", "segmenter.onnx", "vocab.txt"]
    cfg = yaml.safe_load((out / "agent-onnx.yaml").read_text())["agent"]
    assert cfg["relevance_backend"] == "onnx"
    from gausslite.mission import OnnxRelevanceConfig

    o = OnnxRelevanceConfig(**cfg["onnx"])
    assert o.missing() == []
    from gausslite.attention import OnnxFastSAMSegmenter, OnnxGroundingDetector

    det = OnnxGroundingDetector(o.detector_path, o.vocab_path)
    seg = OnnxFastSAMSegmenter(o.segmenter_path)
    assert det.input_size == DET_SIZE == (160, 224) and seg.input_hw == SEG_IMGSZ == (96, 128)
    img = np.zeros((48, 64, 3), np.uint8)
    d = det.detect(img, ["red cup", "desk"])
    assert len(d) <= 20 and d.boxes.shape == (len(d), 4)
    assert seg.segment(img, np.array([[0, 0, 30, 20]], np.float32)).shape == (1, 48, 64)


def test_export_models_lists_missing_files(tmp_path, capsys, monkeypatch):
    need("transformers")
    empty = tmp_path / "ckpt"
    empty.mkdir()
    (empty / "config.json").write_text("{}")
    rc = main(["export", "models", "--detector", str(empty), "--segmenter", str(tmp_path / "FastSAM-s.pt"),
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "model.safetensors (or pytorch_model.bin)" in err and "vocab.txt" in err and "FastSAM-s.pt" in err
    assert f"{empty}/config.json" not in err  # present files are not listed
    assert not (tmp_path / "o").exists()  # nothing exported when something is missing
    # a hub id that is not in the local cache, offline
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    rc = main(["export", "models", "--detector", "IDEA-Research/grounding-dino-tiny", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "config.json" in err and "vocab.txt" in err and "hf download IDEA-Research/grounding-dino-tiny" in err
    rc = main(["export", "models", "--out", str(tmp_path / "o")])
    assert rc == 2 and "--detector and/or --segmenter" in capsys.readouterr().err
