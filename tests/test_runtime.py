"""fmapping.runtime: freed numpy temporaries are reused instead of page-faulting again; BLAS threads."""
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from fmapping.runtime import limit_blas_threads


_FAULTS = """
import resource, sys
import numpy as np
from fmapping.runtime import retain_freed_memory
if not retain_freed_memory(sys.argv[1] == "retain"):
    print(-1); raise SystemExit
def faults(n):  # minor page faults per fresh 2 MiB array (written, then freed; numpy asks for huge pages from 4 MiB)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        a = np.ones(1 << 18)
        del a
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / n
faults(1)  # the first one may grow the heap
print(faults(8))
"""


def _fresh(code: str, *args: str) -> str:
    """Standard output of ``code`` run in a fresh process (the heap's state depends on everything the process
    did before)."""
    root = Path(__file__).resolve().parents[1]
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True, cwd=root,
                          env={**os.environ, "PYTHONPATH": str(root)}).stdout


def _faults_per_alloc(mode: str) -> float:
    return float(_fresh(_FAULTS, mode).strip().splitlines()[-1])


def test_retained_memory_is_reused_without_page_faults():
    default = _faults_per_alloc("static")  # glibc's static thresholds: 128 KiB
    if default < 0:
        pytest.skip("not glibc: mallopt unavailable")
    retained = _faults_per_alloc("retain")
    pages = (1 << 18) * 8 / resource.getpagesize()
    # every 2 MiB block is mapped afresh and faults in as it is written (seen: 513 faults for 512
    # pages here) ...
    assert default > 0.1 * pages
    assert retained < 0.05 * default  # ... retained, it is the same memory again (seen: 0)


def test_limit_blas_threads_sets_numpys_pool_and_can_restore_it():
    import numpy  # noqa: F401  (loads its BLAS before the pools are listed)
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]

    before = blas_threads()
    if not before:
        pytest.skip("numpy without a BLAS thread pool")
    try:
        assert limit_blas_threads(1)
        assert blas_threads() == [1] * len(before)
    finally:
        limit_blas_threads(max(before))
    assert blas_threads() == [max(before)] * len(before)


def test_service_torch_threads_auto_and_explicit():
    """``--threads 0`` takes the service's automatic count (at least 1), a positive value is kept;
    the CPUs counted are this process's affinity set."""
    import os

    import torch

    from services.process import available_cpus, set_torch_threads

    assert available_cpus() == len(os.sched_getaffinity(0))
    before = torch.get_num_threads()
    try:
        assert set_torch_threads(0, auto=available_cpus() // 2) == max(1, available_cpus() // 2) \
            == torch.get_num_threads()
        assert set_torch_threads(0, auto=0) == 1 == torch.get_num_threads()
        assert set_torch_threads(3, auto=1) == 3 == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


_TRIM = """
import sys
import numpy as np
from fmapping.runtime import release_free_memory
def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
blocks = [np.ones(8192) for _ in range(2000)]  # 2,000 x 64 KiB, under the mmap threshold: on the heap
kept = blocks[::10]  # one block in ten stays, the last one among them: the heap's top is not free
del blocks
before = rss_mb()
ok = release_free_memory()
print(int(ok), before, rss_mb())
"""


def test_release_free_memory_gives_the_heaps_free_pages_back():
    """~115 MiB freed in the middle of the heap stay resident (glibc trims only the heap's top) until
    release_free_memory() returns them: the resident size falls by most of it."""
    if not Path("/proc/self/status").exists():
        pytest.skip("no /proc here")
    out = _fresh(_TRIM)
    ok, before, after = out.split()
    if ok == "0":
        pytest.skip("not glibc: malloc_trim unavailable")
    assert float(before) - float(after) > 80, out


_ARENAS = """
import ctypes, sys, tempfile, threading
from fmapping.runtime import single_malloc_arena
libc = ctypes.CDLL(None)
if not hasattr(libc, "malloc_info") or (sys.argv[1] == "single" and not single_malloc_arena()):
    print(-1); raise SystemExit
def work():  # a thread that allocates (blocks over pymalloc's 512 bytes go to malloc), as zenoh's and the BA's do
    keep = [bytearray(100_000) for _ in range(50)]
    del keep
ts = [threading.Thread(target=work) for _ in range(3)]
for t in ts: t.start()
for t in ts: t.join()
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.fclose.argtypes = [ctypes.c_void_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
path = tempfile.mktemp()
f = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, f)
libc.fclose(f)
print(open(path).read().count("<heap nr="))
"""


def _heaps(mode: str) -> int:
    return int(_fresh(_ARENAS, mode).strip().splitlines()[-1])


def test_single_malloc_arena_keeps_the_threads_allocations_in_one_heap():
    """glibc's malloc_info lists one heap per arena: threads that allocate get heaps of their own, unless
    single_malloc_arena() was called before they started."""
    if _heaps("default") < 0:
        pytest.skip("not glibc: malloc_info unavailable")
    assert _heaps("default") >= 2  # the threads' own arenas (seen: 4 with 3 threads)
    assert _heaps("single") == 1


_BA_WORKER = """
import sys
import numpy as np
import fmapping.tracking.mono.ba_thread as bt
from fmapping.runtime import retain_freed_memory
retain_freed_memory()  # as the tracker service: freed memory stays for reuse
def rss_mb():
    return int([l for l in open("/proc/self/status") if l.startswith("VmRSS")][0].split()[1]) / 1024
def solve(camera, prob):  # stands in for a loop's bundle adjustment: 96 MiB of temporaries, freed at the end
    tmp = [np.ones(1 << 20) for _ in range(12)]
    del tmp
    return "solved"
bt.solve_ba_problem = solve
worker = bt.BackgroundBA(None)
before = rss_mb()
worker.submit(None, release_memory=sys.argv[1] == "release")
assert worker.take(wait=True) == (None, "solved")
print(before, rss_mb())
"""


def test_the_ba_worker_hands_a_solves_freed_memory_back():
    """With freed memory retained (the tracker service), a solve's temporaries stay resident after it unless
    the worker releases them (a loop closure's problem, ``MonoConfig.ba_release_memory``)."""
    if not Path("/proc/self/status").exists():
        pytest.skip("no /proc here")
    def grown(mode: str) -> float:
        before, after = (float(x) for x in _fresh(_BA_WORKER, mode).split())
        return after - before

    kept, released = grown("keep"), grown("release")
    if kept < 48:
        pytest.skip(f"the allocator here returned the temporaries by itself ({kept:.0f} MB kept)")
    assert released < 16, (kept, released)


_PRELOAD = """
import sys
import fmapping.mapping  # the mapper's own imports do not bring it in
from fmapping.runtime import preload_optimiser
before = "torch._dynamo" in sys.modules
preload_optimiser()
print(int(before), int("torch._dynamo" in sys.modules))
"""


def test_preload_optimiser_does_the_first_optimisers_imports_at_once():
    """A fresh process imports ``torch._dynamo`` with its first torch optimiser (1-2 s, the mapper service's
    init paid it on the first frames' path): preload_optimiser() makes that happen when it is called."""
    before, after = _fresh(_PRELOAD).split()
    assert (before, after) == ("0", "1")
