"""Returning freed heap memory to the operating system in long missions.

A long mission allocates and frees large temporary buffers again and again (map copies for the share selection,
renders, encoded keyframes) from several threads. glibc's allocator keeps much of that freed memory in its arenas
instead of returning it, so a process's resident memory creeps up over an hour although its live data is bounded
(``bench.soak``, retired: docs/history.md#soak). After each push the agent and its share worker ask the allocator to
give free pages back
(``malloc_trim(0)``), as Dask's workers do for the same reason (distributed, "Memory not released back to the OS").
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
from typing import Optional

log = logging.getLogger(__name__)

_libc: Optional[ctypes.CDLL] = None
_checked = False


def trim_heap(collect: bool = False) -> bool:
    """Return the allocator's free pages to the OS (glibc ``malloc_trim(0)``), after a full garbage collection when
    ``collect``.

    The mapping thread trims without collecting: a full ``gc.collect()`` walks every object the process holds (tens of
    milliseconds with PyTorch loaded, taken from the keyframe's budget after every push: 7 % of a live mission's
    time in a sampling profile), while the buffers a push frees are plain references, freed when they go, and the
    interpreter's own generational collector still runs. The share worker, a process of its own between
    selections, collects first.

    Args:
        collect: run ``gc.collect()`` first.
    Returns:
        True when memory was released; False when nothing could be (or on a C library without ``malloc_trim``,
        e.g. macOS or musl, where this is a no-op).
    """
    global _libc, _checked
    if collect:
        gc.collect()
    if not _checked:
        _checked = True
        name = ctypes.util.find_library("c")
        try:
            lib = ctypes.CDLL(name) if name else None
            _libc = lib if lib is not None and hasattr(lib, "malloc_trim") else None
        except OSError as e:
            log.debug("no C library for malloc_trim: %s", e)
    return bool(_libc.malloc_trim(0)) if _libc is not None else False


__all__ = ["trim_heap"]
