"""SIGINT and SIGTERM: every command ends promptly, with exit status 130 / 143 and no half output.

`install()` (the command line calls it first thing) makes both signals raise `Interrupted`, a
`KeyboardInterrupt` that carries the signal number, in the main thread. The exception unwinds
through `vdo.core.runfolder.run_folder`, which removes its hidden partial folder (or, when the command
asked for it, writes an anytime result there and keeps it), and `vdo.commands.cli.main` turns it into one
line on stderr and the status 128 + signal number.

Four things can keep the exception from arriving, or make it harmful, and each is handled here:

* An exception raised while a native module initialises (importing JAX or Mitsuba) can crash the
  interpreter (a segmentation fault was seen with Ctrl-C during ``import jaxlib``). Heavy imports
  therefore run inside `held()`: a signal that arrives there ends the process at once when no
  output folder is open (nothing to remove or keep), else is raised when the block ends.
* Python runs signal handlers between bytecodes, so an exception raised while a garbage-collector
  callback runs (JAX registers one, `_xla_gc_callback`) is printed as "Exception ignored" and
  dropped. `sys.unraisablehook` sees it; the signal is delivered again, to run at the next bytecode
  of the main thread.
* A native library may catch the exception and raise its own: Mitsuba's render wraps it as
  ``RuntimeError: drjit.custom(...)``. `interruption(exc)` therefore answers from the signal that
  was received, whatever the exception.
* Native code may run for long without returning to Python. A watchdog thread started by the
  signal removes the registered partial folders and ends the process with the same status
  `GRACE_S` seconds later, unless `acknowledge()` says that the exception was caught by code that
  handles it. A second signal ends the process at once the same way.
"""

from __future__ import annotations

import _thread
import os
import shutil
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

GRACE_S = 2.0
REDELIVER_S = 0.01
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread by SIGINT or SIGTERM once `install()` ran."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)

    @property
    def message(self) -> str:
        """The one line the command line prints."""
        return f"vdo: interrupted by {signal.Signals(self.signum).name}"

    @property
    def exit_code(self) -> int:
        """128 + signal number: 130 for SIGINT, 143 for SIGTERM (the shell's convention)."""
        return 128 + self.signum


_lock = threading.RLock()  # the handler may run while the main thread holds it
_received: int | None = None
_redelivering = False
_holding = 0
_pending = False
_watchdog: threading.Timer | None = None
_partials: set[Path] = set()


def register(folder: Path) -> None:
    """Name a partial output folder that an abort must remove (`vdo.core.runfolder` calls this)."""
    with _lock:
        _partials.add(Path(folder))


def unregister(folder: Path) -> None:
    with _lock:
        _partials.discard(Path(folder))


def received() -> int | None:
    """The number of the signal received since `install()`, or None."""
    return _received


def interruption(exc: BaseException) -> Interrupted | None:
    """The interrupt behind `exc`: any exception once a signal was received (native code may wrap
    the `Interrupted` in its own error), a `KeyboardInterrupt` anywhere in its cause/context chain
    otherwise (Ctrl-C in a process where `install()` did not run); None for other errors."""
    if _received is not None:
        return exc if isinstance(exc, Interrupted) else Interrupted(_received)
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc if isinstance(exc, Interrupted) else Interrupted(signal.SIGINT)
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def acknowledge() -> None:
    """The interrupt reached code that handles it: stop the watchdog (a second signal still aborts)."""
    global _watchdog
    with _lock:
        if _watchdog is not None:
            _watchdog.cancel()
            _watchdog = None


def _abort(signum: int) -> None:
    """Remove the registered partial folders and end the process now with 128 + signum."""
    with _lock:
        folders = list(_partials)
    for folder in folders:
        shutil.rmtree(folder, ignore_errors=True)
    try:
        sys.stderr.write(Interrupted(signum).message + "\n")
        sys.stderr.flush()
    finally:
        os._exit(128 + signum)


def _handler(signum, frame):
    global _received, _redelivering, _watchdog, _pending
    if _redelivering:
        _redelivering = False
        raise Interrupted(signum)
    if _received is not None:
        _abort(_received)  # a second signal: the user insists
    _received = signum
    with _lock:
        _watchdog = threading.Timer(GRACE_S, _abort, (signum,))
        _watchdog.daemon = True
        _watchdog.start()
    if _holding:
        if not _partials:  # nothing written yet, nothing to keep: end at once
            _abort(signum)
        _pending = True
        return
    raise Interrupted(signum)


@contextmanager
def held():
    """Run the block (heavy imports) without raising `Interrupted` inside it; a signal received
    meanwhile is raised when the block ends (the watchdog still ends the process after `GRACE_S`)."""
    global _holding, _pending
    _holding += 1
    try:
        yield
    finally:
        _holding -= 1
    if not _holding and _pending:
        _pending = False
        raise Interrupted(_received)


def _redeliver(signum: int) -> None:
    time.sleep(REDELIVER_S)
    os.kill(os.getpid(), signum)


def _unraisable(unraisable):
    """An `Interrupted` raised inside a gc callback (or a finaliser) is dropped by Python: raise
    the signal again, so that the handler runs at the next bytecode of the main thread."""
    global _redelivering
    if isinstance(unraisable.exc_value, Interrupted) and _received is not None:
        _redelivering = True  # from another thread, started without waiting: not inside this hook
        _thread.start_new_thread(_redeliver, (_received,))
        return
    _previous_unraisablehook(unraisable)


_previous_unraisablehook = sys.__unraisablehook__


def install():
    """Route SIGINT and SIGTERM to `Interrupted` (main thread only). Returns a function that puts
    the previous handlers back (the command line calls it when it returns, so that calling
    `vdo.commands.cli.main` in a test leaves the process as it was)."""
    global _received, _redelivering, _pending, _previous_unraisablehook
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    _received, _redelivering, _pending = None, False, False
    previous = {s: signal.signal(s, _handler) for s in SIGNALS}
    previous_hook = sys.unraisablehook
    _previous_unraisablehook = previous_hook
    sys.unraisablehook = _unraisable

    def restore():
        global _received, _redelivering, _pending
        acknowledge()
        for s, h in previous.items():
            signal.signal(s, h)
        sys.unraisablehook = previous_hook
        _received, _redelivering, _pending = None, False, False

    return restore
