"""Real architectures through the ONNX backends: transformers' Grounding DINO exported with torch.onnx and
ultralytics' YOLOv8n-seg exported with ``model.export(format="onnx")``, both reduced in size and with random
weights (nothing downloaded). With random weights the detections mean nothing, so the tests check the
structure: input/output names and shapes, text encoding, thresholds, box scaling and mask geometry."""

from __future__ import annotations

import numpy as np
import pytest

from tests._real_models import DET_SIZE, WORDS, need

H_DET, W_DET = DET_SIZE


@pytest.fixture(scope="module")
def gdino(exported_models):
    """The tiny Grounding DINO exported by ``gausslite export models`` (at :data:`DET_SIZE`) and the model it was
    exported from, loaded again from its checkpoint folder."""
    torch = need("torch")
    from gausslite.attention.export import load_grounding_dino

    assert exported_models["rc"] == 0, exported_models["err"]
    out = exported_models["out"]
    model = load_grounding_dino(exported_models["checkpoint"])
    return model, out / "detector.onnx", out / "vocab.txt", torch


@pytest.fixture(scope="module")
def yolo(tmp_path_factory):
    torch = need("torch")
    need("ultralytics")
    from gausslite.attention.export import export_yolo_seg

    torch.manual_seed(0)  # the random weights
    d = tmp_path_factory.mktemp("yolo")
    return {"rect": export_yolo_seg("yolov8n-seg.yaml", d / "rect.onnx", imgsz=(128, 160)),
            "square": export_yolo_seg("yolov8n-seg.yaml", d / "square.onnx", imgsz=160)}


def test_text_mask_matches_transformers():
    torch = need("torch")
    need("transformers")
    from transformers.models.grounding_dino import modeling_grounding_dino as mg

    from gausslite.attention.export import BERT_SPECIAL_IDS, grounding_text_mask_exportable

    g = torch.Generator().manual_seed(0)
    pool = torch.tensor([0, 7, 2000, *BERT_SPECIAL_IDS])
    for L in (2, 5, 12, 40):
        ids = pool[torch.randint(0, len(pool), (3, L), generator=g)]
        ref = mg.generate_masks_with_special_tokens_and_transfer_map(ids, torch.tensor(BERT_SPECIAL_IDS))
        got = grounding_text_mask_exportable(ids)
        assert torch.equal(ref[0], got[0]) and torch.equal(ref[1], got[1])


def test_grounding_dino_export_loads_and_matches_torch(gdino):
    model, path, vocab, torch = gdino
    from gausslite.attention import OnnxGroundingDetector

    det = OnnxGroundingDetector(path, vocab)
    assert det.image_name == "pixel_values" and (det.logits_name, det.boxes_name) == ("logits", "pred_boxes")
    assert det.input_size == (H_DET, W_DET) and det.text_len is None  # text length is dynamic
    assert set(det.input_names) == {"pixel_values", "input_ids", "attention_mask", "token_type_ids"}
    phrases = ["red cup", "desk", "computer mouse"]
    feeds, spans, n = det.encode_text(phrases)
    # our tokenizer gives the ids transformers' BertTokenizer gives for the Grounding DINO caption
    from transformers import BertTokenizer

    ref_ids = BertTokenizer(str(vocab))("red cup . desk . computer mouse .")["input_ids"]
    assert feeds["input_ids"][0].tolist() == ref_ids and n == len(ref_ids)
    w = {t: 2000 + i for i, t in enumerate(WORDS)}
    assert [feeds["input_ids"][0][s].tolist() for s in spans] == [[w["red"], w["cup"]], [w["desk"]],
                                                                  [w["computer"], w["mouse"]]]
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (120, 200, 3), dtype=np.uint8)
    x = det.preprocess(img)
    sess_feeds = {"pixel_values": x, **{k: feeds[k] for k in ("input_ids", "attention_mask", "token_type_ids")}}
    logits, boxes = det.session.run(["logits", "pred_boxes"], sess_feeds)
    Q = model.config.num_queries
    assert logits.shape == (1, Q, model.config.max_text_len) and boxes.shape == (1, Q, 4)
    with torch.no_grad():
        ref = model(pixel_values=torch.from_numpy(x), input_ids=torch.from_numpy(feeds["input_ids"]),
                    attention_mask=torch.from_numpy(feeds["attention_mask"]),
                    token_type_ids=torch.from_numpy(feeds["token_type_ids"]))
    np.testing.assert_allclose(logits[0, :, :n], ref.logits.numpy()[0, :, :n], atol=2e-4)
    np.testing.assert_allclose(boxes, ref.pred_boxes.numpy(), atol=2e-4)
    assert np.all(np.isneginf(logits[0, :, n:]))  # padded token positions are masked by the model

    # thresholds: with NMS off (IoU 1), detections are exactly the queries passing both thresholds
    prob = 1 / (1 + np.exp(-logits[0, :, :n].astype(np.float64)))
    qmax = prob.max(1)
    for bt, tt in [(0.0, 0.0), (float(np.median(qmax)), 0.0), (float(np.median(qmax)), float(np.quantile(qmax, 0.8)))]:
        det.box_threshold, det.text_threshold, det.nms_iou = bt, tt, 1.0
        d = det.detect(img, phrases)
        best = np.array([max(prob[q, s].max() for s in spans) for q in range(Q)])
        expect = (qmax > bt) & (best > tt)
        assert len(d) == int(expect.sum())
        assert np.all(d.scores > bt) and np.all(np.diff(d.scores) <= 1e-7)
        assert d.phrase_ids.min(initial=0) >= 0 and d.phrase_ids.max(initial=0) < len(phrases)
        assert np.all(d.boxes[:, [0, 2]] >= -0.5) and np.all(d.boxes[:, [0, 2]] <= 199.5)
        assert np.all(d.boxes[:, [1, 3]] >= -0.5) and np.all(d.boxes[:, [1, 3]] <= 119.5)
    # boxes: normalised cxcywh scaled to the original image (not the network input)
    q = int(np.argmax(qmax))
    cx, cy, bw, bh = boxes[0, q]
    det.box_threshold, det.text_threshold = 0.0, 0.0
    d = det.detect(img, phrases)
    exp = np.clip([(cx - bw / 2) * 200, (cy - bh / 2) * 120, (cx + bw / 2) * 200, (cy + bh / 2) * 120],
                  -0.5, [199.5, 119.5, 199.5, 119.5])
    np.testing.assert_allclose(d.boxes[0], exp, atol=1e-2)


