"""Output folders that appear whole or not at all.

Work is written into a hidden sibling folder ``.NAME.partial-PID`` and renamed to NAME when the
command succeeds; on any error (or Ctrl-C) the partial folder is removed, so an output folder never
holds half of a run.
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from .errors import ConfigError


@contextmanager
def run_folder(out, overwrite: bool = False):
    """Yield a temporary folder that becomes `out` on success."""
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "--out", "exists and is not a folder; choose a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ConfigError(out, "--out", "exists and is not empty; choose a new folder or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        yield partial
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)
