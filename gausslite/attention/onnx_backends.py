"""ONNX Runtime backends: Grounding-DINO-style open-vocabulary detector and FastSAM-style segmenter
(paper Sec. III-B: Grounding DINO box_threshold 0.20 / text_threshold 0.25; FastSAM conf 0.4,
iou 0.9). Models are loaded from user-given paths; nothing is downloaded.

Detector export contract (:class:`OnnxGroundingDetector`):
    inputs  image (1, 3, H, W) float32 normalised RGB (names: image, images, pixel_values, samples, img),
            input_ids (1, L) int64, and optionally attention_mask (1, L), token_type_ids (1, L),
            position_ids (1, L), text_self_attention_masks (1, L, L) bool (Grounding DINO's sub-sentence mask),
            pixel_mask (1, H, W) int64 (transformers' exports; fed with ones);
    outputs logits (1, Q, L') pre-sigmoid token logits (names: logits, pred_logits; L' >= number of text
            tokens) and boxes (1, Q, 4) normalised cx, cy, w, h (names: boxes, pred_boxes). Outputs named
            otherwise are recognised by shape when exactly one rank-3 output ends in 4 (boxes) and exactly
            one other rank-3 output shares its query axis (logits).
This covers the original Grounding DINO export (img, input_ids, attention_mask, position_ids,
token_type_ids, text_token_mask) and transformers' ``GroundingDinoForObjectDetection`` exported with
``torch.onnx.export`` (pixel_values, input_ids, attention_mask, token_type_ids; the sub-sentence mask is
computed inside the graph; :mod:`gausslite.attention.export`).
The caption is the phrases joined as ``"phrase a . phrase b ."`` (Grounding DINO convention) and tokenised
with a BERT WordPiece vocab (:class:`WordPieceTokenizer`). Post-processing: sigmoid; a query survives when
its best token probability > ``box_threshold``; its phrase is the one whose token span has the highest
probability, which must exceed ``text_threshold``; boxes are scaled to image pixels (xyxy) and
per-phrase NMS is applied.

Segmenter export contract (:class:`OnnxFastSAMSegmenter`, YOLOv8-seg/FastSAM layout, ultralytics'
``model.export(format="onnx")``):
    input   images (1, 3, h, w) float32 RGB in [0, 1], letterboxed (grey 114 padding, centred); square or
            rectangular; a dynamic input takes ultralytics' ``imgsz`` metadata, else 1024;
    outputs predictions (1, 4 + nc + nm, N) (cx, cy, w, h in input pixels, nc class scores, nm mask
            coefficients) and prototypes (1, nm, h/4, w/4). Exports with NMS inside (``nms=True``,
            end-to-end heads: predictions (1, max_det, 6 + nm)) are refused with the reason.
Post-processing: score > ``conf``, NMS at ``iou``, masks = sigmoid(coefficients · prototypes) upsampled,
cropped to their box, un-letterboxed, thresholded at ``mask_threshold``. Box prompts select, per box, the
candidate mask with the highest mask-vs-box IoU (FastSAM's box prompt).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from gausslite.attention.interfaces import Detections, FrameContext, mask_box_iou, nms
from gausslite.attention.tokenizer import WordPieceTokenizer

__all__ = ["OnnxGroundingDetector", "OnnxFastSAMSegmenter", "build_caption", "phrase_token_spans",
           "grounding_text_masks", "letterbox"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_IMAGE_NAMES = ("image", "images", "pixel_values", "samples", "img", "input")


def _session(path: Union[str, Path], providers: Optional[Sequence[str]], threads: Optional[int] = None):
    """ONNX Runtime session of ``path``; ``threads``: intra-op threads (None: ONNX Runtime's default).

    Raises:
        FileNotFoundError: no such file. ValueError: ONNX Runtime cannot load it (message names the file).
    """
    # lazy: heavy optional dependency, loaded only on this path
    import onnxruntime as ort

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"ONNX model not found: {p}")
    so = ort.SessionOptions()
    so.log_severity_level = 3
    if threads is not None:
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(p), so, providers=list(providers or ["CPUExecutionProvider"]))
    except Exception as e:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{p} is not a loadable ONNX model: {reason}") from None


def _static(dim) -> Optional[int]:
    return int(dim) if isinstance(dim, (int, np.integer)) and int(dim) > 0 else None


def build_caption(phrases: Sequence[str]) -> Tuple[str, List[Tuple[int, int]]]:
    """Grounding-DINO caption ``"a . b ."`` (lower-case) and each phrase's character span in it.

    Raises:
        ValueError: no phrases or an empty phrase.
    """
    if not phrases:
        raise ValueError("need at least one phrase")
    cap, spans = "", []
    for p in phrases:
        p = " ".join(str(p).lower().split())
        if not p:
            raise ValueError("empty phrase")
        spans.append((len(cap), len(cap) + len(p)))
        cap += p + " . "
    return cap.rstrip(), spans


def phrase_token_spans(offsets: Sequence[Tuple[int, int]], char_spans: Sequence[Tuple[int, int]]) -> List[List[int]]:
    """Token indices of each phrase: tokens whose (non-empty) character span lies inside the phrase's span."""
    out = []
    for s, e in char_spans:
        out.append([i for i, (a, b) in enumerate(offsets) if b > a and a >= s and b <= e])
    return out


def grounding_text_masks(tokens: Sequence[str], length: int) -> Tuple[np.ndarray, np.ndarray]:
    """Grounding DINO's sub-sentence attention mask and position ids.

    Special tokens ([CLS], [SEP], ".", [PAD]) attend only to themselves with position 0; the tokens of
    each phrase together with its closing "." attend to each other with positions 0, 1, ...

    Returns:
        (mask (1, L, L) bool, position_ids (1, L) int64) for ``length`` = L >= len(tokens).
    """
    L = int(length)
    mask = np.zeros((L, L), dtype=bool)
    pos = np.zeros(L, dtype=np.int64)
    np.fill_diagonal(mask, True)
    special = [i for i, t in enumerate(tokens) if t in ("[CLS]", "[SEP]", ".", "?", "!")]
    prev = special[0] if special else 0
    for col in special[1:]:
        if col - prev > 1:
            mask[prev + 1 : col + 1, prev + 1 : col + 1] = True
            pos[prev + 1 : col + 1] = np.arange(0, col - prev)
        prev = col
    return mask[None], pos[None]


def letterbox(image: np.ndarray, size: Union[int, Tuple[int, int]], pad_value: int = 114
              ) -> Tuple[np.ndarray, float, Tuple[int, int]]:
    """Resize (keeping aspect) and pad, centred, to ``size`` x ``size`` or to (h, w) = ``size``.

    Returns:
        (padded (h, w, 3) uint8, scale, (pad_x, pad_y) pixels of left/top padding).
    """
    sh, sw = (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))
    H, W = image.shape[:2]
    s = min(sh / H, sw / W)
    nw, nh = max(1, int(round(W * s))), max(1, int(round(H * s)))
    out = np.full((sh, sw, 3), pad_value, dtype=np.uint8)
    px, py = (sw - nw) // 2, (sh - nh) // 2
    out[py : py + nh, px : px + nw] = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR) if (nw, nh) != (W, H) else image
    return out, s, (px, py)


