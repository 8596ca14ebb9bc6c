"""Unit tests of the attention front-end building blocks."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.attention import (
    GrabCutSegmenter,
    KeyframeConfig,
    KeyframeTrigger,
    PhraseMatcher,
    WordPieceTokenizer,
    box_iou,
    filter_boxes_by_area,
    mask_iou,
    match_masks_to_boxes,
    max_box_fraction_for,
    nms,
    normalize_phrase,
    reproject_box,
)
from gausslite.camera import Intrinsics


def _pose(t=(0, 0, 0), yaw_deg=0.0):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def test_keyframe_trigger_translation_rotation_and_every_k():
    trig = KeyframeTrigger(KeyframeConfig(translation_m=1.0, rotation_deg=15.0, every_k=5))
    assert trig.update(_pose()) is True  # first frame
    assert trig.update(_pose((0.5, 0, 0))) is False
    assert trig.update(_pose((1.2, 0, 0))) is True  # > 1 m from the last keyframe
    assert trig.update(_pose((1.2, 0, 0), yaw_deg=10)) is False
    assert trig.update(_pose((1.2, 0, 0), yaw_deg=16)) is True  # > 15 deg
    fired = [trig.update(_pose((1.2, 0, 0), yaw_deg=16)) for _ in range(5)]
    assert fired == [False, False, False, False, True]  # every 5 frames
    with pytest.raises(ValueError):
        KeyframeConfig(every_k=0)
    assert KeyframeConfig().translation_m == 1.0 and KeyframeConfig().rotation_deg == 15.0


def test_box_filter_by_area():
    boxes = np.array([[0, 0, 10, 10], [0, 0, 50, 50], [-20, -20, 200, 200]], dtype=np.float32)
    keep = filter_boxes_by_area(boxes, (100, 100), 0.2)
    assert keep.tolist() == [True, False, False]
    keep = filter_boxes_by_area(boxes, (100, 100), [0.2, 0.4, 1.0])
    assert keep.tolist() == [True, True, True]
    with pytest.raises(ValueError):
        filter_boxes_by_area(boxes, (100, 100), 0.0)
    assert max_box_fraction_for("cup", 1) == 0.20
    assert max_box_fraction_for("side tables", 1) == 0.40
    assert max_box_fraction_for("cup", 3) == 0.70


def test_iou_nms_and_mask_matching():
    a = np.array([[0, 0, 10, 10]], dtype=np.float32)
    b = np.array([[5, 0, 15, 10], [20, 20, 30, 30]], dtype=np.float32)
    np.testing.assert_allclose(box_iou(a, b), [[50 / 150, 0.0]])
    assert nms(np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]]), np.array([0.9, 0.8, 0.7]), 0.5).tolist() == [0, 2]
    H, W = 40, 60
    m = np.zeros((3, H, W), bool)
    m[0, 5:15, 5:15] = True   # object A
    m[1, 20:35, 30:50] = True  # object B
    m[2, 0:2, 0:2] = True      # clutter
    boxes = np.array([[29.5, 19.5, 49.5, 34.5], [4.5, 4.5, 14.5, 14.5]], dtype=np.float32)
    assert match_masks_to_boxes(m, boxes).tolist() == [1, 0]
    np.testing.assert_allclose(mask_iou(m[:1], m[:2]), [[1.0, 0.0]])
    # a box with no overlapping mask gets -1
    assert match_masks_to_boxes(m[:1], boxes).tolist() == [-1, 0]


def test_reprojection_through_frustum_matches_direct_projection():
    intr = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)
    c2w_a = _pose()
    c2w_b = _pose((0.1, 0.05, 0.2), yaw_deg=-4)
    # a fronto-parallel square at z = 2 m in frame A
    sq = np.array([[-0.2, -0.1, 2.0], [0.2, -0.1, 2.0], [0.2, 0.3, 2.0], [-0.2, 0.3, 2.0]])
    u = intr.fx * sq[:, 0] / sq[:, 2] + intr.cx
    v = intr.fy * sq[:, 1] / sq[:, 2] + intr.cy
    box_a = np.array([u.min(), v.min(), u.max(), v.max()])
    got = reproject_box(box_a, 2.0, 2.0, c2w_a, intr, c2w_b, intr)
    pc = (sq - c2w_b[:3, 3]) @ c2w_b[:3, :3]
    ub = intr.fx * pc[:, 0] / pc[:, 2] + intr.cx
    vb = intr.fy * pc[:, 1] / pc[:, 2] + intr.cy
    np.testing.assert_allclose(got, [ub.min(), vb.min(), ub.max(), vb.max()], atol=1e-3)
    assert np.abs(got - box_a).max() > 5  # the camera really moved
    # camera turned around: nothing in front
    assert reproject_box(box_a, 2.0, 2.0, c2w_a, intr, _pose(yaw_deg=180), intr) is None


def test_grabcut_bright_rectangle():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 40, size=(90, 120, 3)).astype(np.uint8)
    img[30:60, 40:90] = rng.integers(200, 255, size=(30, 50, 3)).astype(np.uint8)
    gt = np.zeros((90, 120), bool)
    gt[30:60, 40:90] = True
    masks = GrabCutSegmenter().segment(img, np.array([[30, 20, 100, 70]], dtype=np.float32))
    assert masks.shape == (1, 90, 120) and masks.dtype == bool
    assert mask_iou(masks, gt[None])[0, 0] > 0.8


def test_wordpiece_tokenizer():
    vocab = {t: i for i, t in enumerate(["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "side", "table", "##s", "cup"])}
    tok = WordPieceTokenizer(vocab)
    enc = tok.encode("Side tables . cup")
    assert enc.tokens == ["[CLS]", "side", "table", "##s", ".", "cup", "[SEP]"]
    assert enc.ids == [2, 5, 6, 7, 4, 8, 3]
    assert enc.offsets[2] == (5, 10) and enc.offsets[3] == (10, 11)
    assert tok.encode("zebra").tokens == ["[CLS]", "[UNK]", "[SEP]"]


@pytest.fixture(scope="module")
def matcher():
    return PhraseMatcher()


def test_phrase_normalisation():
    assert normalize_phrase("The Ottomans") == "ottoman"
    assert normalize_phrase("books") == "book"
    assert normalize_phrase("all obstacles") == "obstacle"
    assert normalize_phrase("shelves") == "shelf"


def test_phrase_matching_positives(matcher):
    room = {
        "potted plant": ["potted plant", "plant", "flower pot"],
        "side table": ["side table", "table", "obstacle"],
        "sideboard": ["sideboard", "cabinet", "console table", "obstacle"],
        "books": ["books", "book", "stack of books"],
        "monitor": ["monitor", "screen", "display"],
        "lantern": ["lantern", "candle holder"],
    }
    names = list(room)
    ents = list(room.values())

    def hits(p):
        return {names[j] for j, _ in matcher.match([p], ents)[0]}

    assert hits("obstacles") == {"side table", "sideboard"}
    assert hits("plant") == {"potted plant"}
    assert hits("book") == {"books"}
    assert hits("monitors") == {"monitor"} and hits("screen") == {"monitor"}
    assert hits("side table") == {"side table"}  # not the sideboard
    assert "lantern" in hits("lantern")
    # embedding-only synonym (no lexical overlap)
    assert matcher.uses_embeddings
    assert matcher.score("couch", ["sofa"]) >= matcher.config.threshold


def test_phrase_matching_negatives(matcher):
    assert matcher.score("gamepad", ["keyboard", "computer keyboard", "keys"]) < matcher.config.threshold
    assert matcher.score("lantern", ["lamp", "floor lamp"]) < matcher.config.threshold
    assert matcher.score("mouse", ["phone", "telephone"]) < matcher.config.threshold
    # "cup" must not pick the pen holder (synonym "pen cup") when a real cup is present
    res = matcher.match(["cup"], [["cup", "mug"], ["pen holder", "pen cup", "pens"]])[0]
    assert [j for j, _ in res] == [0]
    # threshold is configurable: with 0.5 the gamepad/keyboard pair would pass
    from gausslite.attention import PhraseMatcherConfig
    loose = PhraseMatcher(PhraseMatcherConfig(threshold=0.5, relative_margin=None), embedder=matcher.embedder)
    assert loose.match(["gamepad"], [["keyboard"]])[0]
