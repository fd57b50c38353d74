"""The C heap's free pages handed back to the system (glibc), between the stages of a run."""

from __future__ import annotations

import ctypes

__all__ = ["trim_heap"]


def trim_heap() -> bool:
    """Give the free pages of the C heap back to the system (glibc's ``malloc_trim``); False where
    there is no glibc (nothing done). Objects freed by Python, numpy or gtsam leave their memory in
    malloc's free chunks, resident until malloc reuses it: after the estimation, what the final
    batch and the let-go estimator used; after a sectioned batch's solve, its kept eliminations and
    factors."""
    try:
        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True
