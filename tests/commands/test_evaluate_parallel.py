"""`vdo evaluate --workers N | --dask ADDRESS`: the run folder of a load path judged on a local
pool and on a Dask LocalCluster is the serial run's (summary.json, load_path.csv, every array of
samples.vtp); bad values are one line, before any work and without an output folder. (The
shipped beam-column path and a failing step: tests/search/test_loadpath_parallel.py.)"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import write_box
from vdo.commands import cli
from vdo.core.vtp import read_points

ROOT = Path(__file__).resolve().parents[2]
WITH_PATH = ROOT / "experiments" / "beam_column" / "ten_cameras.toml"
WITHOUT_PATH = ROOT / "experiments" / "steel_beam" / "four_point_bending.toml"


# The shutter of tests/search/test_loadpath.py: a 1.2 m box sliding 0.5 m per step over the
# plate, which the camera "down" loses at step 5 (the geometry says so).
SHUTTER = """
[[mesh]]
name = "shutter"
file = "shutter.stl"
unit = "mm"
role = "obstacle"

[[group]]
name = "slide"
meshes = ["shutter"]

[load_path]
poses = "poses.csv"
"""


def test_pool_and_dask_write_the_serial_run_folder(plate_experiment, tmp_path, capsys):
    write_box(tmp_path / "shutter.stl", [1200, 1200, 10], [3000, 0, 750])
    rows = ["step,group,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg"]
    rows += [f"{k},slide,{-500 * k},0,0,0,0,0" for k in range(1, 8)]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    config = str(plate_experiment(spacing=100, extra_meshes=SHUTTER))
    runs = {"serial": [], "pool": ["--workers", "2"], "dask": ["--dask", "local", "--workers", "2"]}
    for name, flags in runs.items():
        assert cli.main(["evaluate", config, "--out", str(tmp_path / name), "--quiet", *flags]) == 0
    summary = {n: json.loads((tmp_path / n / "summary.json").read_text()) for n in runs}
    assert [(x["camera"], x["step"]) for x in summary["serial"]["load_path"]["losses"]] == [("down", 5)]
    table = (tmp_path / "serial" / "load_path.csv").read_bytes()
    points, arrays = read_points(tmp_path / "serial" / "samples.vtp")
    assert {"coverage_worst", "sigma_max_worst", "worst_step"} <= set(arrays)
    for name in ("pool", "dask"):
        assert summary[name] == summary["serial"], name
        assert (tmp_path / name / "load_path.csv").read_bytes() == table, name
        other_points, other = read_points(tmp_path / name / "samples.vtp")
        assert np.array_equal(other_points, points) and set(other) == set(arrays)
        for key, values in arrays.items():
            assert np.array_equal(other[key], values, equal_nan=True), (name, key)


def error_lines(capsys) -> list[str]:
    return error_lines_of(capsys.readouterr().err)


@pytest.mark.parametrize("config, flags, words", [
    (WITH_PATH, ["--workers", "0"], "--workers: must be at least 1 (got 0)"),
    (WITHOUT_PATH, ["--workers", "2"], "--workers: runs the load path's steps, and the experiment "
                                       "has no [load_path]"),
    (WITHOUT_PATH, ["--dask", "local"], "--dask: runs the load path's steps"),
])
def test_bad_flags_are_one_line_before_any_work(tmp_path, capsys, config, flags, words):
    started = time.perf_counter()
    out = tmp_path / "run"
    assert cli.main(["evaluate", str(config), "--out", str(out), *flags]) == 2
    lines = error_lines(capsys)
    assert len(lines) == 1 and str(config) in lines[0] and words in lines[0], lines
    assert not out.exists()
    assert time.perf_counter() - started < 10      # before the samples and the ray casts


def test_unreachable_dask_scheduler_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "DASK_CONNECT_S", 2.0)
    monkeypatch.setenv("VDO_SET", "evaluation.sample_spacing_mm = 40; load_path.every = 4")
    started = time.perf_counter()
    out = tmp_path / "run"
    assert cli.main(["evaluate", str(WITH_PATH), "--out", str(out), "--dask", "tcp://127.0.0.1:9"]) == 2
    lines = error_lines(capsys)
    assert len(lines) == 1 and "cannot reach the Dask scheduler at 'tcp://127.0.0.1:9' within 2 s" in lines[0]
    assert not out.exists()
    assert time.perf_counter() - started < 30


def test_a_failed_task_is_one_line_and_status_1(tmp_path, capsys, monkeypatch):
    """What `vdo.search.loadpath` raises when a step fails on its worker (TaskFailed, the worker's
    traceback kept on it) is one line on the command line, exit status 1, no traceback."""
    from vdo.core.parallel import Failure, TaskFailed

    def failing(exp, args):
        raise TaskFailed("load path step 9", Failure("ValueError: operands could not be broadcast",
                                                     "Traceback (most recent call last):\n  ...\n"))

    monkeypatch.setattr(cli, "_evaluate", failing)
    out = tmp_path / "run"
    assert cli.main(["evaluate", str(WITH_PATH), "--out", str(out), "--workers", "2"]) == 1
    err = capsys.readouterr().err
    assert error_lines_of(err) == ["error: load path step 9: ValueError: operands could not be broadcast"]
    assert "Traceback" not in err and not out.exists()


def error_lines_of(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error")]
