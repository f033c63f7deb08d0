"""The public API: `import vdo` is light, its names resolve, and the example script runs."""

import runpy
import subprocess
import sys
from pathlib import Path

import pytest

import vdo

ROOT = Path(__file__).resolve().parent.parent


def test_import_is_light_and_names_resolve():
    code = ("import sys, vdo; heavy = [m for m in ('jax', 'mitsuba', 'matplotlib') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
    for name in vdo.__all__:
        assert getattr(vdo, name) is not None, name
    assert callable(vdo.configure) and callable(vdo.evaluate_experiment)


def test_example_compares_two_layouts(capsys):
    rows = runpy.run_path(str(ROOT / "docs" / "examples" / "compare_layouts.py"))["main"](
        [str(ROOT / "experiments" / "beam_column" / "three_cameras.toml"), "--spacing-mm", "30"])
    out = capsys.readouterr().out
    assert "cam1 raised by 0.1 m" in out or "raised by 0.1 m" in out
    assert set(rows["before"]) == set(rows["after"]) and rows["before"]
    # the joint is seen by the three cameras before and after a 10 cm move
    assert rows["before"]["joint_top"][0] == pytest.approx(1.0)
    assert rows["after"]["joint_top"][1] is not None
