"""Progress bars that follow the package logger instead of `quiet` flags.

A library function that reports progress takes no `quiet` argument: it logs through its module's
logger (`logging.getLogger("vdo....")`) and draws its bar with `bar(log, ...)`, which is shown
only when that logger passes INFO records. The package logger has a null handler and no level, so
a library user sees nothing unless they configure logging; the command line shows INFO (bars
included) and `--quiet` raises the level to WARNING (`vdo.commands.cli`), through `AboveBars`, which
writes each record above the bars instead of through them.

When the stream is not a terminal (a log file, a pipe, CI), a redrawn bar would write a carriage
return per update, thousands of them on one line; there `bar` returns a `PlainBar` instead: whole
lines, one every `PLAIN_FRACTION` of the total or `PLAIN_SECONDS`, whichever comes first, each with
the count, the elapsed time and the time left (elapsed / n x (total - n), or the caller's own
estimate in `PlainBar.left_s`), and one when it closes.

A total is often an estimate (optimize plans one feasibility round per start, and a start may take
up to three): a count that passes it never shows more than 100 %. A plain line then drops the
percentage and says "past the estimated TOTAL"; a terminal bar grows its total to the count and
says the same beside its description (`past_estimate`).
"""

from __future__ import annotations

import functools
import logging
import sys
import time
from contextlib import contextmanager

PLAIN_FRACTION = 0.1      # a plain progress line every tenth of the total ...
PLAIN_SECONDS = 30.0      # ... or every 30 s, whichever comes first


def past_estimate(total) -> str:
    """The words a bar shows once its count has passed its estimated `total`."""
    return f"past the estimated {total}"


def shown(log: logging.Logger) -> bool:
    """Whether `log` passes INFO records (the condition for a progress bar)."""
    return log.isEnabledFor(logging.INFO)


def bar(log: logging.Logger, **tqdm_options):
    """A progress bar on stderr (or `file`), disabled unless `log` passes INFO records:
    `shown_bar`."""
    return shown_bar(shown(log), **tqdm_options)


@contextmanager
def hidden(*names: str):
    """Hide the progress bars (and INFO lines) of the loggers `names` for the block: a loop
    that calls a function with its own bar many times draws one bar of its own instead."""
    loggers = [logging.getLogger(n) for n in names]
    levels = [g.level for g in loggers]
    for g in loggers:
        if g.getEffectiveLevel() < logging.WARNING:
            g.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for g, level in zip(loggers, levels):
            g.setLevel(level)


def shown_bar(show: bool, **tqdm_options):
    """A tqdm bar on stderr (or the `file` option) when that stream is a terminal, else a
    `PlainBar` (module docstring); disabled unless `show` (`disable=True` still disables it).
    `tqdm_options` as tqdm's; the plain lines use iterable, total, initial, desc, unit, file."""
    from tqdm import tqdm

    disable = tqdm_options.pop("disable", False) or not show
    stream = tqdm_options.get("file") or sys.stderr
    if disable:
        return tqdm(disable=True, **tqdm_options)
    if _is_terminal(stream):
        return _growing_tqdm()(**tqdm_options)
    return PlainBar(**tqdm_options)


def finish_early(progress) -> None:
    """End a bar whose work stopped short of its total (a search that reached its target): the
    total becomes the count, so its last line reads 100 % and no time left, not the unfinished
    total's share and the time the skipped work would have taken. Then closes it."""
    if getattr(progress, "total", None) and progress.n < progress.total:
        progress.total = progress.n
        if hasattr(progress, "refresh") and not isinstance(progress, PlainBar):
            progress.refresh()
    progress.close()


@functools.cache
def _growing_tqdm():
    """tqdm whose total, an estimate, grows to the count once the count passes it, the
    description then saying so (`past_estimate`): never more than 100 %. (A class made on
    first use: tqdm is imported only when a bar is drawn.)"""
    from tqdm import tqdm

    class GrowingTqdm(tqdm):
        def update(self, n=1):
            if self.total and self.n + n > self.total:
                if not getattr(self, "estimate", None):
                    self.estimate = self.total
                    self.set_description_str(f"{self.desc} ({past_estimate(self.estimate)})",
                                             refresh=False)
                self.total = self.n + n
            return super().update(n)

    return GrowingTqdm


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):    # no isatty, or a closed stream
        return False


class PlainBar:
    """tqdm's interface (iteration, update, set_postfix[_str], close, a context manager) as
    plain lines: "desc: n/total unit (p %), elapsed s, ~left s left [postfix]", written when the
    count crosses a multiple of `PLAIN_FRACTION` x total or `PLAIN_SECONDS` have passed since the
    last line, and once on close. Without a total: every `PLAIN_SECONDS`, no time left. A caller
    that knows the time left better (a time limit, uneven steps) sets `left_s` (s)."""

    def __init__(self, iterable=None, total=None, initial=0, desc="", unit="it", file=None,
                 **_drawing_options):   # bar_format, leave, dynamic_ncols ...: a line has no bar
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.iterable, self.total, self.n, self.desc, self.unit = iterable, total, initial, desc, unit
        self.file, self.postfix = file, ""
        self.left_s: float | None = None
        self.t0 = self.last_time = time.monotonic()
        self.last_tenth, self.last_n = self._tenth(), initial
        self.closed = False

    def _tenth(self) -> int:
        if not self.total:
            return 0
        return int(self.n / self.total / PLAIN_FRACTION + 1e-9)

    def line(self) -> str:
        """"desc: n/total unit (p %), elapsed s, ~left s left [postfix]"; past the total (an
        estimate): "desc: n unit (past the estimated total), elapsed s [postfix]", the time left
        only where the caller knows it (`left_s`)."""
        elapsed = time.monotonic() - self.t0
        past = bool(self.total) and self.n > self.total
        if past:
            text = f"{self.desc}: {self.n} {self.unit} ({past_estimate(self.total)})"
        else:
            text = f"{self.desc}: {self.n}" + (f"/{self.total}" if self.total else "") + f" {self.unit}"
            if self.total:
                text += f" ({100 * self.n / self.total:.0f} %)"
        text += f", {elapsed:.0f} s"
        if self.left_s is not None:
            text += f", ~{self.left_s:.0f} s left"
        elif self.total and self.n > 0 and not past:
            text += f", ~{elapsed / self.n * (self.total - self.n):.0f} s left"
        return text + (f" [{self.postfix}]" if self.postfix else "")

    def _write(self) -> None:
        stream = self.file or sys.stderr
        stream.write(self.line() + "\n")
        stream.flush()
        self.last_time, self.last_tenth, self.last_n = time.monotonic(), self._tenth(), self.n

    def update(self, n=1) -> None:
        self.n += n
        if self._tenth() > self.last_tenth or time.monotonic() - self.last_time >= PLAIN_SECONDS:
            self._write()

    def set_postfix_str(self, s="", refresh=True) -> None:
        self.postfix = str(s)

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs) -> None:
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.n != self.last_n:
                self._write()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AboveBars(logging.StreamHandler):
    """A stream handler that writes each record on its own line above the open progress bars
    (`tqdm.write`: the bars are cleared, the line written, the bars drawn again)."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        try:
            tqdm.write(self.format(record), file=self.stream)
            self.flush()
        except Exception:
            self.handleError(record)
