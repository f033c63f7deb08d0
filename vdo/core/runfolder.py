"""Output folders that appear whole or not at all, checked before any work, written only inside.

* `check_out(out, overwrite)` refuses, with a one-line `ConfigError` on the field ``--out``, an
  output folder that the command could not write at the end: an existing non-empty folder (without
  ``--overwrite``), an existing file, a parent path that is a file, a parent folder without write
  permission, a place inside ``/proc``, ``/sys`` or ``/dev``. The command line calls it before it
  loads JAX or Mitsuba; `run_folder` calls it again when it opens the folder.
* `run_folder(out, overwrite)` yields a hidden sibling folder ``.NAME.partial-PID``, renamed to
  NAME when the block ends normally. On an error the partial folder is removed. On SIGINT/SIGTERM
  (`vdo.core.interrupts`) it is removed too, unless the command passed ``on_interrupt``: a function
  ``on_interrupt(folder)`` that writes an anytime result (say, the best layout so far) into the
  partial folder, which is then kept as NAME; the interrupt still ends the command with 130 / 143.
  A command that wants an anytime result must therefore open its run folder before the long work.
* Partial folders left by processes that died without cleaning up (SIGKILL, power loss) are
  removed by the next `check_out` into the same parent: a ``.NAME.partial-PID`` folder whose PID
  is not a running process.
* `is_file(path)`: whether a regular file is there, False for a name the system refuses (too
  long, ...) instead of an OSError: for paths typed by a user.
* `inside(folder, name)` joins a relative name (from a config: a camera or case name) to the run
  folder and refuses any result outside it (``..``, an absolute path, a symbolic link out).
"""

from __future__ import annotations

import os
import re
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from vdo.core import interrupts
from vdo.core.errors import ConfigError

_VIRTUAL = (Path("/proc"), Path("/sys"), Path("/dev"))
_PARTIAL = re.compile(r"^\.(?P<name>.+)\.partial-(?P<pid>\d+)$")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, owned by another user
        return True
    return True


def remove_stale_partials(parent: Path) -> list[Path]:
    """Remove the ``.NAME.partial-PID`` folders in `parent` whose process is gone; returns them.
    (A PID reused by an unrelated live process keeps its folder until that process ends.)"""
    removed = []
    try:
        entries = list(Path(parent).iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = _PARTIAL.match(entry.name)
        if (m and int(m["pid"]) != os.getpid() and not _pid_alive(int(m["pid"]))
                and entry.is_dir() and not entry.is_symlink()):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


def is_file(path) -> bool:
    """Whether `path` is a regular file (symbolic links followed); False where the system
    refuses the name itself (a part longer than NAME_MAX, a NUL byte, ...)."""
    try:
        return Path(path).is_file()
    except (OSError, ValueError):
        return False


def check_out(out, overwrite: bool = False) -> Path:
    """The absolute output folder, after the checks in the module docstring (no file written);
    a name the system refuses (a part longer than NAME_MAX, ...) is a `ConfigError` too."""
    try:
        return _check_out(out, overwrite)
    except ConfigError:
        raise
    except (OSError, ValueError) as exc:       # a name too long, a NUL byte
        why = getattr(exc, "strerror", None) or str(exc)
        raise ConfigError(out, "--out", f"cannot be used as a folder ({why}); choose another "
                                        "path") from None


def _check_out(out, overwrite: bool) -> Path:
    out = Path(out).expanduser().resolve()
    for virtual in _VIRTUAL:
        if out.is_relative_to(virtual):
            raise ConfigError(out, "--out", f"is inside {virtual}, a virtual file system; "
                                            "choose a folder on disk")
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "--out", "exists and is not a folder; choose a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ConfigError(out, "--out", "exists and is not empty; choose a new folder or pass "
                                        "--overwrite")
    existing = out.parent
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(out, "--out", f"{existing} is a file, not a folder; choose another path")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(out, "--out", f"cannot create folders in {existing} (no write "
                                        "permission); choose a writable place")
    if out.is_dir() and overwrite and not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(out, "--out", "cannot be replaced (no write permission)")
    if existing == out.parent:
        remove_stale_partials(existing)
    return out


def inside(folder, name) -> Path:
    """`folder` / `name` for a relative `name` (parts separated by ``/``), refused with a
    `ConfigError` when the result would not lie inside `folder` (``..``, an absolute name, a
    symbolic link that leads out)."""
    folder = Path(folder).resolve()
    name = str(name)
    try:
        target = (folder / name).resolve()
    except (ValueError, OSError):  # a NUL byte, a symbolic-link loop
        target = folder
    if Path(name).is_absolute() or not target.is_relative_to(folder) or target == folder:
        raise ConfigError(folder, "output name", f"{name!r} would be written outside the output "
                                                 "folder; use a plain name (letters, digits, _-.)")
    return target


@contextmanager
def run_folder(out, overwrite: bool = False, *, on_interrupt: Callable[[Path], None] | None = None):
    """Yield a temporary folder that becomes `out` on success (module docstring; `on_interrupt`
    is the anytime-result hook)."""
    out = check_out(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    interrupts.register(partial)
    try:
        partial.mkdir()
        try:
            yield partial
        except BaseException as exc:
            stop = interrupts.interruption(exc)
            if stop is not None and on_interrupt is not None:
                interrupts.acknowledge()  # writing the anytime result may take longer than the grace
                try:
                    on_interrupt(partial)
                    _commit(partial, out)
                except BaseException:
                    shutil.rmtree(partial, ignore_errors=True)
                    raise
            else:
                shutil.rmtree(partial, ignore_errors=True)
            raise
        try:
            _commit(partial, out)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
    finally:
        interrupts.unregister(partial)


def _commit(partial: Path, out: Path) -> None:
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)
