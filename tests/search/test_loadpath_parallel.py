"""The load path's steps as tasks (`vdo.search.loadpath.evaluate_load_path` with `workers` or a
Dask `client`, through `vdo.core.parallel.run_tasks`): the shipped beam-column experiment, coarse
(40 mm samples, every 4th step: 7 steps, each a distinct pose), judged in this process and on a
Dask LocalCluster of 2 workers (the local pool of spawned processes writes the same run folder:
tests/commands/test_evaluate_parallel.py). Every per-step array,
the losses and changes, summary.json's "load_path" and load_path.csv's rows are the same to the
last bit; a step that fails on a worker ends the run with one line naming that step."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from vdo.core.parallel import TaskFailed

EXPERIMENT = Path(__file__).resolve().parents[2] / "experiments" / "beam_column" / "ten_cameras.toml"
ARRAYS = ("coverage", "sigma_max", "seen_fraction", "region_covered", "region_sigma_p95")


@pytest.fixture(scope="module")
def judged():
    """(geometry, load path, rest state, the serial `LoadPathResult`)."""
    from vdo.config.experiment import load
    from conftest import load_path_tables
    from vdo.geometry.keyframes import load_path_of
    from vdo.search.loadpath import evaluate_load_path
    from vdo.state import layout_state, prepare

    exp = load(EXPERIMENT).with_settings(evaluation={"sample_spacing_mm": 40}, load_path={"every": 4})
    geometry = prepare(exp)
    load_path = load_path_of(geometry.meshes, **load_path_tables(exp))
    rest = layout_state(geometry, strain_fields=False)
    serial = evaluate_load_path(geometry, load_path, rest=rest)
    return geometry, load_path, rest, serial


def assert_identical(serial, other):
    """Every array bit for bit (NaN where NaN), and what summary.json and load_path.csv hold."""
    from vdo.search import loadpath

    assert other.steps == serial.steps and other.camera_names == serial.camera_names
    for name in ARRAYS:
        a, b = getattr(serial, name), getattr(other, name)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
    assert other.losses == serial.losses and other.changes == serial.changes
    assert loadpath.summary(other) == loadpath.summary(serial)
    assert loadpath.table(other) == loadpath.table(serial)


def test_serial_path_is_worth_comparing(judged):
    """The coarse path moves the cameras' view: 7 distinct poses, and the sigma of some sample
    changes between rest and a step (an equality of constant arrays would prove nothing)."""
    _, load_path, _, serial = judged
    assert len(serial.steps) == 8 and len({load_path.step_key(s) for s in load_path.steps}) == 7
    changed = serial.sigma_max[1:] != serial.sigma_max[:1]
    assert changed.any() and np.isfinite(serial.sigma_max).any()


def test_dask_local_cluster_is_the_serial_run_and_a_failed_step_is_one_line(judged):
    """On a LocalCluster of 2 workers (OpenBLAS started as here: `blas_environment`) the same
    arrays; then a load path whose step 9 holds displacements of the wrong shape fails on its
    worker: TaskFailed, one line naming step 9 and the worker's error."""
    from vdo.core.parallel import blas_environment, dask_client
    from vdo.search.loadpath import evaluate_load_path

    geometry, load_path, rest, serial = judged
    with dask_client("local", 2, env=blas_environment()) as client:
        assert_identical(serial, evaluate_load_path(geometry, load_path, rest=rest, client=client))
        assert 9 in load_path.steps
        broken = dict(load_path.displacements) | {9: np.ones((5, 3))}   # 5 of the mesh's vertices
        bad = dataclasses.replace(load_path, displacements=broken)
        with pytest.raises(TaskFailed) as info:
            evaluate_load_path(geometry, bad, rest=rest, client=client)
    message = str(info.value)
    assert message.startswith("load path step 9: ") and "\n" not in message
    assert "Error" in message and "Traceback" in info.value.traceback
