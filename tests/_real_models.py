"""Real detector/segmenter architectures with random weights, reduced in size, for the export tests:
transformers' Grounding DINO (Swin backbone + BERT text encoder) and ultralytics' YOLOv8n-seg from its YAML.
Nothing is downloaded: the BERT vocab is written here (real BERT ids for the special tokens)."""

from __future__ import annotations

import fcntl
import hashlib
import json
from pathlib import Path

from tests._ci import missing

#: words placed at ids 2000.. of the test vocab
WORDS = ["red", "cup", "desk", "chair", "mug", "computer", "mouse", "keyboard", "on", "the", "##s"]


def need(module: str):
    """Import ``module`` or skip (fail under CI)."""
    import importlib

    try:
        if module == "ultralytics":  # installed without torchvision (see gausslite.attention.export)
            from gausslite.attention.export import import_ultralytics

            return import_ultralytics()
        return importlib.import_module(module)
    except ImportError:
        missing(f"{module} is not installed", user_hint=" (bash scripts/setup.sh installs it)")


def write_bert_vocab(path: Path, size: int = 30522) -> Path:
    """A vocab.txt with BERT's layout: [PAD]=0, [UNK]=100, [CLS]=101, [SEP]=102, [MASK]=103, '.'=1012,
    '?'=1029, :data:`WORDS` from 2000, filler tokens elsewhere."""
    toks = [f"[unused{i}]" for i in range(size)]
    toks[0], toks[100], toks[101], toks[102], toks[103] = "[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"
    toks[1012], toks[1029] = ".", "?"
    for i, w in enumerate(WORDS):
        toks[2000 + i] = w
    path.write_text("\n".join(toks) + "\n", encoding="utf-8")
    return path


def tiny_grounding_dino(seed: int = 0):
    """``GroundingDinoForObjectDetection`` with a 4-stage Swin (embed 24, one block per stage), a one-layer
    BERT (hidden 32), d_model 32, 20 queries; eager attention; random weights."""
    import torch

    tf = need("transformers")
    sw = tf.SwinConfig(embed_dim=24, depths=[1, 1, 1, 1], num_heads=[1, 1, 2, 2], window_size=7,
                       out_features=["stage2", "stage3", "stage4"])
    bt = tf.BertConfig(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64,
                       vocab_size=30522)
    cfg = tf.GroundingDinoConfig(backbone_config=sw, text_config=bt, d_model=32, encoder_layers=1, decoder_layers=2,
                                 num_queries=20, encoder_ffn_dim=64, decoder_ffn_dim=64, encoder_attention_heads=2,
                                 decoder_attention_heads=2, attn_implementation="eager")
    torch.manual_seed(seed)
    return tf.GroundingDinoForObjectDetection(cfg).eval()


def save_checkpoint(folder: Path, seed: int = 0) -> Path:
    """Write a tiny Grounding DINO checkpoint folder (config.json, model.safetensors, vocab.txt)."""
    folder.mkdir(parents=True, exist_ok=True)
    tiny_grounding_dino(seed).save_pretrained(folder)
    write_bert_vocab(folder / "vocab.txt")
    return folder


#: detector input (h, w) and segmenter input (h, w) of :func:`export_models_cli`
DET_SIZE = (160, 224)
SEG_IMGSZ = (96, 128)


def export_models_cli(folder: Path) -> dict:
    """``gausslite export models`` on a tiny Grounding DINO checkpoint (:func:`save_checkpoint`, seed 0) and
    ultralytics' yolov8n-seg.yaml, at :data:`DET_SIZE` / :data:`SEG_IMGSZ`, into ``folder / "models"``.

    Returns:
        {"rc": exit code, "err": what the command wrote to stderr, "checkpoint": the checkpoint folder,
        "out": the output folder}
    """
    import contextlib
    import io

    need("transformers")
    need("onnxscript")
    need("ultralytics")
    from gausslite.cli import main

    ckpt = save_checkpoint(folder / "gdino-ckpt")
    out = folder / "models"
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["export", "models", "--detector", str(ckpt), "--segmenter", "yolov8n-seg.yaml", "--out", str(out),
                   "--det-size", *map(str, DET_SIZE), "--seg-imgsz", *map(str, SEG_IMGSZ)])
    return {"rc": rc, "err": err.getvalue(), "checkpoint": ckpt, "out": out}


def export_models_once(root: Path) -> dict:
    """:func:`export_models_cli` built once under ``root`` and then read by every process that asks: the first to
    take ``root/<key>.lock`` exports into ``root/<key>/`` and records the result there; the others wait on the lock
    (as long as the export takes) and read the record. ``<key>`` hashes the export's inputs (the sizes, the seed and
    the sources of the export code), so a ``root`` shared by the workers of a run holds one export per input.

    Returns:
        As :func:`export_models_cli`.
    """
    repo = Path(__file__).resolve().parents[1]
    h = hashlib.sha256(json.dumps([DET_SIZE, SEG_IMGSZ, 0]).encode())
    for src in sorted([*(repo / "gausslite" / "attention").glob("*.py"), repo / "gausslite" / "cli" / "cmd_export.py",
                       Path(__file__)]):
        h.update(src.read_bytes())
    key = h.hexdigest()[:16]
    root.mkdir(parents=True, exist_ok=True)
    folder, record = root / key, root / key / "result.json"
    with open(root / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not record.is_file():
            folder.mkdir(exist_ok=True)
            result = export_models_cli(folder)
            record.write_text(json.dumps({"rc": result["rc"], "err": result["err"]}), encoding="utf-8")
        done = json.loads(record.read_text(encoding="utf-8"))
    return {**done, "checkpoint": folder / "gdino-ckpt", "out": folder / "models"}
