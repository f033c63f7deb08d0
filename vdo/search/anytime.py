"""Anytime search: a `Stop` request (time limit, SIGINT/SIGTERM via `stop_on_signals`) checked
between solver steps and rounds and while a program compiles (`until_stopped`), and the one
progress line (`Progress`) over the planned steps."""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import threading
import time
from typing import Callable, Protocol

from vdo.core.progress import PlainBar, bar

log = logging.getLogger(__name__)


class Best(Protocol):
    """What the progress line reads of the best result so far (`vdo.search.problem.Result`)."""

    score: float
    violations: int


# --------------------------------------------------------------------------------------------
# Stopping early, and what a run shares
# --------------------------------------------------------------------------------------------
class Stop:
    """A request to end the search early, checked between solver steps and between rounds (never
    inside a JAX or Dr.Jit call): `request` sets it (a signal handler, a caller), and so does the
    clock once `time_limit` seconds have passed since it was made. `reason` is None,
    "time_limit" or "interrupted"."""

    def __init__(self, time_limit: float = math.inf):
        self.deadline = time.perf_counter() + time_limit
        self.reason: str | None = None

    def request(self, reason: str = "interrupted") -> None:
        if self.reason is None:
            self.reason = reason

    def __call__(self) -> bool:
        """True once a stop was requested or the time limit has passed."""
        if self.reason is None and time.perf_counter() >= self.deadline:
            self.reason = "time_limit"
        return self.reason is not None

    @property
    def left(self) -> float:
        """Seconds to the time limit (inf without one)."""
        return max(self.deadline - time.perf_counter(), 0.0)


POLL_S = 0.1     # how often a wait (`until_stopped`) looks at the stop request (s)


def until_stopped(stop: Stop, fn):
    """fn() run in a worker thread and waited for while `stop` allows: (True, its value), or
    (False, None) once the stop request comes first (the time limit, Ctrl-C or SIGTERM: the main
    thread keeps receiving signals while it waits, every POLL_S). For what cannot be interrupted
    from inside, a program's first call that compiles it: XLA's compilation is not cancellable,
    so the thread is left to finish on its own (a daemon: it does not hold the process at exit)
    and its result is dropped. An exception in fn is raised here."""
    job = Beside(fn, name="vdo-compile")
    while job.thread.is_alive():
        job.thread.join(timeout=min(POLL_S, max(stop.left, 1e-3)))
        if job.thread.is_alive() and stop():
            return False, None
    return True, job.result()


class Beside:
    """fn(*args) run from now in a daemon thread beside the caller (native solvers, XLA's
    compiler and NumPy's kernels release the GIL, so it can use another core; a daemon does not
    hold up the process when it is interrupted). `result()` waits for it and returns its value,
    or raises its exception."""

    def __init__(self, fn: Callable, *args, name: str = "vdo-beside"):
        self._box: dict = {}

        def work():
            try:
                self._box["value"] = fn(*args)
            except BaseException as exc:      # handed to the waiting thread
                self._box["error"] = exc

        self.thread = threading.Thread(target=work, name=name, daemon=True)
        self.thread.start()

    def result(self):
        self.thread.join()
        if "error" in self._box:
            raise self._box["error"]
        return self._box["value"]


@contextlib.contextmanager
def stop_on_signals(stop: Stop):
    """While inside: SIGINT (Ctrl-C) and SIGTERM request `stop` instead of raising; a second
    SIGINT raises KeyboardInterrupt as usual. The previous handlers come back on exit. Outside the
    main thread (where Python delivers no signals) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if signum == signal.SIGINT and stop.reason == "interrupted":
            raise KeyboardInterrupt
        stop.request("interrupted")
        log.warning("%s: stopping after the current step; the best layout so far will be written "
                    "(Ctrl-C again to abort without writing)", signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


class Progress:
    """One progress line (tqdm) over the planned solver steps: start, round, step, the best
    score so far (µm; feasible layouts first) and the time left, the least of the time limit
    and the steps left at the mean time per step so far (refreshes and checks included). The
    plan is an estimate (one feasibility round per start; a start may take up to
    `vdo.search.solver.FEASIBILITY_ROUNDS`): past it the bar says so (`vdo.core.progress`) and
    the time left is the time limit's."""

    def __init__(self, planned: int | None, stop: Stop | None = None):
        self.planned, self.stop, self.done = planned, stop, 0
        self.t0 = time.perf_counter()
        self.bar = bar(log, total=planned, desc="optimize", unit="step", disable=planned is None,
                       bar_format="{desc}: {n}/{total} steps{postfix}", dynamic_ncols=True)

    def left(self) -> float:
        """The time left (s): class docstring."""
        if self.stop is not None and self.planned is not None and self.done >= self.planned:
            return self.stop.left
        rate = (time.perf_counter() - self.t0) / max(self.done, 1)
        est = rate * max((self.planned or 0) - self.done, 0)
        return min(est, self.stop.left) if self.stop is not None else est

    def step(self, where: str, best: Best | None) -> None:
        self.done += 1
        if best is None:
            text = "no layout judged yet"
        else:
            text = f"best {best.score:.4g} µm" + ("" if best.violations == 0 else
                                                  f" ({best.violations} violation(s))")
        if isinstance(self.bar, PlainBar):      # the line's own "time left" is this estimate
            self.bar.left_s = self.left()
            self.bar.set_postfix_str(f"{where}, {text}", refresh=False)
        else:
            self.bar.set_postfix_str(f"{where}, {text}, ~{self.left():.0f} s left", refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()
