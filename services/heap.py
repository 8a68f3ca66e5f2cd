"""Hand the C heap's free pages back to the kernel once a service has built its models.

Loading meshes and building collision models (pinocchio, coal, pybullet) allocates and frees tens of
megabytes; glibc keeps what was freed inside its heap, resident, for the process to reuse, and a
service that has started never needs that much again. `malloc_trim(0)` returns those pages (the
executor: some 30 MB). Elsewhere than glibc this does nothing.
"""

from __future__ import annotations

import ctypes


def release_free_memory() -> None:
    """Give the pages the C heap holds free back to the kernel (glibc's malloc_trim), if it can."""
    trim = getattr(ctypes.CDLL(None), "malloc_trim", None)  # the C library the interpreter runs on
    if trim is None:
        return  # not glibc (musl, macOS): nothing to trim this way
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    trim(0)
