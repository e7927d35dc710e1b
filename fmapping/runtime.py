"""Process-wide numeric runtime settings for numpy-heavy loops (the tracker's bundle adjustment).

**Allocator.** glibc returns large freed blocks to the kernel (``mmap`` for blocks over 128 KiB, heap
trimming above a threshold), so every fresh multi-megabyte numpy temporary page-faults
again; on the VMs we run on that cost is of the order of the arithmetic itself
(``bench/tracking.py``, ``ba_allocator``). :func:`retain_freed_memory` raises both
thresholds with ``mallopt`` so freed memory is reused: the resident size stays at its peak
instead. torch has its own caching allocator and is not affected.

**BLAS threads.** numpy's OpenBLAS starts one thread per core. Next to the other services
on the same cores its threads compete for them and the tracker falls behind (measured in
``bench/system.py`` at 10 fps: median pose latency 0.5-1.9 s with them, 0.03 s with one
thread), while one thread is as fast for the bundle adjustment's matrices.
:func:`limit_blas_threads` sets the pool at run time (threadpoolctl).

The ``fmapping`` CLI retains freed memory; the tracker service does both at start. Both are
no-ops (returning False) where the library in question is absent.

**First optimiser.** The first ``torch.optim`` optimiser a process makes imports ``torch._dynamo`` (and with it
sympy): 1.1-2.3 s on the 2-core machines, paid by the mapper's init, on the first frames' path, unless
:func:`preload_optimiser` paid it at start (the mapper service does, and ``fmapping slam`` on a live camera).

**Trimming.** :func:`release_free_memory` hands the heap's free pages back after each mapper update
(once per update, not per temporary: the retained reuse within an update stays), and the tracker's worker
after a loop closure's bundle adjustment (``MonoConfig.ba_release_memory``).

**Arenas.** glibc gives each thread that allocates its own heap ("arena", up to 8 per core). In the tracker
service the frames arrive on zenoh's threads and the bundle adjustment runs in a worker, so each keeps a heap
whose peak is retained. :func:`single_malloc_arena` makes every thread share the main heap. Play and the
tracker alone at 30 fps over 1,000 frames (``bench/results/tracker_memory/``): tracker RSS 390 -> 423 MB from
frame 200 to 950 with the arenas, 358 -> 370 MB with one, at the same count of frames tracked.
"""
from __future__ import annotations

import ctypes
import functools

M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
DEFAULT_THRESHOLD = 128 * 1024  # glibc's static default of both
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # glibc's largest M_MMAP_THRESHOLD on 64-bit
RETAINED_TRIM = 512 * 1024 * 1024


@functools.lru_cache(maxsize=1)
def _libc():
    """The C library already loaded in this process (no library search), if it has ``mallopt``; looked up
    once (the mapper asks after every update)."""
    try:
        lib = ctypes.CDLL(None)
    except OSError:
        return None
    return lib if hasattr(lib, "mallopt") else None


def retain_freed_memory(on: bool = True) -> bool:
    """Keep freed blocks up to 32 MiB (and up to 512 MiB at the heap's top) for reuse
    (``on``), or go back to glibc's static defaults (``on=False``). True when applied."""
    lib = _libc()
    if lib is None:
        return False
    mmap_t, trim_t = (MMAP_THRESHOLD_MAX, RETAINED_TRIM) if on else (DEFAULT_THRESHOLD, DEFAULT_THRESHOLD)
    return bool(lib.mallopt(M_MMAP_THRESHOLD, mmap_t)) and bool(lib.mallopt(M_TRIM_THRESHOLD, trim_t))


def release_free_memory() -> bool:
    """Give the C heap's free pages back to the kernel now (glibc ``malloc_trim(0)``: every arena, not only
    the top of the heap). The mapper calls it after each update: glibc's dynamic ``mmap`` threshold
    moves tensor-sized blocks into the heap, whose free space is otherwise kept, so the resident size
    ratchets up with every update whose temporaries land somewhere new (``bench/long_run.py``: 1,000
    frames of ``fmapping slam``, RSS 498 MB after 129 frames and 544-658 MB later without it, 428 and
    452-472 MB with it, same window time). True when the call exists (glibc)."""
    lib = _libc()
    if lib is None or not hasattr(lib, "malloc_trim"):
        return False
    lib.malloc_trim(0)
    return True


def single_malloc_arena() -> bool:
    """Let every thread of this process allocate from glibc's main heap (``M_ARENA_MAX`` 1) instead of a heap
    of its own. Call it before the threads start (zenoh's, a worker's): an arena once made stays. True when
    applied (glibc)."""
    lib = _libc()
    return lib is not None and bool(lib.mallopt(M_ARENA_MAX, 1))


def limit_blas_threads(n: int = 1) -> bool:
    """Limit the BLAS thread pools loaded so far (numpy's OpenBLAS) to ``n`` threads. True when
    a pool was limited."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import numpy  # noqa: F401  (loads its BLAS)

    if not any(i.get("user_api") == "blas" for i in threadpool_info()):
        return False
    threadpool_limits(limits=n, user_api="blas")
    return True


def preload_optimiser() -> float:
    """Make and drop a throwaway torch optimiser, so that the imports of a process's first one (``torch._dynamo``,
    sympy) happen now rather than in the mapper's init. Returns the seconds it took (near 0 once done)."""
    import time

    import torch

    t0 = time.perf_counter()
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    return time.perf_counter() - t0
