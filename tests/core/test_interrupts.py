"""SIGINT and SIGTERM end `vdo` promptly with 130 / 143, one line on stderr and no output folder,
at start-up (imports, JAX start), mid-computation and mid-write; and importing vdo changes no
process-wide setting until `vdo.configure()`."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import DOWN_CAMERA
from vdo.core.interrupts import GRACE_S

ROOT = Path(__file__).resolve().parents[2]
PROMPT_S = GRACE_S + 1.5   # the watchdog's grace plus the process's own exit
SETTLE_S = 0.2             # stderr quiet this long before the signal ...
SETTLE_MAX_S = 1.0         # ... or this long at most (progress lines may keep coming)


class Run:
    """`python -m vdo ARGS` in the background; stdout and stderr collected line by line."""

    def __init__(self, *args, env=None):
        self.lines: list[str] = []
        self.proc = subprocess.Popen([sys.executable, "-m", "vdo", *map(str, args)], cwd=ROOT,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env=env)
        self.err: list[str] = []
        self._readers = [threading.Thread(target=self._read, args=(s, sink), daemon=True)
                         for s, sink in ((self.proc.stdout, self.lines), (self.proc.stderr, self.err))]
        for r in self._readers:
            r.start()

    def _read(self, stream, sink):
        for line in stream:
            sink.append(line.rstrip("\n"))

    def wait_for(self, ready, timeout=120.0):
        """Poll `ready()` until true; fails if the process ends first."""
        end = time.monotonic() + timeout
        while not ready():
            assert self.proc.poll() is None, f"ended before the marker: {self.err[-5:]}"
            assert time.monotonic() < end, "marker never came"
            time.sleep(0.01)

    def settle(self):
        """Let the reader catch up with what the command already wrote: wait until stderr has
        been quiet for SETTLE_S (at most SETTLE_MAX_S). On a loaded machine the lines logged just
        before the marker could otherwise be read after the signal and count as said after it."""
        end = time.monotonic() + SETTLE_MAX_S
        seen, quiet_since = len(self.err), time.monotonic()
        while time.monotonic() < end and time.monotonic() - quiet_since < SETTLE_S:
            time.sleep(0.01)
            if len(self.err) != seen:
                seen, quiet_since = len(self.err), time.monotonic()

    def signal_and_wait(self, signum):
        self.settle()
        self.err_before_signal = len(self.err)   # what the command logged before (vdo.commands.cli)
        self.proc.send_signal(signum)
        sent = time.monotonic()
        self.proc.wait(timeout=30)
        for r in self._readers:
            r.join(5)
        return time.monotonic() - sent


def check_interrupted(run: Run, signum, elapsed, parent: Path):
    assert run.proc.returncode == 128 + signum, run.err[-10:]
    assert elapsed < PROMPT_S
    # after the signal, one line: the progress messages logged before it and the progress (tqdm
    # bars on a terminal, `vdo.core.progress.PlainBar` lines off one, as here) aside
    plain = re.compile(r"[\w ]+: \d+(/\d+)? \S+( \(\d+ %\))?, \d+ s(, ~\d+ s left)?( \[.*\])?")
    messages = [line for line in run.err[run.err_before_signal:]
                if line.strip() and "%|" not in line and not plain.fullmatch(line.strip())]
    assert messages == [f"vdo: interrupted by {signal.Signals(signum).name}"], run.err[-10:]
    assert not any("Traceback" in line or "Error" in line for line in run.err), run.err[-10:]
    assert sorted(p.name for p in parent.iterdir()) == [], "output or partial folder left"


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    """Two cameras over a plate sampled every 10 mm."""
    from conftest import PLATE_TOML, write_box

    folder = tmp_path_factory.mktemp("plate")
    write_box(folder / "plate.stl", [1000, 1000, 10], center=[0, 0, -5])
    cams = DOWN_CAMERA.format(name="a", focal=24, u=0.4) + DOWN_CAMERA.format(name="b", focal=35, u=0.6)
    path = folder / "plate.toml"
    path.write_text(PLATE_TOML.format(spacing=10, limit=75, height=1.5, cameras=cams, extra_meshes=""))
    return path


def catches_sigterm(pid: int) -> bool:
    """The process has its own SIGTERM handler (vdo's `install()` ran): Linux's SigCgt mask."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc/PID/status")
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_at_start_up(plate, tmp_path, signum):
    """Right after the handlers are installed, and 0.8 s later, during the imports and JAX's
    start (where Ctrl-C used to be swallowed by a gc callback, or crash ``import jaxlib``)."""
    parent = tmp_path / "runs"
    parent.mkdir()
    for delay in (0.0, 0.8):
        run = Run("evaluate", plate, "--out", parent / "out")
        run.wait_for(lambda: catches_sigterm(run.proc.pid))
        time.sleep(delay)
        check_interrupted(run, signum, run.signal_and_wait(signum), parent)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_mid_computation(plate, tmp_path, signum):
    parent = tmp_path / "runs"
    parent.mkdir()
    run = Run("evaluate", plate, "--out", parent / "out")
    run.wait_for(lambda: any("samples on" in line for line in run.err))
    check_interrupted(run, signum, run.signal_and_wait(signum), parent)


@pytest.mark.parametrize("signum, during", [(signal.SIGINT, "render"), (signal.SIGTERM, "write")])
def test_signal_mid_render_and_mid_write(plate, tmp_path, signum, during):
    """While Mitsuba renders (it used to wrap the interrupt in `RuntimeError: drjit.custom(...)`),
    and while the command writes the images into the hidden partial folder."""
    parent = tmp_path / "runs"
    parent.mkdir()
    run = Run("render", plate, "--out", parent / "out", "--spp", 64, "--scale", 0.5)
    if during == "render":
        run.wait_for(lambda: any(line.startswith("rendering") for line in run.err))
    else:
        run.wait_for(lambda: any(p.name.startswith(".out.partial-") for p in parent.iterdir()))
    check_interrupted(run, signum, run.signal_and_wait(signum), parent)


