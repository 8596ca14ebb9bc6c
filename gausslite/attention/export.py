"""Exporting real detector and segmenter networks to the ONNX files the ONNX backends load
(:mod:`gausslite.attention.onnx_backends`); used by ``gausslite export models``, the tests and
the retired ``bench.frontend`` (docs/history.md#frontend). Nothing here downloads anything: sources are local
folders/files, or hub ids that are
already in the local Hugging Face cache (``local_files_only=True``) or, when the caller allows it, that the
machine can reach.

Detector: Grounding DINO through transformers (``GroundingDinoForObjectDetection``). The export has inputs
``pixel_values (1, 3, H, W)`` float32, ``input_ids``, ``attention_mask``, ``token_type_ids`` (1, L) int64 with
L dynamic, and outputs ``logits (1, Q, 256)``, ``pred_boxes (1, Q, 4)``. Plain ``torch.onnx.export`` of the
transformers model fails with torch 2.13: the TorchScript exporter has no ``aten::isin``, and the dynamo
exporter has no ``aten::cummax``/``aten::cummin`` (both used by the text sub-sentence mask) nor the
``aten::_is_all_true`` of transformers' runtime shape checks. :func:`exportable_grounding_dino` swaps the mask
function for an equivalent one made of comparisons and reductions (the same outputs, checked in the tests),
switches transformers' checks off (``TRANSFORMERS_DISABLE_TORCH_CHECK=1``) and uses eager attention.

Segmenter: YOLOv8-seg / FastSAM through ultralytics (``YOLO(path).export(format="onnx")``), inputs
``images (1, 3, h, w)``, outputs ``output0 (1, 4 + nc + 32, N)`` and ``output1 (1, 32, h/4, w/4)``.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

__all__ = ["MissingModelFiles", "import_ultralytics", "exportable_grounding_dino", "grounding_text_mask_exportable",
           "load_grounding_dino", "export_grounding_dino", "write_vocab", "export_yolo_seg", "ExportedModels",
           "export_models", "GDINO_FILES", "BERT_SPECIAL_IDS"]

log = logging.getLogger(__name__)

#: files a Grounding DINO checkpoint folder must hold (weights in either format)
GDINO_FILES = ("config.json", "model.safetensors | pytorch_model.bin", "vocab.txt")
#: BERT ids of [CLS], [SEP], "." and "?": the delimiters of Grounding DINO's sub-sentence text mask
BERT_SPECIAL_IDS = (101, 102, 1012, 1029)


class MissingModelFiles(FileNotFoundError):
    """A model source lacks files (or is not reachable offline). ``needed`` lists what the user must provide.

    Attributes:
        source: the source as given (folder, file or hub id).
        needed: human-readable list of the files needed.
    """

    def __init__(self, source: str, needed: Sequence[str], hint: str = "") -> None:
        self.source = str(source)
        self.needed = list(needed)
        msg = f"{source}: missing {', '.join(self.needed)}"
        super().__init__(msg + (f". {hint}" if hint else ""))


# ------------------------------------------------------------------------------------------ ultralytics
def import_ultralytics():
    """Import ``ultralytics`` (with its auto-install and online checks off) and return the module.

    ultralytics reads torchvision's installed version when it is imported, but building a model from its
    YAML or a ``.pt`` and exporting it to ONNX never imports torchvision. On a CPU-only torch there is no
    matching torchvision wheel on PyPI (the PyPI wheel is a CUDA build whose ops do not load without CUDA
    torch, and a broken torchvision also breaks transformers), so GaussLite installs ultralytics without
    torchvision; then the version lookup answers, for torchvision only and only during the import, the
    release that pairs with the installed torch. ultralytics' training/NMS paths that really use
    torchvision stay unavailable.

    Raises:
        ImportError: ultralytics is not installed.
    """
    os.environ.setdefault("YOLO_OFFLINE", "1")
    os.environ.setdefault("YOLO_AUTOINSTALL", "False")
    os.environ.setdefault("YOLO_VERBOSE", "False")
    try:
        importlib.metadata.version("torchvision")
        patch = False
    except importlib.metadata.PackageNotFoundError:
        patch = True
    if not patch:
        # lazy: heavy optional dependency, loaded only on this path
        import ultralytics

        return ultralytics
    # lazy: keeps gausslite.attention.export importable without torch
    import torch

    major, minor = (int(v) for v in torch.__version__.split("+")[0].split(".")[:2])
    paired = f"0.{minor + 15}.0" if major == 2 else "0.0.0"
    real = importlib.metadata.version

    def version(name):
        return paired if name == "torchvision" else real(name)

    importlib.metadata.version = version
    try:
        # lazy: heavy optional dependency, loaded only on this path
        import ultralytics
        import ultralytics.utils  # noqa: F401  (reads the version at import)
        import ultralytics.utils.checks  # noqa: F401
        import ultralytics.utils.torch_utils  # noqa: F401
    finally:
        importlib.metadata.version = real
    return ultralytics


def export_yolo_seg(source: Union[str, Path], out_path: Union[str, Path],
                    imgsz: Union[int, Tuple[int, int]] = 640, opset: Optional[int] = None) -> Path:
    """Export a YOLOv8-seg / FastSAM model to ONNX with ultralytics (``model.export(format="onnx")``).

    Args:
        source: an ultralytics ``.pt`` checkpoint (must exist locally: ultralytics would otherwise try to
            download it) or a model ``.yaml`` (a file, or a name ultralytics ships such as
            ``yolov8s-seg.yaml``: random weights).
        out_path: the ``.onnx`` to write.
        imgsz: square size or (h, w) of the network input, rounded up by ultralytics to multiples of 32.
        opset: ONNX opset (None: ultralytics' default).

    Returns:
        ``out_path``.

    Raises:
        MissingModelFiles: a ``.pt`` that does not exist. ImportError: ultralytics not installed.
        ValueError: a source that is neither ``.pt`` nor ``.yaml``, or a model that is not a segmenter.
    """
    src = str(source)
    suffix = Path(src).suffix.lower()
    if suffix not in (".pt", ".yaml", ".yml"):
        raise ValueError(f"segmenter source must be an ultralytics .pt or .yaml, got {src}")
    if suffix == ".pt" and not Path(src).is_file():
        raise MissingModelFiles(src, [Path(src).name],
                                "Copy the ultralytics checkpoint (e.g. FastSAM-s.pt or yolov8s-seg.pt from the "
                                "ultralytics assets release) to this path")
    if suffix != ".pt" and os.sep in src and not Path(src).is_file():
        raise MissingModelFiles(src, [Path(src).name])
    import_ultralytics()
    # lazy: heavy optional dependency, loaded only on this path
    from ultralytics import YOLO

    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    model = YOLO(src, task="segment")
    if getattr(model, "task", None) != "segment":
        raise ValueError(f"{src} is a '{model.task}' model, not a segmentation model")
    work = out.parent / f".export-{out.stem}"
    work.mkdir(parents=True, exist_ok=True)
    try:
        with _chdir(work):
            kw = dict(format="onnx", imgsz=imgsz, simplify=False, dynamic=False, nms=False, half=False, device="cpu")
            if opset is not None:
                kw["opset"] = int(opset)
            produced = Path(model.export(**kw))
            produced = produced if produced.is_absolute() else work / produced
        shutil.move(str(produced), out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out


@contextlib.contextmanager
def _chdir(path: Path) -> Iterator[None]:
    prev = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(prev)


# ------------------------------------------------------------------------------------------ Grounding DINO
def grounding_text_mask_exportable(input_ids, special_tokens=None):
    """Grounding DINO's sub-sentence text mask and position ids without ``isin``/``cummax``/``cummin``.

    Same results as transformers' ``generate_masks_with_special_tokens_and_transfer_map`` (a token attends
    to the tokens of its phrase, up to and including the next delimiter; delimiters and padding attend to
    themselves; positions count from the previous delimiter), built from comparisons and masked max/min
    over an (L, L) triangle, which every ONNX exporter handles. O(L²) memory, L <= 256.

    Args:
        input_ids: (B, L) int64 token ids.
        special_tokens: (S,) int64 delimiter ids (default :data:`BERT_SPECIAL_IDS`).

    Returns:
        (attention mask (B, L, L) bool, position ids (B, L) int64).
    """
    # lazy: keeps gausslite.attention.export importable without torch
    import torch

    if special_tokens is None:
        special_tokens = torch.tensor(BERT_SPECIAL_IDS, dtype=torch.long, device=input_ids.device)
    batch, seq_len = input_ids.shape
    device = input_ids.device
    special = (input_ids.unsqueeze(-1) == special_tokens.to(input_ids.dtype).view(1, 1, -1)).any(-1)
    idx = torch.arange(seq_len, device=device).unsqueeze(0).expand(batch, -1)
    tri = torch.ones(seq_len, seq_len, dtype=torch.bool, device=device).tril()  # [i, j]: j <= i
    neg = torch.full_like(idx, -1)
    prev = torch.where(special, idx, neg)
    prev = torch.where(tri.unsqueeze(0), prev.unsqueeze(1), neg.unsqueeze(1)).amax(-1)
    prev = torch.cat([prev.new_full((batch, 1), -1), prev[:, :-1]], dim=1)
    big = torch.full_like(idx, seq_len)
    nxt = torch.where(special, idx, big)
    nxt = torch.where(tri.T.unsqueeze(0), nxt.unsqueeze(1), big.unsqueeze(1)).amin(-1)
    valid = (nxt != 0) & (nxt != seq_len - 1) & (nxt != seq_len)
    mask = (nxt.unsqueeze(2) == nxt.unsqueeze(1)) & valid.unsqueeze(1)
    mask = torch.eye(seq_len, device=device, dtype=torch.bool).unsqueeze(0).expand(batch, -1, -1) | mask
    pos = torch.where(valid, idx - prev - 1, torch.zeros_like(idx))
    return mask, torch.clamp(pos, min=0).to(torch.long)


@contextlib.contextmanager
def exportable_grounding_dino() -> Iterator[None]:
    """While active: transformers' Grounding DINO uses :func:`grounding_text_mask_exportable` and skips its
    runtime tensor checks (``TRANSFORMERS_DISABLE_TORCH_CHECK=1``), so ``torch.onnx.export`` succeeds.

    Raises:
        ImportError: transformers is not installed.
    """
    # lazy: heavy optional dependency, loaded only on this path
    from transformers.models.grounding_dino import modeling_grounding_dino as mg

    name = "generate_masks_with_special_tokens_and_transfer_map"
    orig = getattr(mg, name)
    env = os.environ.get("TRANSFORMERS_DISABLE_TORCH_CHECK")
    setattr(mg, name, grounding_text_mask_exportable)
    os.environ["TRANSFORMERS_DISABLE_TORCH_CHECK"] = "1"
    try:
        yield
    finally:
        setattr(mg, name, orig)
        if env is None:
            os.environ.pop("TRANSFORMERS_DISABLE_TORCH_CHECK", None)
        else:
            os.environ["TRANSFORMERS_DISABLE_TORCH_CHECK"] = env


def _gdino_needed(folder: Path) -> List[str]:
    need = []
    if not (folder / "config.json").is_file():
        need.append("config.json")
    if not any((folder / w).is_file() for w in ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json")):
        need.append("model.safetensors (or pytorch_model.bin)")
    if not (folder / "vocab.txt").is_file() and not (folder / "tokenizer.json").is_file():
        need.append("vocab.txt (or tokenizer.json)")
    return need


def load_grounding_dino(source: Union[str, Path], local_files_only: bool = True):
    """Load ``GroundingDinoForObjectDetection`` (eager attention, eval mode) from a checkpoint folder or a
    hub id.

    Args:
        source: a folder with ``config.json``, ``model.safetensors`` (or ``pytorch_model.bin``) and
            ``vocab.txt``; or a hub id (e.g. ``IDEA-Research/grounding-dino-tiny``).
        local_files_only: hub ids only from the local Hugging Face cache (no network).

    Returns:
        the model (torch.nn.Module).

    Raises:
        MissingModelFiles: a folder lacks files, or a hub id is not available (offline, not cached).
        ImportError: transformers is not installed.
    """
    # lazy: heavy optional dependency, loaded only on this path
    from transformers import GroundingDinoForObjectDetection

    p = Path(source)
    if p.exists():
        if not p.is_dir():
            raise MissingModelFiles(str(source), list(GDINO_FILES), "Give the checkpoint folder, not a file")
        need = _gdino_needed(p)
        if need:
            raise MissingModelFiles(str(source), need)
    try:
        model = GroundingDinoForObjectDetection.from_pretrained(str(source), local_files_only=local_files_only,
                                                                attn_implementation="eager")
    except OSError as e:
        raise MissingModelFiles(str(source), list(GDINO_FILES),
                                f"Not available {'offline (local_files_only)' if local_files_only else 'from the hub'}: "
                                f"{str(e).splitlines()[0]}. On a connected machine run "
                                f"'hf download {source} config.json model.safetensors vocab.txt --local-dir DIR' "
                                f"and pass DIR") from None
    return model.eval()


def write_vocab(source: Union[str, Path], out_path: Union[str, Path], local_files_only: bool = True) -> Path:
    """Write the BERT WordPiece ``vocab.txt`` of a Grounding DINO checkpoint (folder or hub id) to ``out_path``.

    Raises:
        MissingModelFiles: no vocab in the folder / not available offline.
    """
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    p = Path(source)
    if p.is_dir() and (p / "vocab.txt").is_file():
        if (p / "vocab.txt").resolve() != out.resolve():
            shutil.copyfile(p / "vocab.txt", out)
        return out
    try:
        # lazy: heavy optional dependency, loaded only on this path
        from transformers import AutoTokenizer

        tok = AutoTokenizer.from_pretrained(str(source), local_files_only=local_files_only)
        vocab = tok.get_vocab()
    except (OSError, ValueError) as e:
        raise MissingModelFiles(str(source), ["vocab.txt"], str(e).splitlines()[0]) from None
    by_id = sorted(vocab.items(), key=lambda kv: kv[1])
    if [i for _, i in by_id] != list(range(len(by_id))):
        raise ValueError(f"{source}: the tokenizer's ids are not contiguous; cannot write a vocab.txt")
    out.write_text("\n".join(t for t, _ in by_id) + "\n", encoding="utf-8")
    return out


def export_grounding_dino(model, out_path: Union[str, Path], image_size: Tuple[int, int] = (800, 800),
                          opset: int = 18, dynamic_text: bool = True) -> Path:
    """Export a transformers Grounding DINO to ONNX with ``torch.onnx.export`` (dynamo exporter).

    Args:
        model: ``GroundingDinoForObjectDetection`` (eval mode; build or load it with eager attention,
            ``attn_implementation="eager"``: the dynamo exporter cannot reshape SDPA's Swin output).
        out_path: the ``.onnx`` to write.
        image_size: (H, W) static network input, pixels (the detector resizes every image to it).
        opset: ONNX opset.
        dynamic_text: text length dynamic (2..255 tokens); False: fixed at 256 (callers pad).

    Returns:
        ``out_path`` (inputs ``pixel_values, input_ids, attention_mask, token_type_ids``; outputs
        ``logits (1, Q, 256)``, ``pred_boxes (1, Q, 4)``).

    Raises:
        torch.onnx errors when the export fails.
    """
    # lazy: keeps gausslite.attention.export importable without torch
    import torch

    class _Wrapped(torch.nn.Module):
        def __init__(self, m):
            super().__init__()
            self.m = m

        def forward(self, pixel_values, input_ids, attention_mask, token_type_ids):
            o = self.m(pixel_values=pixel_values, input_ids=input_ids, attention_mask=attention_mask,
                       token_type_ids=token_type_ids)
            return o.logits, o.pred_boxes

    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    H, W = int(image_size[0]), int(image_size[1])
    L = 8 if dynamic_text else 256
    ids = torch.zeros((1, L), dtype=torch.long)
    ids[0, :6] = torch.tensor([101, 2000, 1012, 2001, 1012, 102])
    args = (torch.zeros(1, 3, H, W), ids, (ids != 0).long(), torch.zeros_like(ids))
    dyn = None
    if dynamic_text:
        seq = torch.export.Dim("text_len", min=2, max=255)
        dyn = {"pixel_values": None, "input_ids": {1: seq}, "attention_mask": {1: seq}, "token_type_ids": {1: seq}}
    with exportable_grounding_dino(), torch.no_grad():
        torch.onnx.export(_Wrapped(model.eval()).eval(), args, str(out), dynamo=True, opset_version=int(opset),
                          input_names=["pixel_values", "input_ids", "attention_mask", "token_type_ids"],
                          output_names=["logits", "pred_boxes"], dynamic_shapes=dyn, verbose=False)
    data = out.with_name(out.name + ".data")
    if data.exists():  # small models: fold external data back into one file
        # lazy: heavy optional dependency, loaded only on this path
        import onnx

        m = onnx.load(str(out))
        onnx.save(m, str(out), save_as_external_data=m.ByteSize() > 1_900_000_000)
        if m.ByteSize() <= 1_900_000_000:
            data.unlink()
    return out


# ------------------------------------------------------------------------------------------ both
@dataclass
class ExportedModels:
    """Files written by :func:`export_models` (None: not requested)."""

    detector: Optional[Path] = None
    vocab: Optional[Path] = None
    segmenter: Optional[Path] = None

    def agent_yaml(self) -> str:
        """The ``agent`` YAML section that makes an agent use these files."""
        lines = ["agent:", "  relevance_backend: onnx", "  onnx:"]
        for key, p in (("detector_path", self.detector), ("vocab_path", self.vocab), ("segmenter_path", self.segmenter)):
            lines.append(f"    {key}: {p.resolve() if p else 'null'}")
        return "\n".join(lines) + "\n"


def export_models(out_dir: Union[str, Path], detector: Optional[str] = None, segmenter: Optional[str] = None,
                  det_size: Tuple[int, int] = (800, 800), seg_imgsz: Union[int, Tuple[int, int]] = 640,
                  local_files_only: bool = True) -> ExportedModels:
    """Export the detector (``detector.onnx`` + ``vocab.txt``) and/or segmenter (``segmenter.onnx``) to ``out_dir``.

    Args:
        out_dir: output folder (created).
        detector: Grounding DINO checkpoint folder or hub id (see :func:`load_grounding_dino`).
        segmenter: ultralytics ``.pt`` / ``.yaml`` (see :func:`export_yolo_seg`).
        det_size: (H, W) detector input, pixels. seg_imgsz: segmenter input size (int or (h, w)).
        local_files_only: never reach the network for hub ids.

    Returns:
        :class:`ExportedModels`.

    Raises:
        MissingModelFiles: listing every missing file of both sources (checked before exporting anything).
        ValueError: nothing requested.
    """
    if detector is None and segmenter is None:
        raise ValueError("nothing to export: give a detector and/or a segmenter")
    out = Path(out_dir)
    missing: List[str] = []
    if detector is not None and Path(detector).is_dir():
        missing += [f"{detector}/{n}" for n in _gdino_needed(Path(detector))]
    if segmenter is not None and Path(segmenter).suffix.lower() == ".pt" and not Path(segmenter).is_file():
        missing.append(str(segmenter))
    if missing:
        raise MissingModelFiles("model sources", missing)
    res = ExportedModels()
    if detector is not None:
        model = load_grounding_dino(detector, local_files_only=local_files_only)
        res.vocab = write_vocab(detector, out / "vocab.txt", local_files_only=local_files_only)
        res.detector = export_grounding_dino(model, out / "detector.onnx", image_size=det_size)
    if segmenter is not None:
        res.segmenter = export_yolo_seg(segmenter, out / "segmenter.onnx", imgsz=seg_imgsz)
    return res

