"""Process-wide settings, in one place: `configure()`.

Importing a vdo module changes nothing outside it. The settings that vdo's computations need are
applied by one idempotent call, which the command line makes after it has validated its input, the
test suite makes at session start, and a worker process or a library user makes before the first
vdo computation:

* ``jax_enable_x64``: vdo computes in float64 (the objective's per-pair work may opt into float32,
  see `vdo.objective`). `require_x64()` raises a clear error where this was forgotten.
* JAX's persistent compilation cache in ``cache_dir() / "jax"``, for every compiled program
  (`MIN_COMPILE_S` = 0; programs holding a host callback are never cached, by JAX's rule), so
  that a second run (or test session, or worker) loads the compiled programs instead of
  compiling them again. An explicit ``JAX_COMPILATION_CACHE_DIR``
  (or ``jax_compilation_cache_dir`` set before) is kept.
* matplotlib's non-interactive ``Agg`` backend (vdo only writes figures to files).
* glibc's malloc options of `vdo.core.memory.retain_freed_memory` (call before the first JAX
  computation: threads that allocated before keep their own arenas).
* The Mitsuba variant and the Dr.Jit thread count (`vdo.core.backend.configure`; applied when Mitsuba
  is first needed).

The cache folder: ``$VDO_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/vdo``, else
``~/.cache/vdo``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vdo.core import backend
from vdo.core.memory import retain_freed_memory

log = logging.getLogger(__name__)

MIN_COMPILE_S = 0.0  # every program goes into the persistent cache: the many small ones (~5-50 ms
                     # each) add up to seconds per run


def cache_dir() -> Path:
    """vdo's cache folder (module docstring); not created here."""
    if os.environ.get("VDO_CACHE_DIR"):
        return Path(os.environ["VDO_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "vdo"


def configure(*, compilation_cache: bool = True, retain_memory: bool = True,
              variant: str | None = None, threads: int | None = None) -> None:
    """Apply the settings of the module docstring; calling it again changes nothing more.

    compilation_cache  use JAX's persistent compilation cache (False: leave JAX's setting alone)
    retain_memory      apply the malloc options of `vdo.core.memory` (glibc only)
    variant, threads   Mitsuba variant (default: ``$VDO_VARIANT``, else CUDA when usable, else
                       ``llvm_ad_rgb``) and Dr.Jit thread count (default: the CPUs this process
                       may run on), see `vdo.core.backend`
    """
    if retain_memory:
        retain_freed_memory()
    import jax

    jax.config.update("jax_enable_x64", True)
    if compilation_cache:
        if jax.config.jax_compilation_cache_dir is None:
            folder = cache_dir() / "jax"
            folder.mkdir(parents=True, exist_ok=True)
            jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
        log.debug("JAX compilation cache: %s", jax.config.jax_compilation_cache_dir)
    import matplotlib

    matplotlib.use("Agg")
    backend.configure(variant=variant, threads=threads)


def require_x64() -> None:
    """Raise a clear error when `configure()` (or ``jax_enable_x64``) was not applied: without it
    JAX silently rounds vdo's float64 inputs to float32."""
    import jax

    if not jax.config.jax_enable_x64:
        raise RuntimeError("vdo computes in float64: call vdo.configure() once before using vdo "
                           "(it enables JAX's jax_enable_x64, among other settings)")
