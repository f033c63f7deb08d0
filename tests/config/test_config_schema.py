"""One schema: every table round-trips through `Experiment.to_dict` and a TOML file, and
docs/config.md is the text the schema generates."""

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from config_documents import NO_SHRINK, documents, plate_file, same
from hypothesis import HealthCheck, given, settings

from vdo.config import experiment as config
from vdo.config.reference import markdown
from vdo.config.schema import REQUIRED

ROOT = Path(__file__).resolve().parents[2]
EXPERIMENTS = sorted(p for p in (ROOT / "experiments").rglob("*.toml")
                     if "experiment" in tomllib.loads(p.read_text()) and "mesh" in tomllib.loads(p.read_text()))


def round_trip(exp: config.Experiment) -> config.Experiment:
    """Write `exp` as `report.write_config` does (tomli_w) and read it back."""
    return config.parse(tomllib.loads(tomli_w.dumps(exp.to_dict())), exp.path)


def test_every_experiment_file_is_found():
    assert {p.name for p in EXPERIMENTS} >= {"ten_cameras.toml", "three_cameras.toml"}


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.name for p in EXPERIMENTS])
def test_experiment_files_round_trip(path):
    exp = config.load(path)
    again = round_trip(exp)
    same(exp, again)
    assert again.to_dict() == exp.to_dict()          # a second write changes nothing


def test_optimized_toml_solves_the_same_problem():
    """The defect: writing ten_cameras.toml dropped [optimize], so a re-run scored every region with
    a 1 % obscuration limit and 3 rounds instead of the joint, 5 % and 5 rounds."""
    exp = round_trip(config.load(ROOT / "experiments/beam_column/ten_cameras.toml"))
    assert exp.optimize.regions == ("joint_top", "joint_bottom", "joint_front")
    assert (exp.optimize.max_obscuration, exp.optimize.rounds, exp.optimize.starts) == (0.05, 5, 1)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("schema")
    plate_file(path)
    return path


@settings(max_examples=100, deadline=None, derandomize=True, phases=NO_SHRINK,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(doc=documents())
def test_generated_experiments_round_trip(folder, doc):
    exp = config.parse(doc, folder / "exp.toml")
    again = round_trip(exp)
    same(exp, again)
    same(round_trip(again), again)
    # what the file said is what was parsed: every given value comes back, in file units
    written = exp.to_dict()
    for table, given_table in doc.items():
        items = given_table if isinstance(given_table, list) else [given_table]
        out = written[table] if isinstance(written[table], list) else [written[table]]
        for given_item, out_item in zip(items, out):
            for key, value in given_item.items():
                if key in ("sensor_mm", "file", "normal"):   # written as sensor_width_mm, a path, a unit vector
                    continue
                assert close(out_item[key], sorted(set(value)) if key == "lenses_mm" else value), (table, key)


def close(a, b) -> bool:
    if isinstance(a, (str, bool)) or (isinstance(a, list) and a and isinstance(a[0], str)):
        return a == b
    return np.allclose(a, b, rtol=1e-11)


def test_defaults_live_in_the_schema():
    """A dataclass built without arguments holds the documented defaults, in SI units."""
    assert config.Evaluation().sample_spacing == pytest.approx(0.01)
    assert config.Evaluation().incidence_limit == pytest.approx(np.radians(75))
    assert config.OptimizeSpec().free == ("u", "pan", "tilt")
    for sec in config.sections():
        fields = {f.name: f for f in dataclasses.fields(sec.cls)}
        for row in sec.rows:
            if row.default not in (None, REQUIRED):
                field = fields[row.attr]
                value = field.default if field.default_factory is dataclasses.MISSING else field.default_factory()
                assert close(row.kind.write(value, row.scale), row.default), (sec.key, row.key)


def test_docs_are_generated_from_the_schema():
    assert (ROOT / "docs" / "config.md").read_text() == markdown(), \
        "docs/config.md is stale: run `python scripts/config_docs.py`"
    text = markdown()
    for sec in config.sections():                      # every key of every table is documented
        for row in sec.rows + sec.extra:
            assert f"| `{row.key}` |" in text, row.key
