"""Handing host memory back between the phases of a long run.

A search keeps its sampler's caches (the supernet's stage outputs, the encoders' features: about a
gigabyte) until sampling ends, then retrains networks at the deployment size, whose activations take
about as much again. Freed tensors go back to the C allocator, not to the system: glibc keeps the
pages of its heaps for later allocations, and the next phase's tensors, of other sizes, fit them
badly, so the process's resident memory stays at the sum of both phases. ``release_host_memory``
collects what Python still holds in cycles and asks glibc to return its free pages (``malloc_trim``),
so that a phase starts from what is really in use.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_host_memory() -> bool:
    """Collects unreachable Python objects, then returns the allocator's free pages to the system;
    whether the allocator could be asked (glibc)."""
    gc.collect()
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
