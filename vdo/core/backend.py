"""Mitsuba / Dr.Jit set-up: the variant, the libLLVM it needs, the thread count.

Every module that uses Mitsuba gets it from `mitsuba()` here, so the variant is chosen once:
``cuda_ad_rgb`` when a CUDA device is usable, else ``llvm_ad_rgb`` (what tests and CI use). The
environment variable ``VDO_VARIANT``, or `configure(variant=...)` (what `vdo.core.configure` passes on),
overrides the choice; `configure(threads=...)` sets Dr.Jit's thread count (default: the CPUs this
process may run on).

Dr.Jit's CPU backend loads a shared libLLVM at run time. It refuses LLVM 14 and LLVM 15 aborted on
a plain render on Debian 12, so we point ``DRJIT_LIBLLVM_PATH`` at the newest libLLVM >= 16 we find
before Dr.Jit is imported, and fail with the command that fixes it when there is none.
"""

from __future__ import annotations

import functools
import glob
import os
import re

from vdo.core import interrupts

MIN_LLVM = 16
EXR_MIN_THREADS = 2   # Dr.Jit pool threads during an OpenEXR write (`write_exr`)
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)


class BackendError(RuntimeError):
    """Mitsuba or Dr.Jit cannot start on this machine; the message says what to install."""


def _llvm_version(path: str) -> int | None:
    m = re.search(r"libLLVM-?(\d+)|libLLVM\.so\.(\d+)", os.path.basename(path))
    return int(m.group(1) or m.group(2)) if m else None


def find_libllvm() -> str | None:
    """Newest shared libLLVM >= MIN_LLVM on the usual Debian/Ubuntu paths, or None."""
    found = []
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            version = _llvm_version(path)
            if version is not None and version >= MIN_LLVM:
                found.append((version, path))
    return max(found)[1] if found else None


def _cuda_available() -> bool:
    return any(os.path.exists(p) for p in ("/dev/nvidia0", "/dev/nvidiactl"))


_chosen = {"variant": None, "threads": None}


def configure(variant: str | None = None, threads: int | None = None) -> None:
    """Choose the Mitsuba variant and the Dr.Jit thread count (None: the defaults above). Applied
    at the next `mitsuba()`; the thread count at once when Mitsuba is already loaded."""
    if variant != _chosen["variant"]:
        mitsuba.cache_clear()
    _chosen.update(variant=variant, threads=threads)
    if threads is not None and mitsuba.cache_info().currsize:
        import drjit as dr

        if dr.has_backend(dr.JitBackend.LLVM):
            dr.set_thread_count(threads)


def cpu_threads() -> int:
    """The CPU threads this process's numerical work uses: `configure(threads=...)` (a worker's
    share of the machine), else every core it may run on (`vdo.core.parallel.cores`: by affinity,
    not by container quota)."""
    from vdo.core.parallel import cores

    return _chosen["threads"] or cores()


@functools.cache
def mitsuba():
    """The `mitsuba` module with vdo's variant set (first call chooses it; a CUDA variant that
    cannot start falls back to ``llvm_ad_rgb``)."""
    variant = (_chosen["variant"] or os.environ.get("VDO_VARIANT")
               or ("cuda_ad_rgb" if _cuda_available() else "llvm_ad_rgb"))
    try:
        return _load(variant)
    except BackendError:
        if not variant.startswith("cuda"):
            raise
        return _load("llvm_ad_rgb")


def _load(variant: str):
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        libllvm = find_libllvm()
        if libllvm is None:
            raise BackendError(
                f"Dr.Jit's CPU backend needs a shared libLLVM >= {MIN_LLVM} and none was found. "
                "Install it with `sudo apt-get install -y libllvm19` (Debian/Ubuntu), or set "
                "DRJIT_LIBLLVM_PATH to a libLLVM.so of version 16 or newer."
            )
        os.environ["DRJIT_LIBLLVM_PATH"] = libllvm  # Dr.Jit reads it when it starts its backend
    with interrupts.held():  # no KeyboardInterrupt inside a native module's initialisation
        import drjit as dr
        import mitsuba as mi

        try:
            mi.set_variant(variant)
        except (ImportError, AttributeError, RuntimeError) as exc:
            raise BackendError(
                f"Mitsuba variant {variant!r} could not start ({exc}). For the CPU variant install "
                "`libllvm19` (sudo apt-get install -y libllvm19)."
            ) from exc
    if variant.startswith("llvm"):
        dr.set_thread_count(cpu_threads())
    return mi


def write_exr(path, image) -> None:
    """Write `image` (H, W), linear values, as a one-channel float32 OpenEXR file with Mitsuba's
    `Bitmap`. Mitsuba's EXR writer never returns when Dr.Jit's thread pool has one thread (a
    one-CPU machine or batch job, `taskset -c 0`, `configure(threads=1)`): the pool is given
    `EXR_MIN_THREADS` for the write and its own count back after it."""
    import numpy as np

    mi = mitsuba()
    import drjit as dr

    threads = dr.thread_count()
    if threads < EXR_MIN_THREADS:
        dr.set_thread_count(EXR_MIN_THREADS)
    try:
        mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)[..., None]).write(str(path))
    finally:
        if threads < EXR_MIN_THREADS:
            dr.set_thread_count(threads)
