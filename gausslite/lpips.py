"""LPIPS perceptual distance (Zhang et al. 2018) with the AlexNet backbone, in plain torch.

No torchvision and no network access: weights are loaded **only** from local files that the user
supplies. Nothing here downloads anything.

Architecture (identical to the official ``lpips`` package, version 0.1, ``net='alex'``):
    input in [0, 1] -> x * 2 - 1 -> ScalingLayer ((x - shift) / scale, shift = (-.030, -.088, -.188),
    scale = (.458, .448, .450)) -> AlexNet ``features`` (torchvision layout); activations are tapped
    after the ReLUs of the 5 conv layers (channels 64, 192, 384, 256, 256) -> each feature vector is
    unit-normalised over channels -> squared difference -> 1x1 conv "lin" head (no bias) -> spatial
    mean -> sum over the 5 layers.

Accepted state-dict keys (any mix, from one or two files; extra keys such as torchvision's
``classifier.*`` are ignored):
    backbone, torchvision ``alexnet`` naming:      ``features.{0,3,6,8,10}.{weight,bias}``
    backbone, official ``lpips.LPIPS`` naming:     ``net.slice1.0.*``, ``net.slice2.3.*``,
                                                   ``net.slice3.6.*``, ``net.slice4.8.*``,
                                                   ``net.slice5.10.*``
    heads, official ``lpips`` naming (``weights/v0.1/alex.pth``):  ``lin{k}.model.1.weight``
    heads, short naming:                           ``lin{k}.weight``                (k = 0..4)
    shapes: conv weights (64,3,11,11), (192,64,5,5), (384,192,3,3), (256,384,3,3), (256,256,3,3);
            head weights (1, C_k, 1, 1) with C_k = 64, 192, 384, 256, 256.
So the usual setup is ``LPIPS.load("alexnet-owt-7be5be79.pth", "alex.pth")`` with the torchvision
ImageNet AlexNet checkpoint and the lpips package's linear weights, both copied locally.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, Mapping, Optional, Union

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["LPIPS", "ALEX_CONV_SPECS", "ALEX_CHANNELS", "MIN_IMAGE_SIZE"]

# (features index, in_ch, out_ch, kernel, stride, padding) of torchvision's AlexNet convs.
ALEX_CONV_SPECS = (
    (0, 3, 64, 11, 4, 2),
    (3, 64, 192, 5, 1, 2),
    (6, 192, 384, 3, 1, 1),
    (8, 384, 256, 3, 1, 1),
    (10, 256, 256, 3, 1, 1),
)
ALEX_CHANNELS = tuple(s[2] for s in ALEX_CONV_SPECS)
#: Smallest height/width for which every AlexNet tap has at least one pixel.
MIN_IMAGE_SIZE = 31

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def _normalize_keys(sd: Mapping[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
    """Map any accepted naming onto ``conv{i}.{weight,bias}`` and ``lin{k}``."""
    out: Dict[str, torch.Tensor] = {}
    for i, (fi, *_rest) in enumerate(ALEX_CONV_SPECS):
        for kind in ("weight", "bias"):
            for key in (f"features.{fi}.{kind}", f"net.slice{i + 1}.{fi}.{kind}"):
                if key in sd:
                    out[f"conv{i}.{kind}"] = sd[key]
    for k in range(5):
        for key in (f"lin{k}.model.1.weight", f"lin{k}.weight"):
            if key in sd:
                out[f"lin{k}"] = sd[key]
    return out


class LPIPS(nn.Module):
    """LPIPS-Alex distance; lower = more similar, 0 for identical images.

    Build with :meth:`load` (from files) or :meth:`from_state_dict`. The module holds no trainable
    state in practice (put it in ``eval()``; it is differentiable w.r.t. its inputs).
    """

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(cin, cout, k, stride=s, padding=p) for (_fi, cin, cout, k, s, p) in ALEX_CONV_SPECS
        )
        self.lins = nn.ParameterList(nn.Parameter(torch.zeros(1, c, 1, 1)) for c in ALEX_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.eval()
        for p in self.parameters():
            p.requires_grad_(False)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, torch.Tensor]) -> "LPIPS":
        """Build from an in-memory state dict (see module docstring for key names).

        Raises:
            KeyError: required keys missing (the message lists them).
            ValueError: a tensor has the wrong shape.
        """
        sd = _normalize_keys(state_dict)
        required = [f"conv{i}.{k}" for i in range(5) for k in ("weight", "bias")] + [f"lin{k}" for k in range(5)]
        missing = [r for r in required if r not in sd]
        if missing:
            raise KeyError(
                f"LPIPS state dict lacks {missing} (expected torchvision 'features.N.*' or lpips "
                f"'net.sliceK.N.*' backbone keys and 'linK.model.1.weight' head keys)"
            )
        m = cls()
        with torch.no_grad():
            for i, conv in enumerate(m.convs):
                for kind in ("weight", "bias"):
                    src, dst = sd[f"conv{i}.{kind}"], getattr(conv, kind)
                    if tuple(src.shape) != tuple(dst.shape):
                        raise ValueError(f"LPIPS conv{i}.{kind}: expected shape {tuple(dst.shape)}, got {tuple(src.shape)}")
                    dst.copy_(src)
            for k, lin in enumerate(m.lins):
                src = sd[f"lin{k}"]
                if tuple(src.shape) != tuple(lin.shape):
                    raise ValueError(f"LPIPS lin{k}: expected shape {tuple(lin.shape)}, got {tuple(src.shape)}")
                lin.copy_(src)
        return m

    @classmethod
    def load(
        cls,
        path: Union[str, os.PathLike],
        lin_path: Optional[Union[str, os.PathLike]] = None,
        map_location: Union[str, torch.device] = "cpu",
    ) -> "LPIPS":
        """Load from local ``torch.save``'d state dict(s); never downloads.

        Args:
            path: file with the backbone (and optionally the heads).
            lin_path: optional second file with the heads (e.g. lpips ``weights/v0.1/alex.pth``);
                its keys override ``path``'s.
        Raises:
            FileNotFoundError: a file does not exist.
            ValueError: a file is not a state dict of tensors; KeyError/ValueError as in
                :meth:`from_state_dict`.
        """
        merged: Dict[str, torch.Tensor] = {}
        for p in [path] + ([lin_path] if lin_path is not None else []):
            fp = Path(p)
            if not fp.is_file():
                raise FileNotFoundError(f"LPIPS weights not found: {fp} (weights are never downloaded)")
            obj = torch.load(str(fp), map_location=map_location, weights_only=True)
            if isinstance(obj, Mapping) and "state_dict" in obj and isinstance(obj["state_dict"], Mapping):
                obj = obj["state_dict"]
            if not isinstance(obj, Mapping):
                raise ValueError(f"{fp}: expected a state dict (mapping of tensors), got {type(obj).__name__}")
            merged.update({k.removeprefix("module."): v for k, v in obj.items() if isinstance(v, torch.Tensor)})
        return cls.from_state_dict(merged)

    def _features(self, x: torch.Tensor):
        feats = []
        h = x
        for i, conv in enumerate(self.convs):
            if i in (1, 2):  # max-pools precede conv2 and conv3 in AlexNet
                h = F.max_pool2d(h, kernel_size=3, stride=2)
            h = F.relu(conv(h))
            feats.append(h)
        return feats

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """LPIPS distance.

        Args:
            pred, gt: (H, W, 3) or batched (B, H, W, 3) float images in [0, 1], H, W >= 31.
        Returns:
            0-dim tensor for unbatched input, (B,) for batched input.
        Raises:
            ValueError: shape mismatch, wrong channel count or image too small.
        """
        if pred.shape != gt.shape or pred.ndim not in (3, 4) or pred.shape[-1] != 3:
            raise ValueError(
                f"LPIPS expects matching (H, W, 3) or (B, H, W, 3) images, got {tuple(pred.shape)} and {tuple(gt.shape)}"
            )
        if min(pred.shape[-3], pred.shape[-2]) < MIN_IMAGE_SIZE:
            raise ValueError(f"LPIPS-Alex needs H, W >= {MIN_IMAGE_SIZE}, got {tuple(pred.shape[-3:-1])}")
        batched = pred.ndim == 4
        dt = self.shift.dtype
        x = torch.stack([pred, gt]) if not batched else torch.cat([pred, gt])
        x = x.reshape(-1, *pred.shape[-3:]).to(dt).permute(0, 3, 1, 2)
        x = ((x * 2 - 1) - self.shift) / self.scale
        b = x.shape[0] // 2
        total = 0.0
        for f, w in zip(self._features(x), self.lins):
            f = f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            d = (f[:b] - f[b:]) ** 2
            total = total + F.conv2d(d, w).mean(dim=(1, 2, 3))
        return total if batched else total[0]
