"""Replayed CPU kernel launches: the Python cost of a Warp launch paid once per kernel, not per call.

``wp.launch`` resolves the kernel's overload from its arguments, wraps every tensor in a ``wp.array``
(``wp.from_torch``) and packs every argument on each call: about 60 µs per launch plus about 11 µs per
tensor on the machine of docs/realtime.md, ``Mapping throughput``, against a projection kernel's 0.3 ms of
work for 2,000 Gaussians. A mapping iteration launches about 18 kernels. :func:`launch_cpu` records one
``wp.Launch`` per kernel, argument signature and thread (``wp.launch(..., record_cmd=True)``, Warp's own
replay object, which resolves and validates the overload exactly as ``wp.launch`` does) and replays it: each
call only rewrites the argument slots (a tensor becomes Warp's array descriptor from its pointer, shape and
strides) and invokes the compiled kernel.

Arguments are given in the kernel's parameter order (inputs, then outputs): a ``torch.Tensor`` (CPU;
converted as ``wp.from_torch`` would, with its own dtype), a :class:`Vec` (a tensor viewed as an array of a
Warp vector type, ``wp.from_torch(t, dtype=...)``), an ``int`` or ``float``, or a Warp value (a vector or
matrix such as ``wp.mat33d``, a Warp scalar, or an array descriptor from ``wp.from_torch(...,
return_ctype=True)``) passed through. Launches are per thread (the recorded slots are not shared), so the
stripes of :func:`gausslite.render.warp_kernels.run_parallel` replay their own.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import torch
import warp as wp

_local = threading.local()
_ARRAY_T = None
#: Warp's scalar types (a value of one is written to its slot as a plain number)
_SCALARS = frozenset((wp.float16, wp.float32, wp.float64, wp.int8, wp.int16, wp.int32, wp.int64, wp.uint8, wp.uint16,
                       wp.uint32, wp.uint64, wp.bool))


class Vec(NamedTuple):
    """A (N, k) or (N, ..., k) tensor launched as a Warp array of the vector type ``dtype`` (``wp.vec4``, …)."""

    tensor: torch.Tensor
    dtype: object


def _array_t():
    """Warp's array descriptor type (the ``ctypes.Structure`` a launch takes for an array parameter)."""
    global _ARRAY_T
    if _ARRAY_T is None:
        _ARRAY_T = type(wp.empty(1, dtype=wp.float32, device="cpu").__ctype__())
    return _ARRAY_T


def _signature(a) -> tuple:
    """What decides the recorded launch an argument needs: a tensor's dtype and dims, a vector view's type."""
    if isinstance(a, torch.Tensor):
        return ("t", a.dtype, a.dim())
    if isinstance(a, Vec):
        return ("v", a.tensor.dtype, a.tensor.dim(), a.dtype)
    return ("s", type(a))


def _warp_value(a):
    """An argument as ``wp.launch`` takes it (used once, to record the launch)."""
    if isinstance(a, torch.Tensor):
        return wp.from_torch(a)
    if isinstance(a, Vec):
        return wp.from_torch(a.tensor, dtype=a.dtype)
    return a


def _check(t: torch.Tensor, ndim: int) -> None:
    """Raise ValueError unless tensor ``t`` can be seen as a ``ndim``-dimensional Warp array: on the CPU, and its
    trailing dims (a vector element) contiguous."""
    if t.device.type != "cpu":
        raise ValueError(f"launch_cpu takes CPU tensors, got one on {t.device}")
    if t.dim() > ndim:
        expect, stride = 1, []
        for n in reversed(t.shape[ndim:]):
            stride.insert(0, expect)
            expect *= n
        if list(t.stride()[ndim:]) != stride:
            raise ValueError(f"the vector dimensions {tuple(t.shape[ndim:])} of a launch argument must be "
                             f"contiguous, got strides {t.stride()}")


def _write(desc, t: torch.Tensor, ndim: int) -> None:
    """Point Warp's array descriptor ``desc`` at tensor ``t`` seen as a ``ndim``-dimensional array (trailing
    dims form the element type): its pointer, shape and byte strides, written in place."""
    _check(t, ndim)
    desc.data = t.data_ptr()
    item = t.element_size()
    shape, strides = t.shape, t.stride()
    for d in range(ndim):
        desc.shape[d] = shape[d]
        desc.strides[d] = strides[d] * item


class _Recorded:
    """One recorded launch and, per argument, how to write its slot."""

    def __init__(self, kernel, dim, args: list):
        self.cmd = wp.launch(kernel, dim=dim, inputs=[_warp_value(a) for a in args], device="cpu", record_cmd=True)
        self.cmd.fwd_args = None  # the recording's arrays (and the tensors they hold) are not kept
        self.dim = dim
        params = kernel.adj.args
        #: per argument: the array's dims (tensors and vector views) or None (scalars and Warp values)
        self.ndims = [params[i].type.ndim if isinstance(a, (torch.Tensor, Vec)) else None for i, a in enumerate(args)]
        #: per array argument: the launch's own descriptor, rewritten in place at every call
        self.descs = [None] * len(args)
        for i, nd in enumerate(self.ndims):
            if nd is not None:
                self.descs[i] = _array_t()(data=0, grad=0, ndim=nd, shape=(0,) * nd, strides=(0,) * nd)
                self.cmd.set_param_at_index_from_ctype(i, self.descs[i])

    def __call__(self, dim, args: list) -> None:
        cmd = self.cmd
        if dim != self.dim:
            cmd.set_dim(dim)
            self.dim = dim
        for i, (a, nd) in enumerate(zip(args, self.ndims)):
            if nd is not None:
                _write(self.descs[i], a if isinstance(a, torch.Tensor) else a.tensor, nd)
            elif isinstance(a, (bool, int, float)):
                cmd.set_param_at_index_from_ctype(i, a)
            elif type(a) in _SCALARS:
                cmd.set_param_at_index_from_ctype(i, a.value)
            else:
                cmd.set_param_at_index(i, a)
        cmd.launch()


def launch_cpu(kernel, dim, args: list) -> None:
    """Launch Warp ``kernel`` on the CPU over ``dim`` threads (an int, or a tuple for a 2-D launch) with ``args``
    (module docstring: every parameter in order, inputs then outputs), replaying this thread's recorded launch for
    the kernel and the arguments' types. Same effect as ``wp.launch(kernel, dim=dim, inputs=args, device="cpu")``;
    a launch of no threads does nothing.

    Raises:
        ValueError: a tensor off the CPU, or a vector view whose vector dimensions are not contiguous.
        Whatever ``wp.launch`` raises for arguments that do not match the kernel (on the first call with
        each argument signature).
    """
    if (min(dim) if isinstance(dim, tuple) else dim) <= 0:
        return
    cache = getattr(_local, "launches", None)
    if cache is None:
        cache = _local.launches = {}
    key = (kernel, tuple(_signature(a) for a in args))
    rec = cache.get(key)
    if rec is None:
        rec = cache[key] = _Recorded(kernel, dim, args)
    rec(dim, args)


__all__ = ["Vec", "launch_cpu"]
