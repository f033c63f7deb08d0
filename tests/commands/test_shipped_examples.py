"""Every shipped example runs: each TOML under experiments/ (found by glob, so a new one is picked
up) passes its up-front checks, and each command that applies to it runs on it, as does every
`vdo ...` command shown in a code block of README.md and docs/*.md, in a reduced form:

* the environment variable VDO_SET (`vdo.config.reader.with_overrides`) coarsens every file
  the same way, from the file's own values: the sample spacings (`[evaluation]`, `[design]`)
  `SPACING_FACTOR` times the file's, one optimizer start, round and `OPTIMIZE_STEPS` steps, the
  design search's candidates thinned, its bound given 1 s per count and its branch and bound 1 s (`DESIGN`), its curve
  ended at one camera more than the file's `min_cameras`, validation renders at `VALIDATION_SPP` spp, a load path at every
  `LOAD_PATH_EVERY`-th step (all rows still checked);
* flags that the commands already have: `--seeds 2` (validate), `--scale 0.05 --spp 1` (render),
  `--time-limit 1` (optimize), `--workers 1 --max-points SWEEP_POINTS` (sweep), a fresh `--out` in
  the test's folder.

A command is applicable to an experiment when the file has what it needs: evaluate (and `vdo report`
on its folder) and export always, render when it has cameras, render --series with a
`[load_path]`, optimize when a camera stands on a rail or mount, design with a `[design]` table;
validate to a validation file, sweep to a sweep file. A command shown in the docs on a file that is
not shipped under experiments/ is a placeholder (CONFIG, my-sweep.toml) and is not run; one that
names a missing file under experiments/ fails. The commands on one file and subcommand run in one
test, in order, so that the docs' sweep variants resume the first one's store.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from vdo.config.reader import read_toml

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "experiments").glob("**/*.toml"))
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

SPACING_FACTOR = 4          # sample spacings x 4: about 16x fewer samples
OPTIMIZE_STEPS = 2          # BFGS steps of the one start and round
SWEEP_POINTS = 2            # a sweep runs its first points (`--max-points`), the rest stay pending
LOAD_PATH_EVERY = 8         # a load path judged and rendered at every 8th step and the last
VALIDATION_SPP = 4          # validation renders: 4 samples per pixel (the file's are 64)
DESIGN = ("design.rail_positions = 3; design.zone_points = 1; design.zone_heights = 1; design.keyframes = 1; "
          "design.bound_s = 1; design.restart_s = 1; design.branch_s = 1")
# per command: the flags that shorten it (a flag given in the docs is replaced)
FLAGS = {"validate": ["--seeds", "2"], "render": ["--scale", "0.05", "--spp", "1"],
         "optimize": ["--time-limit", "1"], "sweep": ["--workers", "1", "--max-points", str(SWEEP_POINTS)]}
REPLACED = {"--out": 1, "--seeds": 1, "--scale": 1, "--spp": 1, "--time-limit": 1, "--workers": 1, "--max-points": 1,
            "--overwrite": 0, "--quiet": 0}


def kind(path: str) -> str:
    data = read_toml(ROOT / path)
    return "validation" if "validation" in data else "sweep" if "sweep" in data else "experiment"


def applicable(path: str) -> list[list[str]]:
    """The commands (argv after `vdo`, without --out) that apply to a shipped file."""
    if kind(path) == "validation":
        return [["check", path], ["validate", path]]
    if kind(path) == "sweep":
        return [["check", path], ["sweep", path]]
    from vdo.config.experiment import load

    exp = load(ROOT / path)
    out = [["check", path], ["evaluate", path], ["export", path, "--format", "opencv"]]
    if exp.camera_specs:
        out.append(["render", path])
    if exp.load_path.active:
        out.append(["render", path, "--series"])
    if any(c.rail is not None or c.mount is not None for c in exp.camera_specs):
        out.append(["optimize", path])
    if "design" in read_toml(ROOT / path):
        out.append(["design", path])
    return out


def doc_commands(docs=DOCS) -> tuple[list[tuple[str, list[str]]], list[str]]:
    """(commands, unreadable): (where, argv) of every `vdo NAME ...` (or `python -m vdo NAME ...`)
    line in a fenced code block of README.md and docs/*.md, NAME one of the CLI's subcommands
    (`vdo.commands.cli.subcommands`: prose in a code block that starts with "vdo" is not a
    command): '$ ' prompts, '# ' comments, [optional] parts and leading environment assignments
    (the test sets VDO_SET itself) dropped, '\\' continuations joined; unreadable: where such a
    line cannot be split by shlex (a test fails on it, the collection does not)."""
    from vdo.commands.cli import subcommands

    names = "|".join(sorted(subcommands(), key=len, reverse=True))
    command = re.compile(rf'(\w+=("[^"]*"|\S*)\s+)*(python3? -m )?vdo\s+({names})(\s|$)')
    found, unreadable = [], []
    for doc in docs:
        inside, lines = False, doc.read_text().splitlines()
        k = 0
        while k < len(lines):
            line, number = lines[k], k + 1
            k += 1
            if line.lstrip().startswith("```"):
                inside = not inside
                continue
            while inside and line.rstrip().endswith("\\") and k < len(lines):
                line = line.rstrip()[:-1] + " " + lines[k].strip()
                k += 1
            text = re.sub(r"\[[^\]]*\]", "", re.sub(r"\s#.*$", "", line.strip().removeprefix("$ ")))
            if not inside or not command.match(text):
                continue
            where = f"{doc.relative_to(ROOT) if doc.is_relative_to(ROOT) else doc}:{number}"
            try:
                words = shlex.split(text)
            except ValueError as err:
                unreadable.append(f"{where}: {err}")
                continue
            while re.fullmatch(r"\w+=.*", words[0]):
                words = words[1:]
            words = words[3:] if words[0].startswith("python") else words[1:]
            found.append((where, words))
    return found, unreadable


DOC_COMMANDS, UNREADABLE = doc_commands()


def _strip(argv: list[str]) -> list[str]:
    """argv without the flags the test sets itself (REPLACED)."""
    out, k = [], 0
    while k < len(argv):
        if argv[k] in REPLACED:
            k += 1 + REPLACED[argv[k]]
            continue
        out.append(argv[k])
        k += 1
    return out


def groups() -> dict[tuple[str, str], list[list[str]]]:
    """(file, subcommand) -> the argv variants to run: the applicable command first, then each
    different one the docs show. Docs' commands on files outside experiments/ are placeholders."""
    from vdo.core.errors import ConfigError

    out: dict[tuple[str, str], list[list[str]]] = {}
    for path in SHIPPED:
        try:
            commands = applicable(path)
        except ConfigError:     # a broken file: its first command fails, with the message
            commands = [["validate" if kind(path) == "validation" else "evaluate", path]]
        for argv in commands:
            out.setdefault((path, argv[0]), []).append(argv)
    for where, argv in DOC_COMMANDS:
        argv = _strip(argv)
        files = [a for a in argv[1:] if a.endswith(".toml")]
        if not files or files[0] not in SHIPPED:
            if files and files[0].startswith("experiments/"):
                out.setdefault((files[0], argv[0]), []).append(argv)   # fails: not shipped
            continue
        variants = out.setdefault((files[0], argv[0]), [])
        if argv not in variants:
            variants.append(argv)
    return out


GROUPS = groups()


def reduced(path: str) -> str:
    """VDO_SET for a file (module docstring): from its own spacings (the smallest over a sweep's
    base experiments)."""
    from vdo.config.experiment import load

    settings = [f"optimize.starts = 1; optimize.rounds = 1; optimize.max_steps = {OPTIMIZE_STEPS}",
                DESIGN, f"defaults.spp = {VALIDATION_SPP}"]
    if kind(path) == "validation":
        return "; ".join(settings)
    if kind(path) == "sweep":
        from vdo.config.sweep import load_sweep

        experiments = [load(base) for _, base in load_sweep(ROOT / path).experiments]
    else:
        experiments = [load(ROOT / path)]
    spacing = min(e.evaluation.sample_spacing for e in experiments) * 1e3 * SPACING_FACTOR
    design = min(e.design.sample_spacing for e in experiments) * 1e3 * SPACING_FACTOR
    settings.append(f"evaluation.sample_spacing_mm = {spacing:g}; design.sample_spacing_mm = {design:g}")
    if kind(path) == "experiment" and experiments[0].load_path.active:
        settings.append(f"load_path.every = {LOAD_PATH_EVERY}")
    if all("design" in read_toml(e.path) for e in experiments):
        settings.append(f"design.max_cameras = {max(e.design.min_cameras for e in experiments) + 1}")
    return "; ".join(settings)


def test_every_shipped_file_and_doc_command_is_covered():
    """The glob finds the shipped files, every file gets a command, and every docs command on a
    shipped file is one of the runs."""
    assert "experiments/validation.toml" in SHIPPED and len(SHIPPED) >= 8
    assert {path for path, _ in GROUPS} >= set(SHIPPED)
    assert not UNREADABLE, UNREADABLE
    assert len(DOC_COMMANDS) >= 10
    for where, argv in DOC_COMMANDS:
        argv = _strip(argv)
        files = [a for a in argv[1:] if a.endswith(".toml")]
        if files and files[0] in SHIPPED:
            assert argv in GROUPS[(files[0], argv[0])], where


def test_the_docs_reader_takes_commands_not_prose(tmp_path):
    """A code block's line is a command when `vdo` is followed by a subcommand; prose that starts
    with "vdo" is skipped, and a command shlex cannot split is reported with its place."""
    doc = tmp_path / "doc.md"
    doc.write_text("```\nvdo sweep, the calibration's Monte Carlo\n$ vdo check experiments/a.toml  # ok\n"
                   "vdo evaluate 'unclosed --out x\n```\nvdo check outside.toml\n")
    found, unreadable = doc_commands([doc])
    assert found == [(f"{doc}:3", ["check", "experiments/a.toml"])]
    assert unreadable and unreadable[0].startswith(f"{doc}:4")


@pytest.mark.parametrize("path", SHIPPED)
def test_upfront_checks(path):
    """What every command checks before any work: the file (every case, every point) and the
    load path's files, every step."""
    from vdo.config.experiment import load
    from vdo.geometry.keyframes import check_load_path

    if kind(path) == "validation":
        from vdo.dic.validate import load as load_validation

        assert load_validation(ROOT / path).cases
    elif kind(path) == "sweep":
        from vdo.commands.sweep import check_points
        from vdo.config.sweep import expand, load_sweep

        spec = load_sweep(ROOT / path)
        check_points(spec, expand(spec))
    else:
        exp = load(ROOT / path)
        check_load_path(load_path_spec=exp.load_path, groups=exp.groups, mesh_specs=exp.meshes,
                        regions=exp.regions, camera_specs=exp.camera_specs, rails=exp.rails,
                        mounts=exp.mounts, path=exp.path)


@pytest.mark.parametrize("path, command", list(GROUPS), ids=[f"{p}::{c}" for p, c in GROUPS])
def test_command_runs_reduced(path, command, tmp_path, monkeypatch):
    from vdo.commands.cli import main

    monkeypatch.chdir(ROOT)
    monkeypatch.delenv("VDO_SET", raising=False)
    monkeypatch.setenv("VDO_SET", reduced(path))
    for k, argv in enumerate(GROUPS[(path, command)]):
        if command == "check":   # reads and checks the file, writes nothing
            assert main(argv) == 0, argv
            continue
        out = tmp_path / ("store" if command == "sweep" else f"run{k}")
        full = [*argv, *FLAGS.get(command, []), "--out", str(out)]
        status = main(full)
        if command == "validate":   # 2 seeds leave a ratio inconclusive unless it is wild (above
            # 4.2 over 32 ratios at 95 % joint confidence, docs/validation.md): then status 1
            assert status in (0, 1), full
        else:
            assert status == 0, full
        assert out.is_dir() and any(out.iterdir()), full
        if command == "evaluate":
            assert main(["report", str(out)]) == 0
            assert (out / "report.html").is_file()


SCRIPTS = {"experiments/holed_plate/edge_profile.py": "evaluation.sample_spacing_mm = 4"}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_experiment_scripts_run_reduced(script, tmp_path):
    """The analysis scripts shipped beside the experiments (the mesh builders aside: they write
    into the repository) run as the docs show them, on coarser samples; edge_profile's σ beside
    its clipped-patch model σ_far/√φ (φ by point sampling of the disc): median within 5 %."""
    import csv
    import os
    import subprocess
    import sys

    assert sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "experiments").glob("**/*.py")
                  if p.name != "make_meshes.py") == sorted(SCRIPTS), "a new script: add it here"
    env = {**os.environ, "VDO_SET": SCRIPTS[script]}
    run = subprocess.run([sys.executable, script, "--out", str(tmp_path / "out")], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "edge_profile.csv")))
    assert len(rows) > 20
    ratio = np.array([float(r["sigma_max_um"]) / float(r["sigma_model_um"]) for r in rows])
    assert abs(np.median(ratio) - 1) < 0.05