def test_yolov8_seg_export_loads(yolo):
    from gausslite.attention import OnnxFastSAMSegmenter
    from gausslite.attention.onnx_backends import letterbox

    seg = OnnxFastSAMSegmenter(yolo["rect"])
    assert seg.input_hw == (128, 160) and (seg.pred_name, seg.proto_name) == ("output0", "output1")
    assert (seg.conf, seg.iou) == (0.4, 0.9)
    outs = {o.name: o.shape for o in seg.session.get_outputs()}
    assert outs["output1"] == [1, 32, 32, 40]  # 32 prototypes at 1/4 of the input
    assert outs["output0"][1] == 4 + 80 + 32  # cx cy w h, 80 class scores, 32 mask coefficients
    sq = OnnxFastSAMSegmenter(yolo["square"])
    assert sq.input_hw == (160, 160)

    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    x, s, pad = seg.preprocess(img)
    assert x.shape == (1, 3, 128, 160) and s == pytest.approx(0.5) and pad == (0, 4)
    assert np.allclose(x[0, :, :4], 114 / 255) and np.allclose(x[0, :, -4:], 114 / 255)
    lb, _, _ = letterbox(img, (128, 160))
    np.testing.assert_allclose(x[0].transpose(1, 2, 0) * 255, lb, atol=1e-3)
    pred, protos = seg.session.run([seg.pred_name, seg.proto_name], {seg.input_name: x})
    scores_raw = pred[0, 4:84].max(0)
    seg.conf, seg.iou = float(np.quantile(scores_raw, 0.9)), 1.0  # NMS off: exactly the candidates above conf
    masks, boxes, scores = seg.segment_everything(img)
    assert masks.shape == (int((scores_raw > seg.conf).sum()), 240, 320) and masks.dtype == bool
    assert np.all(scores > seg.conf) and np.all(np.diff(scores) <= 0)
    # the best candidate's box, un-letterboxed: (input box - pad) / scale, in pixel-edge coordinates
    k = int(np.argmax(scores_raw))
    cx, cy, bw, bh = pred[0, :4, k]
    np.testing.assert_allclose(boxes[0], [(cx - bw / 2 - 0) / s - 0.5, (cy - bh / 2 - 4) / s - 0.5,
                                          (cx + bw / 2 - 0) / s - 0.5, (cy + bh / 2 - 4) / s - 0.5], atol=1e-2)
    # every mask lies inside its box (masks are cropped to their box; 1 px of resampling slack)
    for m, b in zip(masks, boxes):
        ys, xs = np.nonzero(m)
        if len(xs):
            assert xs.min() >= b[0] - 1.5 and xs.max() <= b[2] + 1.5 and ys.min() >= b[1] - 1.5 and ys.max() <= b[3] + 1.5
    # box prompts: per box, the candidate with the highest mask-vs-box IoU; only candidates near the prompts
    # are turned into masks, which must not change the answer
    from gausslite.attention.interfaces import mask_box_iou

    prompts = np.concatenate([boxes[:3], [[0, 0, 40, 30], [150, 100, 250, 200], [300, 220, 319, 239]]]).astype(np.float32)
    out = seg.segment(img, prompts)
    assert out.shape == (len(prompts), 240, 320)
    iou = mask_box_iou(masks, prompts)
    for k in range(len(prompts)):
        j = int(np.argmax(iou[:, k]))
        np.testing.assert_array_equal(out[k], masks[j] if iou[j, k] > 0 else np.zeros((240, 320), bool))


def test_bad_model_files_name_the_file(tmp_path, gdino):
    from gausslite.attention import OnnxFastSAMSegmenter, OnnxGroundingDetector

    _, det_path, vocab, _ = gdino
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not an onnx file")
    with pytest.raises(ValueError, match="junk.onnx is not a loadable ONNX model"):
        OnnxFastSAMSegmenter(junk)
    with pytest.raises(ValueError, match="junk.onnx is not a loadable ONNX model"):
        OnnxGroundingDetector(junk, vocab)
    # a detector given as the segmenter: refused with the file and the reason
    with pytest.raises(ValueError, match=r"detector\.onnx: expected one \(1, 3, h, w\) image input"):
        OnnxFastSAMSegmenter(det_path)
