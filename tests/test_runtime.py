"""Process settings for solves: restored afterwards, applied where the platform has them."""
import sys

import pytest
import torch

from hemirad.core.runtime import keep_freed_memory, torch_threads


def test_torch_threads_sets_and_restores_the_pool():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("a failing solve")
    assert torch.get_num_threads() == before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_freed_memory_takes_on_glibc_and_is_idempotent():
    import platform
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_freed_memory() is True
    assert keep_freed_memory() is True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_freed_heap_past_what_is_kept_goes_back_to_the_system():
    # In a fresh process: 200 MB of 100 kB blocks kept in the heap (keep_freed_memory), nine
    # in ten freed, the tenth holding the pages between them: the freed heap stays resident
    # until release_freed_memory hands it back, and only past what it is told to keep.
    import platform
    import subprocess
    libc, version = platform.libc_ver()
    if libc != "glibc" or tuple(int(part) for part in version.split(".")[:2]) < (2, 33):
        pytest.skip("mallinfo2 needs glibc 2.33 or later")
    code = ("import numpy as np\n"
            "from hemirad.core.runtime import keep_freed_memory, release_freed_memory\n"
            "import os\n"
            "rss = lambda: int(open('/proc/self/statm').read().split()[1]) * os.sysconf('SC_PAGE_SIZE')\n"
            "keep_freed_memory()\n"
            "blocks = [np.ones(100_000 // 8) for _ in range(2000)]\n"
            "kept = blocks[::10]\n"
            "del blocks\n"
            "before = rss()\n"
            "print(release_freed_memory(1 << 40), release_freed_memory(64 << 20), before - rss())\n")
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert ran[:2] == ["False", "True"]
    assert int(ran[2]) > 100 << 20  # most of the 180 MB freed


@pytest.mark.parametrize("asked", [None, "3"])
def test_the_rasteriser_gets_one_core_fewer_unless_the_user_chose(asked):
    # A sweep's two threads work beside llvmpipe's; LP_NUM_THREADS is read when the context is
    # made, so a fresh process shows what it was given.
    import os
    import subprocess
    env = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    if asked is not None:
        env["LP_NUM_THREADS"] = asked
    code = ("import os; from hemirad.transport.gl import GLContext; GLContext.get(); "
            "names = [open(f'/proc/self/task/{t}/comm').read() for t in os.listdir('/proc/self/task')]; "
            "print(os.environ['LP_NUM_THREADS'], GLContext.is_software(), "
            "sum(name.startswith('llvmpipe') for name in names))")
    given, software, raster_threads = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                                     text=True, check=True).stdout.split()
    cores = len(os.sched_getaffinity(0))
    assert given == (asked or str(max(1, cores - 1)))
    if software == "True" and sys.platform.startswith("linux"):
        assert int(raster_threads) == int(given)
