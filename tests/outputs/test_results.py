"""The typed result of `vdo evaluate` (`vdo.outputs.report.EvaluationResult`): its `to_json()` is
the summary.json written, byte for byte, and its figures are those `LayoutState.region_stats`
computes its own way from the state's fields."""

from __future__ import annotations

import json
import pickle

import pytest

from conftest import aimed_camera
from vdo.commands.evaluate import write_evaluation
from vdo.config.experiment import load
from vdo.state import layout_state, prepare


def test_evaluation_result_is_summary_json_and_the_region_statistics(plate_experiment, tmp_path):
    cameras = aimed_camera("a", 0.4) + aimed_camera("b", 0.6) + "[render]\nambient_radiance = 20\n"
    state = layout_state(prepare(load(plate_experiment(spacing=50, cameras=cameras))))
    result = write_evaluation(state, tmp_path / "run")
    text = (tmp_path / "run" / "summary.json").read_text()
    assert text == json.dumps(result.to_json(), indent=2) + "\n"
    written = json.loads(text)

    top, stats = result.regions["top"], state.region_stats("top")
    assert top.sigma_max_um.p95 == written["regions"]["top"]["sigma_max_um"]["p95"]
    assert top.sigma_max_um.p95 == pytest.approx(stats.sigma_max_um_p95, rel=1e-12)
    assert top.sigma_max_um.p50 == pytest.approx(stats.sigma_max_um_p50, rel=1e-12)
    assert top.sigma_axis_um["z"].p95 == pytest.approx(stats.sigma_z_um_p95, rel=1e-12)
    assert top.seen_by_2_or_more == written["regions"]["top"]["seen_by_2_or_more"]
    assert top.seen_by_2_or_more == pytest.approx(stats.seen_by_2_or_more, rel=1e-12) and 0 < top.seen_by_2_or_more
    assert top.area_m2 == pytest.approx(stats.area_m2, rel=1e-12) and top.n_samples == stats.n_samples
    assert result.settings.n_samples == len(state.samples) == written["settings"]["n_samples"]
    assert result.settings.n_cameras == 2 and result.cameras_seeing_nothing == []
    assert result.constraints is None and "constraints" not in written      # not judged here
    assert set(top.sigma_strain_microstrain) == {"eps_uu", "eps_vv", "eps_uv"}
    # picklable (a sweep's worker returns results across processes), and the same after the trip
    assert json.dumps(pickle.loads(pickle.dumps(result)).to_json(), indent=2) + "\n" == text