class OnnxGroundingDetector:
    """Open-vocabulary detector over an ONNX Grounding-DINO-style export (module docstring).

    Args:
        model_path: the ``.onnx`` file.
        vocab_path: BERT WordPiece ``vocab.txt`` of the model's text encoder.
        box_threshold: minimum best-token probability of a query (paper 0.20).
        text_threshold: minimum probability of the assigned phrase's tokens (paper 0.25).
        nms_iou: IoU of the per-phrase NMS.
        input_size: (H, W) network input; default: the model's static input size, else (800, 800).
        max_text_len: token limit (Grounding DINO: 256); a static text length of the model overrides it.
        mean, std: RGB normalisation (ImageNet).
        providers: ONNX Runtime execution providers (default CPU).
        threads: ONNX Runtime intra-op threads (None: its default, one per core).

    Raises:
        FileNotFoundError: model or vocab missing. ValueError: the file does not load, or the model's
        inputs/outputs do not follow the export contract (the message names the file).
    """

    def __init__(self, model_path, vocab_path, box_threshold: float = 0.20, text_threshold: float = 0.25,
                 nms_iou: float = 0.5, input_size: Optional[Tuple[int, int]] = None, max_text_len: int = 256,
                 mean=IMAGENET_MEAN, std=IMAGENET_STD, providers: Optional[Sequence[str]] = None,
                 threads: Optional[int] = None) -> None:
        self.model_path = Path(model_path)
        self.session = _session(model_path, providers, threads)
        try:
            self._check_contract()
        except ValueError as e:
            raise ValueError(f"{self.model_path}: {e}") from None
        self.tokenizer = WordPieceTokenizer(vocab_path)
        self.box_threshold = float(box_threshold)
        self.text_threshold = float(text_threshold)
        self.nms_iou = float(nms_iou)
        self.mean = np.asarray(mean, dtype=np.float32)
        self.std = np.asarray(std, dtype=np.float32)
        if input_size is None:
            h, w = self._image_hw
            input_size = (h, w) if h and w else (800, 800)
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self.max_text_len = self.text_len or int(max_text_len)

    def _check_contract(self) -> None:
        ins = {i.name: i for i in self.session.get_inputs()}
        img = [n for n in ins if n in _IMAGE_NAMES] or [n for n, i in ins.items() if len(i.shape) == 4]
        if len(img) != 1:
            raise ValueError(f"cannot identify the image input among {list(ins)}")
        self.image_name = img[0]
        if "input_ids" not in ins:
            raise ValueError(f"the model has no 'input_ids' input (inputs: {list(ins)})")
        known = {self.image_name, "input_ids", "attention_mask", "token_type_ids", "position_ids",
                 "text_self_attention_masks", "text_token_mask", "pixel_mask"}
        unknown = [n for n in ins if n not in known]
        if unknown:
            raise ValueError(f"unsupported model inputs {unknown}")
        self.input_names = list(ins)
        self.input_types = {n: i.type for n, i in ins.items()}
        shp = ins[self.image_name].shape
        if len(shp) != 4:
            raise ValueError(f"image input {self.image_name!r} must be (1, 3, H, W), got {shp}")
        self._image_hw = (_static(shp[2]), _static(shp[3]))
        if len(ins["input_ids"].shape) != 2:
            raise ValueError(f"input_ids must be (1, L), got {ins['input_ids'].shape}")
        self.text_len = _static(ins["input_ids"].shape[1])
        outputs = self.session.get_outputs()
        outs = [o.name for o in outputs]
        lg = [n for n in outs if n in ("logits", "pred_logits")]
        bx = [n for n in outs if n in ("boxes", "pred_boxes")]
        if len(lg) != 1 or len(bx) != 1:
            r3 = [o for o in outputs if len(o.shape) == 3]
            bx = [o.name for o in r3 if _static(o.shape[2]) == 4]
            lg = [o.name for o in r3 if o.name not in bx and (len(bx) != 1 or o.shape[1] == next(
                p.shape[1] for p in r3 if p.name == bx[0]))]
            if len(lg) != 1 or len(bx) != 1:
                raise ValueError(f"expected outputs 'logits'/'pred_logits' (1, Q, L) and 'boxes'/'pred_boxes' "
                                 f"(1, Q, 4), got {[(o.name, o.shape) for o in outputs]}")
        self.logits_name, self.boxes_name = lg[0], bx[0]

    def preprocess(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (1, 3, h, w) float32: resize to ``input_size``, /255, (x - mean) / std.

        Raises:
            ValueError: not an (H, W, 3) uint8 image.
        """
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        h, w = self.input_size
        x = cv2.resize(img, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        x = (x - self.mean) / self.std
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    def encode_text(self, phrases: Sequence[str]) -> Tuple[Dict[str, np.ndarray], List[List[int]], int]:
        """Model text inputs, each phrase's token indices, and the number of real tokens."""
        caption, cspans = build_caption(phrases)
        enc = self.tokenizer.encode(caption, max_length=self.max_text_len)
        n = len(enc.ids)
        L = self.text_len or n
        ids = np.full((1, L), self.tokenizer.pad_id, dtype=np.int64)
        ids[0, :n] = enc.ids
        att = np.zeros((1, L), dtype=np.int64)
        att[0, :n] = 1
        tokens = enc.tokens + ["[PAD]"] * (L - n)
        tmask, pos = grounding_text_masks(tokens, L)
        feeds = {"input_ids": ids, "attention_mask": att, "token_type_ids": np.zeros((1, L), dtype=np.int64),
                 "position_ids": pos, "text_self_attention_masks": tmask, "text_token_mask": att.astype(bool),
                 "pixel_mask": np.ones((1,) + self.input_size, dtype=np.int64)}
        spans = phrase_token_spans(enc.offsets, cspans)
        return feeds, spans, n

    def postprocess(self, logits: np.ndarray, boxes: np.ndarray, spans: List[List[int]], n_tokens: int,
                    image_hw: Tuple[int, int]) -> Detections:
        """Logits (Q, L') and normalised cxcywh boxes (Q, 4) -> thresholded, phrase-assigned, NMS'd detections."""
        logits = np.asarray(logits, dtype=np.float64).reshape(-1, np.asarray(logits).shape[-1])[:, :n_tokens]
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        prob = 1.0 / (1.0 + np.exp(-logits))
        qmax = prob.max(axis=1) if prob.size else np.zeros(len(boxes))
        H, W = image_hw
        out_b, out_s, out_p = [], [], []
        for q in np.flatnonzero(qmax > self.box_threshold):
            ps = [prob[q, s].max() if s else -1.0 for s in spans]
            pi = int(np.argmax(ps))
            if ps[pi] <= self.text_threshold:
                continue
            cx, cy, w, h = boxes[q]
            b = np.array([(cx - w / 2) * W, (cy - h / 2) * H, (cx + w / 2) * W, (cy + h / 2) * H])
            b[[0, 2]] = np.clip(b[[0, 2]], -0.5, W - 0.5)
            b[[1, 3]] = np.clip(b[[1, 3]], -0.5, H - 0.5)
            out_b.append(b)
            out_s.append(qmax[q])
            out_p.append(pi)
        if not out_b:
            return Detections.empty()
        det = Detections(np.stack(out_b), out_s, out_p)
        keep = []
        for pi in np.unique(det.phrase_ids):
            ix = np.flatnonzero(det.phrase_ids == pi)
            keep.extend(ix[nms(det.boxes[ix], det.scores[ix], self.nms_iou)])
        keep = np.asarray(sorted(keep, key=lambda i: -det.scores[i]), dtype=np.int64)
        return det.select(keep)

    def session_feeds(self, image: np.ndarray, phrases: Sequence[str]) -> Tuple[Dict[str, np.ndarray], List[List[int]], int]:
        """The ONNX Runtime feeds for ``image`` and ``phrases`` (every model input, in its dtype), each phrase's
        token indices and the number of real tokens."""
        x = self.preprocess(image)
        text, spans, n = self.encode_text(phrases)
        feeds = {self.image_name: x}
        for name in self.input_names:
            if name == self.image_name:
                continue
            v = text[name]
            t = self.input_types[name]
            feeds[name] = v.astype(bool) if "bool" in t else v.astype(np.int32) if "int32" in t else v.astype(np.int64) if "int64" in t else v.astype(np.float32)
        return feeds, spans, n

    def detect(self, image: np.ndarray, phrases: Sequence[str], context: Optional[FrameContext] = None) -> Detections:
        """Detect ``phrases`` in an (H, W, 3) uint8 RGB image; boxes in that image's pixels."""
        feeds, spans, n = self.session_feeds(image, phrases)
        logits, boxes = self.session.run([self.logits_name, self.boxes_name], feeds)
        return self.postprocess(np.asarray(logits)[0], np.asarray(boxes)[0], spans, n, np.asarray(image).shape[:2])


class OnnxFastSAMSegmenter:
    """Promptable segmenter over an ONNX FastSAM / YOLOv8-seg export (module docstring).

    Args:
        model_path: the ``.onnx`` file.
        conf: candidate score threshold (paper 0.4).
        iou: NMS IoU threshold among candidates (paper 0.9).
        imgsz: input size, int (square) or (h, w); default: the model's static size, else ultralytics'
            ``imgsz`` metadata, else 1024.
        mask_threshold: probability threshold of the upsampled masks.
        providers: ONNX Runtime execution providers.
        threads: ONNX Runtime intra-op threads (None: its default, one per core).

    Attributes:
        input_hw: (h, w) network input, pixels. imgsz: h (kept for square models).

    Raises:
        FileNotFoundError: model missing. ValueError: the file does not load, or its outputs are not in
        the YOLOv8-seg layout (the message names the file and the reason).
    """

    def __init__(self, model_path, conf: float = 0.4, iou: float = 0.9,
                 imgsz: Optional[Union[int, Tuple[int, int]]] = None, mask_threshold: float = 0.5,
                 providers: Optional[Sequence[str]] = None, threads: Optional[int] = None) -> None:
        self.model_path = Path(model_path)
        self.session = _session(model_path, providers, threads)
        self.conf, self.iou, self.mask_threshold = float(conf), float(iou), float(mask_threshold)
        try:
            self._check_contract(imgsz)
        except ValueError as e:
            raise ValueError(f"{self.model_path}: {e}") from None

    def _check_contract(self, imgsz) -> None:
        ins = self.session.get_inputs()
        if len(ins) != 1 or len(ins[0].shape) != 4:
            raise ValueError(f"expected one (1, 3, h, w) image input, got {[(i.name, i.shape) for i in ins]}")
        self.input_name = ins[0].name
        meta = self.session.get_modelmeta().custom_metadata_map or {}
        args = str(meta.get("args", ""))
        if "'nms': True" in args or str(meta.get("end2end", "")).lower() == "true":
            raise ValueError("the export has NMS / an end-to-end head inside (predictions (1, max_det, 6 + nm)); "
                             "export with nms=False from a YOLOv8-seg or FastSAM model")
        if imgsz is None:
            h, w = _static(ins[0].shape[2]), _static(ins[0].shape[3])
            if not (h and w):
                nums = [int(v) for v in str(meta.get("imgsz", "")).strip("[]() ").replace(",", " ").split() if v.isdigit()]
                h, w = (nums[0], nums[-1]) if nums else (1024, 1024)
            imgsz = (h, w)
        self.input_hw = (int(imgsz), int(imgsz)) if np.isscalar(imgsz) else (int(imgsz[0]), int(imgsz[1]))
        self.imgsz = self.input_hw[0]
        outs = self.session.get_outputs()
        ranks = {o.name: len(o.shape) for o in outs}
        pr = [n for n, r in ranks.items() if r == 3]
        pt = [n for n, r in ranks.items() if r == 4]
        if len(pr) != 1 or len(pt) != 1:
            raise ValueError(f"expected a 3-D prediction output and a 4-D prototype output, got "
                             f"{[(o.name, o.shape) for o in outs]}")
        self.pred_name, self.proto_name = pr[0], pt[0]

    def preprocess(self, image: np.ndarray) -> Tuple[np.ndarray, float, Tuple[int, int]]:
        """(H, W, 3) uint8 RGB -> ((1, 3, S, S) float32 in [0, 1], scale, (pad_x, pad_y))."""
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        lb, s, pad = letterbox(img, self.input_hw)
        return np.ascontiguousarray(lb.astype(np.float32).transpose(2, 0, 1)[None] / 255.0), s, pad

    def postprocess(self, pred: np.ndarray, protos: np.ndarray, scale: float, pad: Tuple[int, int],
                    image_hw: Tuple[int, int], near: Optional[np.ndarray] = None
                    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predictions (C, N) and prototypes (nm, mh, mw) -> (masks (M, H, W) bool, boxes (M, 4) xyxy pixels
        of the original image, scores (M,)), sorted by score.

        ``near``: optional (K, 4) xyxy boxes of the original image; only candidates whose box (grown by 2 px)
        overlaps one of them are turned into masks (the others' masks, cropped to their boxes, cannot
        overlap these boxes)."""
        pred = np.asarray(pred, dtype=np.float64)
        protos = np.asarray(protos, dtype=np.float64)
        nm, mh, mw = protos.shape
        if pred.shape[0] < 4 + 1 + nm and pred.shape[1] >= 4 + 1 + nm:
            pred = pred.T
        C = pred.shape[0]
        nc = C - 4 - nm
        if nc < 1:
            raise ValueError(f"prediction has {C} channels, too few for 4 + classes + {nm} coefficients")
        H, W = image_hw
        Sh, Sw = self.input_hw
        scores = pred[4 : 4 + nc].max(axis=0)
        sel = np.flatnonzero(scores > self.conf)
        if len(sel) == 0:
            return np.zeros((0, H, W), dtype=bool), np.zeros((0, 4), np.float32), np.zeros(0, np.float32)
        cx, cy, w, h = pred[0:4, sel]
        bx = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
        keep = nms(bx, scores[sel], self.iou)
        sel, bx = sel[keep], bx[keep]
        if near is not None:
            nb = np.asarray(near, dtype=np.float64).reshape(-1, 4)
            ob = (bx - np.array([pad[0], pad[1], pad[0], pad[1]])) / scale - 0.5 + np.array([-2.0, -2.0, 2.0, 2.0])
            hit = ((ob[:, None, 0] < nb[None, :, 2]) & (ob[:, None, 2] > nb[None, :, 0])
                   & (ob[:, None, 1] < nb[None, :, 3]) & (ob[:, None, 3] > nb[None, :, 1])).any(axis=1)
            sel, bx = sel[hit], bx[hit]
            if len(sel) == 0:
                return np.zeros((0, H, W), dtype=bool), np.zeros((0, 4), np.float32), np.zeros(0, np.float32)
        coef = pred[4 + nc :, sel].T  # (M, nm)
        m = 1.0 / (1.0 + np.exp(-(coef @ protos.reshape(nm, -1)))).reshape(-1, mh, mw)
        px, py = pad
        nw, nh = int(round(W * scale)), int(round(H * scale))
        masks = np.zeros((len(sel), H, W), dtype=bool)
        boxes = np.zeros((len(sel), 4), dtype=np.float32)
        yy, xx = np.mgrid[0:Sh, 0:Sw]
        for k in range(len(sel)):
            up = cv2.resize(m[k].astype(np.float32), (Sw, Sh), interpolation=cv2.INTER_LINEAR)
            x0, y0, x1, y1 = bx[k]
            up = np.where((xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1), up, 0.0).astype(np.float32)
            crop = up[py : py + nh, px : px + nw]
            masks[k] = cv2.resize(crop, (W, H), interpolation=cv2.INTER_LINEAR) > self.mask_threshold
            boxes[k] = [(x0 - px) / scale - 0.5, (y0 - py) / scale - 0.5, (x1 - px) / scale - 0.5, (y1 - py) / scale - 0.5]
        return masks, boxes, scores[sel].astype(np.float32)

    def segment_everything(self, image: np.ndarray, near: Optional[np.ndarray] = None
                           ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All candidate masks of an image: (masks (M, H, W) bool, boxes (M, 4), scores (M,)); with ``near``
        (K, 4) xyxy, only the candidates whose box overlaps one of those boxes."""
        x, s, pad = self.preprocess(image)
        outs = dict(zip([o.name for o in self.session.get_outputs()], self.session.run(None, {self.input_name: x})))
        return self.postprocess(outs[self.pred_name][0], outs[self.proto_name][0], s, pad, np.asarray(image).shape[:2],
                                near=near)

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        """(K, H, W) bool: per prompt box (K, 4) xyxy, the candidate mask with the highest mask-vs-box IoU
        (empty when no candidate overlaps the box)."""
        boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
        H, W = np.asarray(image).shape[:2]
        out = np.zeros((len(boxes), H, W), dtype=bool)
        if len(boxes) == 0:
            return out
        masks, _, _ = self.segment_everything(image, near=boxes)
        if len(masks) == 0:
            return out
        iou = mask_box_iou(masks, boxes)  # (M, K)
        for k in range(len(boxes)):
            j = int(np.argmax(iou[:, k]))
            if iou[j, k] > 0:
                out[k] = masks[j]
        return out
