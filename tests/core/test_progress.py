"""Progress off a terminal (`vdo.core.progress`): plain whole lines, a bounded number of them, each
with the time left, instead of a bar redrawn by carriage returns."""

from __future__ import annotations

import io
import logging

import pytest

from vdo.core import progress

LOG = logging.getLogger("vdo.test_progress")


class FakeClock:
    """time.monotonic advanced by hand (seconds)."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(progress.time, "monotonic", fake)
    return fake


@pytest.fixture
def shown():
    """LOG passes INFO records for the test, through setLevel: it clears the loggers' cache of
    isEnabledFor, which a level set as an attribute leaves stale from an earlier test."""
    level = LOG.level
    LOG.setLevel(logging.INFO)
    yield
    LOG.setLevel(level)


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_off_a_terminal_lines_every_tenth_with_the_time_left(shown, clock):
    """1000 updates, 0.05 s each (50 s in all, under 30 s between tenths): one line per tenth,
    no carriage return, and the time left at each line is elapsed / n x (total - n)."""
    stream = io.StringIO()
    with progress.bar(LOG, total=1000, desc="validate", unit="seed", file=stream) as bar:
        assert isinstance(bar, progress.PlainBar)
        for k in range(1000):
            clock.now += 0.05
            bar.set_postfix_str(f"case{k // 300}")
            bar.update()
    text = stream.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == round(1 / progress.PLAIN_FRACTION)
    assert lines[0] == "validate: 100/1000 seed (10 %), 5 s, ~45 s left [case0]"
    assert lines[4] == "validate: 500/1000 seed (50 %), 25 s, ~25 s left [case1]"
    assert lines[-1].startswith("validate: 1000/1000 seed (100 %), 50 s, ~0 s left")


def test_off_a_terminal_slow_work_gets_a_line_every_30_s(shown, clock):
    """20 updates of 40 s each: every update is more than PLAIN_SECONDS after the last line, so
    each gets one (20 lines, none drawn in place); an open-ended count (no total) gets a line
    per PLAIN_SECONDS and one on close."""
    stream = io.StringIO()
    bar = progress.bar(LOG, total=20, desc="optimize", unit="step", file=stream,
                       bar_format="{desc}", dynamic_ncols=True)
    for _ in range(20):
        clock.now += 40.0
        bar.update(1)
    bar.close()
    bar.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 20 and "\r" not in stream.getvalue()
    assert lines[1] == "optimize: 2/20 step (10 %), 80 s, ~720 s left"

    stream = io.StringIO()
    for _ in progress.shown_bar(True, iterable=iter(range(95)), desc="rays", unit="batch",
                                file=stream):
        clock.now += 1.0
    lines = stream.getvalue().splitlines()
    assert lines == ["rays: 30 batch, 30 s", "rays: 60 batch, 60 s", "rays: 90 batch, 90 s",
                     "rays: 95 batch, 95 s"]


def test_a_terminal_gets_the_tqdm_bar_and_a_quiet_logger_nothing(shown):
    from tqdm import tqdm

    bar = progress.bar(LOG, total=10, file=Terminal())
    assert isinstance(bar, tqdm) and not bar.disable
    bar.close()
    LOG.setLevel(logging.WARNING)
    stream = io.StringIO()
    quiet = progress.bar(LOG, total=10, file=stream)
    for _ in range(10):
        quiet.update()
    quiet.close()
    assert stream.getvalue() == ""


def optimizer_lines(monkeypatch, capsys, planned: int, steps: int, time_limit: float) -> list[str]:
    """The plain lines of `vdo optimize`'s progress (`vdo.search.anytime.Progress`) for `steps`
    steps of 1 s each, `planned` steps planned, under `time_limit` s."""
    from vdo.search import anytime

    monkeypatch.setattr(logging.getLogger(anytime.__name__), "level", logging.INFO)
    now = [0.0]
    monkeypatch.setattr(anytime.time, "perf_counter", lambda: now[0])
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    bar = anytime.Progress(planned, anytime.Stop(time_limit=time_limit))
    for k in range(steps):
        now[0] += 1.0
        bar.step(f"start 1 round 1/3, step {k + 1}/{planned}", None)
    bar.close()
    return capsys.readouterr().err.splitlines()


def test_the_optimizer_line_says_its_own_time_left_once(monkeypatch, capsys):
    """`vdo optimize` off a terminal: 10 steps of a planned 100 in 1 s each under a time limit of
    30 s: the steps left at the mean rate would take 90 s, the limit leaves ~20 s; each plain
    line says "s left" once, the lesser figure (the search stops at the limit)."""
    lines = optimizer_lines(monkeypatch, capsys, planned=100, steps=10, time_limit=30.0)
    assert lines and all(line.count("s left") == 1 for line in lines)
    assert lines[0] == ("optimize: 10/100 step (10 %), 10 s, ~20 s left "
                        "[start 1 round 1/3, step 10/100, no layout judged yet]")


def test_a_count_past_the_estimated_total_never_shows_more_than_100_percent(shown, clock):
    """A total is an estimate (trial 4's optimize: "528/480 step (110 %)"): off a terminal the
    lines past it drop the percentage and the time left and say "past the estimated 480"; a
    terminal bar grows its total to the count (100 %) and says the same in its description."""
    stream = io.StringIO()
    bar = progress.bar(LOG, total=480, desc="optimize", unit="step", file=stream)
    for _ in range(547):
        clock.now += 0.1
        bar.update(1)
    bar.close()
    lines = stream.getvalue().splitlines()
    assert lines[9] == "optimize: 480/480 step (100 %), 48 s, ~0 s left"
    assert lines[10:] == ["optimize: 528 step (past the estimated 480), 53 s",
                          "optimize: 547 step (past the estimated 480), 55 s"]
    assert not any("%" in line for line in lines[10:])

    terminal = Terminal()
    bar = progress.bar(LOG, total=480, desc="optimize", unit="step", file=terminal,
                       bar_format="{desc}: {n}/{total} steps ({percentage:.0f} %)")
    bar.update(528)
    assert (bar.n, bar.total) == (528, 528)
    assert str(bar) == "optimize (past the estimated 480): 528/528 steps (100 %)"
    bar.update(19)
    assert str(bar) == "optimize (past the estimated 480): 547/547 steps (100 %)"
    bar.close()


def test_the_optimizer_past_its_plan_says_the_time_limit_left(monkeypatch, capsys):
    """`vdo optimize` past its planned steps (feasibility rounds beyond the plan's one): the
    line says the step count past the estimate, and the time left is the time limit's (the
    mean rate over no steps left said ~0 s)."""
    lines = optimizer_lines(monkeypatch, capsys, planned=10, steps=12, time_limit=100.0)
    assert lines[-1] == ("optimize: 12 step (past the estimated 10), 12 s, ~88 s left "
                         "[start 1 round 1/3, step 12/10, no layout judged yet]")


def test_hidden_silences_an_inner_bar_and_restores_the_level(shown):
    """`hidden`: a bar of the named logger writes nothing inside the block, the logger's own
    level comes back after it (also when the block raises), and other loggers keep theirs."""
    inner = logging.getLogger("vdo.test_progress.inner")
    stream = io.StringIO()
    with pytest.raises(KeyError):
        with progress.hidden(LOG.name):
            quiet = progress.bar(LOG, total=4, file=stream)
            for _ in range(4):
                quiet.update()
            quiet.close()
            assert inner.getEffectiveLevel() >= logging.WARNING    # a child follows its parent
            raise KeyError
    assert stream.getvalue() == "" and LOG.level == logging.INFO
    loud = progress.bar(LOG, total=4, file=stream)
    for _ in range(4):
        loud.update()
    loud.close()
    assert "4/4" in stream.getvalue()


def test_work_that_ends_before_its_total_ends_at_100_percent(shown, clock):
    """`finish_early` (the calibration planner once its target is reached: 7 of 105 poses):
    the last line is the count over itself, with no time left, not 7 % and the time that the
    skipped 98 would have taken; on a terminal, tqdm's total becomes the count the same way."""
    stream = io.StringIO()
    bar = progress.bar(LOG, total=105, desc="planning the session", unit="pose", file=stream)
    clock.now += 9.0
    bar.update(7)
    progress.finish_early(bar)
    last = stream.getvalue().splitlines()[-1]
    assert last == "planning the session: 7/7 pose (100 %), 9 s, ~0 s left"
    terminal = Terminal()
    drawn = progress.bar(LOG, total=105, desc="planning the session", unit="pose", file=terminal)
    drawn.update(7)
    progress.finish_early(drawn)
    assert drawn.total == 7 and "7/7" in terminal.getvalue().split("\r")[-1]
