"""Progress bars that follow the package logger instead of `quiet` flags.

A library function that reports progress takes no `quiet` argument: it logs through its module's
logger (`logging.getLogger("vdo....")`) and draws its bar with `bar(log, ...)`, which is shown
only when that logger passes INFO records. The package logger has a null handler and no level, so
a library user sees nothing unless they configure logging; the command line shows INFO (bars
included) and `--quiet` raises the level to WARNING (`vdo.commands.cli`), through `AboveBars`, which
writes each record above the bars instead of through them.
"""

from __future__ import annotations

import logging


def shown(log: logging.Logger) -> bool:
    """Whether `log` passes INFO records (the condition for a progress bar)."""
    return log.isEnabledFor(logging.INFO)


def bar(log: logging.Logger, **tqdm_options):
    """A tqdm bar (stderr), disabled unless `log` passes INFO records; `tqdm_options` as tqdm's
    (`disable=True` still disables it)."""
    from tqdm import tqdm

    disable = tqdm_options.pop("disable", False) or not shown(log)
    return tqdm(disable=disable, **tqdm_options)


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
