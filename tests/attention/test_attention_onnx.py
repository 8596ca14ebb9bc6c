"""ONNX backends' pre/post-processing with tiny models built here (no downloaded weights)."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from gausslite.attention import OnnxFastSAMSegmenter, OnnxGroundingDetector
from gausslite.attention.onnx_backends import grounding_text_masks, letterbox

VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "red", "cup", "desk", "mouse"]
L = 16


def _logit(p):
    return float(np.log(p / (1 - p)))


def _save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _detector_model(path, logits, boxes):
    """logits/boxes constants + 0 * (sum of every text input) + mean(image) on the boxes."""
    ins = [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 8, 8])]
    nodes, zero_terms = [], []
    for name, t in [("input_ids", TensorProto.INT64), ("attention_mask", TensorProto.INT64),
                    ("token_type_ids", TensorProto.INT64), ("position_ids", TensorProto.INT64),
                    ("text_self_attention_masks", TensorProto.BOOL)]:
        shape = [1, L, L] if name == "text_self_attention_masks" else [1, L]
        ins.append(helper.make_tensor_value_info(name, t, shape))
        nodes.append(helper.make_node("Cast", [name], [name + "_f"], to=TensorProto.FLOAT))
        nodes.append(helper.make_node("ReduceSum", [name + "_f"], [name + "_s"], keepdims=0))
        zero_terms.append(name + "_s")
    nodes.append(helper.make_node("Sum", zero_terms, ["tsum"]))
    nodes.append(helper.make_node("Mul", ["tsum", "zero"], ["tzero"]))
    nodes.append(helper.make_node("Add", ["C_logits", "tzero"], ["logits"]))
    nodes.append(helper.make_node("ReduceMean", ["image"], ["imean"], keepdims=0))
    nodes.append(helper.make_node("Add", ["C_boxes", "imean"], ["boxes"]))
    inits = [numpy_helper.from_array(np.float32(0.0), "zero"),
             numpy_helper.from_array(logits.astype(np.float32), "C_logits"),
             numpy_helper.from_array(boxes.astype(np.float32), "C_boxes")]
    outs = [helper.make_tensor_value_info("logits", TensorProto.FLOAT, list(logits.shape)),
            helper.make_tensor_value_info("boxes", TensorProto.FLOAT, list(boxes.shape))]
    return _save(helper.make_graph(nodes, "tiny_gdino", ins, outs, inits), path)


@pytest.fixture()
def vocab_file(tmp_path):
    p = tmp_path / "vocab.txt"
    p.write_text("\n".join(VOCAB) + "\n")
    return p


def test_grounding_detector_postprocessing(tmp_path, vocab_file):
    # caption "red cup . desk ." -> [CLS] red cup . desk . [SEP] (7 tokens, padded to 16)
    Q = 5
    lg = np.full((1, Q, L), -10.0)
    lg[0, 0, 2] = 3.0                   # q0: "cup" -> phrase 0
    lg[0, 1, 4] = 2.0                   # q1: "desk" -> phrase 1
    lg[0, 2, 1] = _logit(0.22)          # q2: passes box_threshold, fails text_threshold
    lg[0, 3, 1] = 2.5                   # q3: duplicate of q0 (lower score), removed by NMS
    lg[0, 4, 10] = 5.0                  # q4: only a padding token fires -> ignored
    bx = np.array([[[0.5, 0.5, 0.25, 0.5], [0.2, 0.7, 0.3, 0.4], [0.8, 0.2, 0.1, 0.1],
                    [0.51, 0.5, 0.25, 0.5], [0.5, 0.5, 0.9, 0.9]]])
    model = _detector_model(tmp_path / "gd.onnx", lg, bx)
    det = OnnxGroundingDetector(model, vocab_file)
    assert det.input_size == (8, 8) and det.text_len == L
    assert (det.box_threshold, det.text_threshold) == (0.20, 0.25)
    img = np.zeros((40, 80, 3), np.uint8)
    img[..., 0] = 200
    x = det.preprocess(img)
    expect_x = (np.array([200, 0, 0]) / 255.0 - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225])
    np.testing.assert_allclose(x[0, :, 3, 3], expect_x, rtol=1e-5)
    feeds, spans, n = det.encode_text(["red cup", "desk"])
    assert n == 7 and spans == [[1, 2], [4]]
    assert feeds["input_ids"][0, :7].tolist() == [2, 5, 6, 4, 7, 4, 3] and feeds["attention_mask"][0].sum() == 7

    img = np.full((40, 80, 3), 120, np.uint8)  # normalised mean ~0.1: shifts the boxes a little
    d = det.detect(img, ["red cup", "desk"])
    m = float(det.preprocess(img).mean())
    assert 0.05 < m < 0.15
    assert d.phrase_ids.tolist() == [0, 1]
    np.testing.assert_allclose(d.scores, [1 / (1 + np.exp(-3.0)), 1 / (1 + np.exp(-2.0))], rtol=1e-5)
    cx, cy, w, h = bx[0, 0] + m
    np.testing.assert_allclose(d.boxes[0], [(cx - w / 2) * 80, (cy - h / 2) * 40, (cx + w / 2) * 80, (cy + h / 2) * 40],
                               atol=1e-3)
    # stricter box threshold drops the desk query
    det.box_threshold = 0.9
    assert det.detect(img, ["red cup", "desk"]).phrase_ids.tolist() == [0]


def test_grounding_text_masks_blocks():
    tokens = ["[CLS]", "red", "cup", ".", "desk", ".", "[SEP]", "[PAD]"]
    mask, pos = grounding_text_masks(tokens, 8)
    assert mask.shape == (1, 8, 8)
    assert mask[0, 1, 2] and mask[0, 2, 3] and not mask[0, 2, 4] and mask[0, 4, 5] and not mask[0, 0, 1]
    assert pos[0].tolist() == [0, 0, 1, 2, 0, 1, 0, 0]


def _fastsam_model(path, pred, protos, S=64):
    ins = [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, S, S])]
    nodes = [helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
             helper.make_node("Mul", ["m", "zero"], ["z"]),
             helper.make_node("Add", ["C_pred", "z"], ["output0"]),
             helper.make_node("Add", ["C_proto", "z"], ["output1"])]
    inits = [numpy_helper.from_array(np.float32(0.0), "zero"), numpy_helper.from_array(pred.astype(np.float32), "C_pred"),
             numpy_helper.from_array(protos.astype(np.float32), "C_proto")]
    outs = [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(pred.shape)),
            helper.make_tensor_value_info("output1", TensorProto.FLOAT, list(protos.shape))]
    return _save(helper.make_graph(nodes, "tiny_fastsam", ins, outs, inits), path)


def test_fastsam_segmenter_postprocessing(tmp_path):
    S = 64
    protos = np.full((1, 2, 16, 16), -5.0)
    protos[0, 0, 6:8, 4:8] = 5.0     # input rows 24..31, cols 16..31 -> original rows 8..15 (pad_y 16)
    protos[0, 1, 10:12, 10:14] = 5.0  # input rows 40..47, cols 40..55 -> original rows 24..31
    # columns: cx, cy, w, h, score, c0, c1
    cand = [[24, 28, 16, 8, 0.9, 1, 0],     # object A
            [24, 28, 16, 8, 0.3, 1, 0],     # below conf 0.4
            [24.2, 28, 16, 8, 0.8, 1, 0],   # duplicate of A (IoU > 0.9): NMS
            [48, 44, 16, 8, 0.6, 0, 1]]     # object B
    pred = np.asarray(cand, dtype=np.float64).T[None]  # (1, 7, 4)
    model = _fastsam_model(tmp_path / "fs.onnx", pred, protos, S)
    seg = OnnxFastSAMSegmenter(model)
    assert seg.imgsz == S and (seg.conf, seg.iou) == (0.4, 0.9)
    img = np.full((32, 64, 3), 50, np.uint8)
    lb, s, pad = letterbox(img, S)
    assert s == 1.0 and pad == (0, 16) and lb[0, 0, 0] == 114 and lb[20, 5, 0] == 50
    masks, boxes, scores = seg.segment_everything(img)
    assert masks.shape == (2, 32, 64)
    np.testing.assert_allclose(scores, [0.9, 0.6], rtol=1e-6)
    gt_a = np.zeros((32, 64), bool)
    gt_a[8:16, 16:32] = True
    gt_b = np.zeros((32, 64), bool)
    gt_b[24:32, 40:56] = True
    assert (masks[0] == gt_a).mean() > 0.99 and (masks[1] == gt_b).mean() > 0.99
    np.testing.assert_allclose(boxes[0], [15.5, 7.5, 31.5, 15.5], atol=1e-4)
    # box prompts pick the best-overlapping candidate; a box over nothing gets an empty mask
    out = seg.segment(img, np.array([[39.5, 23.5, 55.5, 31.5], [15.5, 7.5, 31.5, 15.5], [0, 0, 5, 5]]))
    assert (out[0] == gt_b).mean() > 0.99 and (out[1] == gt_a).mean() > 0.99 and not out[2].any()


def test_onnx_missing_model(tmp_path, vocab_file):
    with pytest.raises(FileNotFoundError):
        OnnxGroundingDetector(tmp_path / "nope.onnx", vocab_file)
    with pytest.raises(FileNotFoundError):
        OnnxFastSAMSegmenter(tmp_path / "nope.onnx")