def test_importing_vdo_changes_no_global_setting():
    """Every vdo module imported: JAX still in float32, matplotlib's backend untouched; a vdo
    computation then fails with the message that names vdo.configure(); after it, it runs."""
    script = """
import importlib, pkgutil, sys, jax, matplotlib
import vdo
backend = matplotlib.rcParams._get_backend_or_none()
for m in pkgutil.walk_packages(vdo.__path__, "vdo."):
    if m.name != "vdo.__main__":
        importlib.import_module(m.name)
assert not jax.config.jax_enable_x64, "x64 set at import"
assert matplotlib.rcParams._get_backend_or_none() == backend, "matplotlib backend set at import"
from vdo.model.camera import Camera
make = lambda: Camera("c", 640, 480, 5e-6, 0.025, [0.0, 0.0, 1.0], 0.0, -1.5)
try:
    make()
except RuntimeError as exc:
    print(exc)
vdo.configure()
print(make().project([[0.0, 0.0, 0.0]]).dtype)
"""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert "call vdo.configure()" in lines[0]
    assert lines[1] == "float64"


def test_settings_live_only_in_configure():
    """No module but vdo/core/configure.py changes JAX's configuration or matplotlib's backend."""
    pattern = re.compile(r"jax\.config\.update|matplotlib\.use\(")
    hits = [f"{p.relative_to(ROOT)}:{n}" for p in sorted((ROOT / "vdo").rglob("*.py"))
            for n, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert hits and all(h.startswith(os.path.join("vdo", "core", "configure.py")) for h in hits), hits


SCRIPT = """
import gc, sys, time
from vdo.core import interrupts
from vdo.core.runfolder import run_folder
interrupts.install()
try:
    with run_folder(sys.argv[1]) as tmp:
        (tmp / "half.json").write_text("{")
{body}
except BaseException as exc:
    stop = interrupts.interruption(exc)
    print(stop.message, file=sys.stderr)
    sys.exit(stop.exit_code)
"""


def scripted(tmp_path, body: str):
    """A process that opens a run folder, runs `body` inside it and says "ready" on stdout."""
    parent = tmp_path / "runs"
    parent.mkdir()
    text = SCRIPT.replace("{body}", "\n".join("        " + line for line in body.strip().splitlines()))
    child = subprocess.Popen([sys.executable, "-c", text, str(parent / "out")], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "ready"
    return child, parent


def finish(child, signum, count=1, settle=0.3):
    time.sleep(settle)  # into the loop that follows "ready"
    sent = time.monotonic()
    for _ in range(count):
        child.send_signal(signum)
        time.sleep(0.05)
    _, err = child.communicate(timeout=30)
    return time.monotonic() - sent, err


# A child that catches every interrupt and carries on, as native code may.
SWALLOWS_INTERRUPTS = """
print("ready", flush=True)
for _ in range(200):
    try:
        time.sleep(0.05)
    except BaseException:
        pass
"""


def test_swallowed_interrupt_ends_by_the_watchdog(tmp_path):
    """Code that catches the interrupt and carries on (as native code may) is ended after the
    grace period, with the status of the signal and the partial folder removed."""
    child, parent = scripted(tmp_path, SWALLOWS_INTERRUPTS)
    elapsed, err = finish(child, signal.SIGTERM)
    assert child.returncode == 143 and err.strip() == "vdo: interrupted by SIGTERM"
    assert GRACE_S - 0.2 < elapsed < PROMPT_S
    assert list(parent.iterdir()) == []


def test_second_signal_ends_at_once(tmp_path):
    child, parent = scripted(tmp_path, SWALLOWS_INTERRUPTS)
    elapsed, err = finish(child, signal.SIGINT, count=2)
    assert child.returncode == 130 and err.strip() == "vdo: interrupted by SIGINT"
    assert elapsed < GRACE_S - 0.5
    assert list(parent.iterdir()) == []


def test_interrupt_inside_a_gc_callback_is_delivered(tmp_path):
    """Python drops an exception raised in a gc callback ("Exception ignored in ..."; JAX's
    `_xla_gc_callback` swallowed Ctrl-C this way): it is raised again outside, well before the
    watchdog would end the process."""
    child, parent = scripted(tmp_path, """
slow = [True]
def callback(phase, info):
    if slow[0] and phase == "start":
        slow[0] = False
        print("ready", flush=True)
        time.sleep(1.0)
gc.callbacks.append(callback)
junk = []
for _ in range(10**9):
    junk.append([[]])
    if len(junk) > 10000:
        junk.clear()
""")
    elapsed, err = finish(child, signal.SIGINT, settle=0.0)
    assert child.returncode == 130 and err.strip() == "vdo: interrupted by SIGINT", err
    assert elapsed < GRACE_S - 0.3
    assert list(parent.iterdir()) == []


@pytest.mark.parametrize("signum", [signal.SIGINT])
def test_signal_during_optimize_start_up(plate, tmp_path, signum):
    """`vdo optimize` before its search starts (no layout judged yet): the signal ends the run
    at once, as for any command, instead of being held until the search's first step."""
    parent = tmp_path / "runs"
    parent.mkdir()
    run = Run("optimize", plate, "--out", parent / "out", "--time-limit", 600)
    run.wait_for(lambda: any("start-up:" in line for line in run.lines + run.err))
    check_interrupted(run, signum, run.signal_and_wait(signum), parent)
