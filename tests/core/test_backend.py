"""Mitsuba's set-up in `vdo.core.backend`: an OpenEXR write with a one-thread Dr.Jit pool."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
EXR_WRITE_S = 120   # the write takes well under a second; without the fix it never returns

SCRIPT = """
import sys
import numpy as np
import drjit as dr
from vdo.core.configure import configure
configure(compilation_cache=False, threads=1)
from vdo.core.backend import mitsuba, write_exr
mitsuba()
image = np.random.default_rng(0).random((48, 64)).astype(np.float32)
write_exr(sys.argv[1], image)
print(dr.thread_count())
"""


def test_exr_written_with_a_one_thread_pool(tmp_path):
    """On one CPU (a one-core job, `taskset -c 0`, `threads=1`) Mitsuba's EXR writer waits for a
    pool thread that never comes: `write_exr` lends the pool a second thread for the write. The
    file holds the image to the bit, and the pool has its one thread again."""
    path = tmp_path / "one.exr"
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(path)], cwd=ROOT, capture_output=True,
                         text=True, timeout=EXR_WRITE_S)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["1"]
    from vdo.core.backend import mitsuba

    back = np.array(mitsuba().Bitmap(str(path)))
    assert np.array_equal(back.reshape(48, 64), np.random.default_rng(0).random((48, 64)).astype(np.float32))
