"""`vdo.core.memory.retain_freed_memory`: a large block freed and allocated again no longer faults its
pages in again (counted by the kernel, `getrusage`), in a fresh process as the command line uses it;
`release_freed_memory` gives the retained heap's free pages back."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import resource, sys
import numpy as np
if sys.argv[1] == "retain":
    from vdo.core.memory import retain_freed_memory
    assert retain_freed_memory()
faults = []
for _ in range(5):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(2 ** 24)  # 128 MB, every page written
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(*faults)
"""


def _faults(mode):
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc options")
def test_freed_memory_is_reused_without_page_faults():
    default, retained = _faults("default"), _faults("retain")
    # glibc maps and unmaps the block every time: every allocation faults its pages in again. How
    # many faults a 128 MB block costs depends on how much of it the kernel backs with 2 MiB huge
    # pages (32,768 faults with none, 576 here, 2,109 on the CI machine): compare with that figure
    assert min(default) >= 0.5 * max(default) > 0
    # retained: the first allocation faults its pages in, the next four reuse them
    assert retained[0] > 0
    assert max(retained[1:]) <= 0.01 * min(default), (default, retained)


RELEASE_SCRIPT = """
import sys
import numpy as np
from vdo.core.memory import release_freed_memory, retain_freed_memory
assert retain_freed_memory()

def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096

blocks = [np.ones(2 ** 17) for _ in range(2000)]   # 2,000 blocks of 1 MB, every page written
kept = blocks[::4]                                 # a quarter stays: the freed ones are holes
del blocks
before = rss()
assert release_freed_memory()
print(before, rss())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc_trim")
def test_release_gives_the_retained_heaps_free_pages_back():
    """With the heap retained (`retain_freed_memory`), 1.5 GB of freed 1 MB blocks between kept
    ones stay resident until `release_freed_memory` (glibc `malloc_trim(0)`) gives their pages
    back: the resident size falls by at least 1 GB (/proc/self/statm)."""
    out = subprocess.run([sys.executable, "-c", RELEASE_SCRIPT], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    before, after = (int(x) for x in out.split())
    assert before - after >= 2 ** 30, (before, after)
