"""Freed memory handed back to the operating system during long fits (glibc's ``malloc_trim``).

A fit allocates and frees arrays of many sizes at every step (the meshes of the sequences still
descending, the Chamfer term's nearest-neighbour answers and lists). glibc serves those under
32 MB from its heap and keeps what they free for later requests; a heap with holes between
live blocks does not give them back, so a process's resident memory climbs over a fit of a thousand
steps far above what it holds. Measured on the sls unit of frequency-guided at 10,000 points (8
sequences x 100 anchors, one thread): without release, a worker's resident memory climbed to 8.2 GB
after about an hour of its fit (the same unit was killed by the out-of-memory killer at 11.5 GB on
a 24 GB machine the round before); with a release every 50 steps, the resident memory fell from
3.81, 4.32 and 4.51 GB to 2.73 GB at each of the first three releases (46-69 ms each, against about
4.5 s per step on a shared core): what the fit holds stays at 2.7 GB, the rest was freed memory kept by the heap.

:func:`release_free_memory` asks glibc to return the free pages of its heaps (``malloc_trim``
releases the free pages inside the heap too, not only at its top). It changes no value a fit
computes. Where the C library has no ``malloc_trim`` (macOS, musl, Windows) it does nothing.
"""

from __future__ import annotations

import ctypes
import sys

RELEASE_EVERY = 50  # optimiser steps between two releases (benchmark.protocols.step_rules.adam_step)

_trim = None  # the C library's malloc_trim, resolved on first use (False: none)


def _malloc_trim():
    global _trim
    if _trim is None:
        _trim = False
        if sys.platform.startswith("linux"):
            try:
                fn = getattr(ctypes.CDLL(None), "malloc_trim", None)
            except OSError:
                fn = None
            if fn is not None:
                fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
                _trim = fn
    return _trim or None


def release_free_memory() -> bool:
    """Return the free pages of the C heap to the operating system; True where that was possible."""
    fn = _malloc_trim()
    if fn is None:
        return False
    fn(0)
    return True


__all__ = ["RELEASE_EVERY", "release_free_memory"]
