"""Process settings a solve runs best under, applied for its duration or once per process.

A shot allocates and frees dozens of per-pixel tensors (megabytes each at hemicube 256) and
per-element ones; two process-wide defaults make that slow on a CPU-only machine, and are
changed here, not in the algorithms.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys
import warnings
from contextlib import contextmanager

import torch

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_allocator_tuned = False
#: The freed heap a solve keeps for reuse (``keep_freed_memory``) is handed back to the system
#: where it grows past this (``release_freed_memory``).
FREED_HEAP_KEPT = 512 << 20


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (glibc 2.33 and later)."""

    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


@contextmanager
def deterministic(device: torch.device):
    """Run the block with PyTorch's deterministic algorithms on CUDA, then restore the setting.

    On CUDA, index_add and scatter sums add in whatever order the threads finish: the same
    scene would give numbers that differ in the last bits from run to run, and a refinement
    threshold can turn that into a different mesh. In deterministic mode they sum in a
    fixed order. On the CPU every operation a solve uses is deterministic already.

    PyTorch flags every CUDA scatter_reduce as nondeterministic; a solve reduces only by
    amax and amin, which give the same result in any order, so that warning is silenced.
    """
    if device.type != "cuda":
        yield
        return
    before, warn_only = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"scatter_reduce_cuda does not have a deterministic implementation")
            yield
    finally:
        torch.use_deterministic_algorithms(before, warn_only=warn_only)


@contextmanager
def torch_threads(count: int):
    """Run the block with torch's intra-op pool at ``count`` threads, then restore it.

    With a software renderer, llvmpipe already runs a thread per core during every
    hemicube; a second torch thread on a 2-core machine only fights it for the cores and
    spins between the many small per-shot operations. Measured on 2 cores: the
    Fig. 6(c)-class benchmark took 1.6 times as long with torch on 2 threads as on 1.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed blocks of up to 32 MiB for reuse (once per process).

    By default glibc serves blocks over 128 KiB to 32 MiB by mmap and returns them to the
    system on free, so every per-pixel tensor of every pass is mapped afresh and
    page-faulted in again. Kept in the heap, they are reused: measured on 2 cores, the
    Fig. 6(c)-class benchmark ran 12% faster (30.4 s -> 26.9 s). The cost is that the
    process keeps its peak heap until it exits. Returns whether the setting took (False on
    other C libraries, where nothing is changed).
    """
    global _allocator_tuned
    if _allocator_tuned:
        return True
    mallopt = _libc_function("mallopt", (ctypes.c_int, ctypes.c_int), ctypes.c_int)
    if mallopt is None:
        return False
    _allocator_tuned = bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20) and mallopt(_M_TRIM_THRESHOLD, 256 << 20)
                            and mallopt(_M_TOP_PAD, 64 << 20))
    return _allocator_tuned


def release_freed_memory(kept: int = FREED_HEAP_KEPT) -> bool:
    """Hand the pages of glibc's heaps that hold only freed blocks back to the system
    (``malloc_trim``) where more than ``kept`` bytes of the heaps are free; whether it did.

    ``keep_freed_memory`` keeps freed blocks for reuse, but a sweep's blocks grow with the
    light it keeps and are freed by two threads into two arenas, so much of the freed heap
    is never reused: the furnished room of ``scripts/peer_room.py`` refined once peaked at
    2.7 GB, of which about 0.6 GB was free heap. A solve calls this between sweep groups; it
    costs a walk over the heaps' free lists (about a millisecond) and, where it trims, the
    trim and the page faults of reusing what it handed back. Does nothing where the C
    library is not glibc 2.33 or later.
    """
    mallinfo2 = _libc_function("mallinfo2", (), _MallInfo2)
    trim = _libc_function("malloc_trim", (ctypes.c_size_t,), ctypes.c_int)
    if mallinfo2 is None or trim is None or mallinfo2().fordblks <= kept:
        return False
    trim(0)
    return True


@functools.lru_cache(maxsize=None)
def _libc_function(name: str, argtypes: tuple, restype):
    """The C library's function ``name`` with its ctypes signature, or None where there is
    none (not Linux, or a C library without it)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        function = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None
    function.argtypes, function.restype = list(argtypes), restype
    return function