BAD_TOML = 'x = [\n'         # not TOML: the reader's own one-line error


SCRIPT_ARGS = [
    ("docs/examples/compare_layouts.py", ["{bad}"]),
    ("docs/examples/custom_objective.py", ["{bad}", "--out", "{out}"]),
    ("docs/examples/lens_study.py", ["{bad}"]),
    ("docs/examples/python_sweep.py", ["{bad}", "--out", "{out}"]),
    ("docs/examples/virtual_test.py", ["--experiment", "{bad}", "--out", "{out}", "--quick"]),
    ("experiments/holed_plate/edge_profile.py", ["--out", "{out}"])]


@pytest.mark.parametrize("script, argv", SCRIPT_ARGS)
def test_scripts_say_a_bad_experiment_in_one_line(script, argv, tmp_path, monkeypatch, capsys):
    """Each shipped script given a broken experiment (not TOML; edge_profile, which reads its
    own file, a negative sample spacing through VDO_SET) stops with one line naming the file,
    as vdo's commands do: no traceback, nothing written."""
    import runpy
    import sys

    assert sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs" / "examples").glob("*.py")) == \
        sorted(s for s, _ in SCRIPT_ARGS if s.startswith("docs/")), "a new example: add it here"
    bad = tmp_path / "bad.toml"
    bad.write_text(BAD_TOML)
    monkeypatch.setenv("VDO_SET", "evaluation.sample_spacing_mm = -4")
    monkeypatch.setattr(sys, "argv", [script, *(a.format(bad=bad, out=tmp_path / "out") for a in argv)])
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(ROOT / script), run_name="__main__")
    message = str(stop.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    assert ("bad.toml" in message) if "{bad}" in argv else ("sample_spacing_mm" in message), message
    assert not (tmp_path / "out").exists()
