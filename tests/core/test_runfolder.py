"""Output folders: refused before any work when they cannot be written, written whole or not at
all, stale partial folders of dead processes removed, and nothing written outside them."""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vdo.commands import evaluate as evaluate_module
from vdo.commands.cli import main
from vdo.core.errors import ConfigError
from vdo.core.interrupts import Interrupted
from vdo.core.runfolder import check_out, inside, remove_stale_partials, run_folder

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if the command gets as far as computing."""
    def refuse(*args, **kwargs):
        raise AssertionError("evaluate ran before the output folder was checked")
    monkeypatch.setattr(evaluate_module, "evaluate", refuse)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("error: ") and ": --out: " in err[0], err
    return err[0]


def test_non_empty_folder_refused_before_work(plate_experiment, tmp_path, no_work, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["evaluate", str(plate_experiment()), "--out", str(out)]) == 2
    assert "exists and is not empty" in one_error_line(capsys)
    assert (out / "keep.txt").read_text() == "mine"


def test_file_as_output_refused(plate_experiment, tmp_path, no_work, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["evaluate", str(plate_experiment()), "--out", str(tmp_path / "afile")]) == 2
    assert "exists and is not a folder" in one_error_line(capsys)


def test_file_as_parent_refused(plate_experiment, tmp_path, no_work, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["evaluate", str(plate_experiment()), "--out", str(tmp_path / "afile" / "sub" / "x")]) == 2
    assert "afile is a file, not a folder" in one_error_line(capsys)
    assert (tmp_path / "afile").read_text() == "x"


@pytest.mark.parametrize("place", ["/proc/vdo_out", "/sys/vdo_out", "/dev/vdo_out"])
def test_virtual_file_systems_refused(plate_experiment, no_work, capsys, place):
    assert main(["evaluate", str(plate_experiment()), "--out", place]) == 2
    assert "virtual file system" in one_error_line(capsys)


def test_a_name_the_system_refuses_is_one_line(plate_experiment, tmp_path, no_work, capsys):
    """A folder name longer than the file system allows (NAME_MAX, 255 bytes on Linux) or with a
    NUL byte: one line on --out, not the OSError or ValueError of the first stat."""
    assert main(["evaluate", str(plate_experiment()), "--out", str(tmp_path / ("a" * 300))]) == 2
    assert "cannot be used as a folder (File name too long)" in one_error_line(capsys)
    assert main(["evaluate", str(plate_experiment()), "--out", str(tmp_path / "a\x00b")]) == 2
    assert "cannot be used as a folder" in one_error_line(capsys)
    assert not [p for p in tmp_path.iterdir() if p.name.lstrip(".").startswith("a")]


def test_other_paths_the_system_refuses_are_one_line(tmp_path, capsys):
    """Any other path typed by the user that the system refuses (a run folder for vdo report or
    vdo export): one line naming it, exit status 2."""
    long = str(tmp_path / ("a" * 300))
    for argv in (["report", long], ["export", long, "--format", "opencv", "--out", str(tmp_path / "x")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"error: {long}: File name too long; check the path (its length, its "
                       "permissions, the space left)"], err


def test_output_checked_before_the_config(tmp_path, capsys):
    """A bad --out is reported even when the config cannot be read: it costs nothing to check."""
    (tmp_path / "afile").write_text("x")
    assert main(["evaluate", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "afile")]) == 2
    assert "exists and is not a folder" in one_error_line(capsys)


def _without_dac_override():
    """Child process: drop CAP_DAC_OVERRIDE/CAP_DAC_READ_SEARCH so that root obeys permissions."""
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def test_read_only_parent_refused(plate_experiment, tmp_path):
    """The whole command, cold, as a user without write permission on the parent."""
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        run = subprocess.run([sys.executable, "-m", "vdo", "evaluate", str(plate_experiment()),
                              "--out", str(parent / "out")], cwd=ROOT, capture_output=True,
                             text=True, timeout=120,
                             preexec_fn=_without_dac_override if os.geteuid() == 0 else None)
    finally:
        parent.chmod(0o755)
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines() == [
        f"error: {parent / 'out'}: --out: cannot create folders in {parent} (no write permission); "
        "choose a writable place"]
    assert list(parent.iterdir()) == []


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_stale_partials_of_dead_processes_removed(tmp_path, plate_experiment, capsys):
    dead = tmp_path / f".old.partial-{_dead_pid()}"
    (dead / "maps").mkdir(parents=True)
    (dead / "maps" / "half.png").write_bytes(b"\x89PNG")
    alive = tmp_path / f".other.partial-{os.getppid()}"        # a running process: kept
    alive.mkdir()
    not_ours = [tmp_path / ".hidden", tmp_path / f"old.partial-{_dead_pid()}"]
    for p in not_ours:
        p.mkdir()
    a_file = tmp_path / f".notes.partial-{_dead_pid()}"         # a file, not a folder: kept
    a_file.write_text("x")
    # the next run into the same parent, even one that stops at a config error
    assert main(["evaluate", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "new")]) == 2
    assert "missing.toml" in capsys.readouterr().err
    assert not dead.exists()
    assert alive.is_dir() and a_file.is_file() and all(p.is_dir() for p in not_ours)
    assert remove_stale_partials(tmp_path) == []


def test_partial_left_by_sigkill_is_removed_by_the_next_run(tmp_path):
    """A process killed with SIGKILL inside `run_folder` leaves its hidden folder; the next
    `check_out` into the same parent removes it."""
    script = ("import sys, time\nfrom vdo.core.runfolder import run_folder\n"
              "with run_folder(sys.argv[1]) as tmp:\n"
              "    (tmp / 'half.json').write_text('{')\n    print('ready', flush=True)\n"
              "    time.sleep(60)\n")
    child = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "out")], cwd=ROOT,
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "ready"
    child.send_signal(signal.SIGKILL)
    child.wait()
    left = [p.name for p in tmp_path.iterdir()]
    assert left == [f".out.partial-{child.pid}"]
    check_out(tmp_path / "next")
    assert list(tmp_path.iterdir()) == []


def test_interrupted_block_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with run_folder(tmp_path / "out") as tmp:
            (tmp / "half.json").write_text("{")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_anytime_result_kept_on_interrupt(tmp_path):
    """`on_interrupt` writes what the command has into the partial folder, which becomes the
    output folder; the interrupt still propagates (the command still ends with 130/143)."""
    def best_so_far(folder: Path):
        (folder / "best.json").write_text('{"score": 1.5}')

    with pytest.raises(Interrupted) as caught:
        with run_folder(tmp_path / "out", on_interrupt=best_so_far) as tmp:
            (tmp / "history.csv").write_text("round,score\n0,2.0\n1,1.5\n")
            raise Interrupted(signal.SIGTERM)
    assert caught.value.exit_code == 143
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["best.json", "history.csv"]
    # other errors are not interrupts: nothing is kept
    with pytest.raises(ValueError):
        with run_folder(tmp_path / "out2", on_interrupt=best_so_far):
            raise ValueError("a bug")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("name", ["../../evil_cam.png", "../evil.png", "/tmp/evil.png", "a/../../x.png",
                                  "..", ".", "", "sub/../../x"])
def test_names_that_leave_the_folder_are_refused(tmp_path, name):
    folder = tmp_path / "run" / "images"
    folder.mkdir(parents=True)
    with pytest.raises(ConfigError, match="outside the output folder"):
        inside(folder, name)


def test_symbolic_link_out_of_the_folder_is_refused(tmp_path):
    folder, outside = tmp_path / "run", tmp_path / "elsewhere"
    folder.mkdir()
    outside.mkdir()
    (folder / "link").symlink_to(outside)
    with pytest.raises(ConfigError):
        inside(folder, "link/cam1.png")
    assert inside(folder, "cam1.png") == (folder / "cam1.png").resolve()


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="./\\a~\x00 ", max_size=12))
def test_inside_never_points_outside(tmp_path_factory, name):
    """Any name: either a path strictly inside the folder, or a ConfigError."""
    folder = tmp_path_factory.getbasetemp() / "confined"
    folder.mkdir(exist_ok=True)
    try:
        target = inside(folder, name)
    except ConfigError:
        return
    assert target.is_relative_to(folder.resolve()) and target != folder.resolve()
