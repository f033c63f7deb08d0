"""`vdo validate`, reduced: the predicted uncertainty (vdo.physics.predict) against correlation on renders.

Two small cases (a stereo pair 25 deg apart on a frontal plate, and three cameras around a plate
tilted 30 deg), 120 x 90 images, 160 noise seeds each, deterministic. Statistics, stated so that
the checks are honest: the measured sigma of one axis from n seeds has a relative sampling error
1/sqrt(2(n - 1)) = 5.6 % at n = 160, so a per-axis ratio whose true value is ~1.05 (what the full run
measures, docs/validation.md) lies in [0.8, 1.25] with > 3 sampling sigmas of margin; the pooled
ratio (rms over the 6 axes) has a smaller error still and is held to [0.85, 1.18]. The noise-free
check: correlation of the noise-free renders recovers the imposed displacement within 0.01 px in
every camera.
"""

from __future__ import annotations

import csv
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from small_plate import DEFAULTS
from vdo.dic import validate as V
from vdo.commands.validate import validate_cases
from vdo.core import tolerances
from vdo.core.errors import ConfigError

SEEDS = 160

TOML = """
[validation]
name = "test"
seeds = 4

""" + DEFAULTS + """
[[case]]
name = "stereo"
cameras = [{name = "left", polar_deg = 12.5, azimuth_deg = 180}, {name = "right", polar_deg = 12.5, azimuth_deg = 0}]
seed = 11

[[case]]
name = "three_tilted"
tilt_deg = 30
cameras = [{polar_deg = 15, azimuth_deg = 90}, {polar_deg = 20, azimuth_deg = 200}, {polar_deg = 25, azimuth_deg = 330}]
sensor = {photons_per_unit = 3000, read_noise_e = 40}
seed = 12
"""


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    path = tmp_path_factory.mktemp("validate") / "validation.toml"
    path.write_text(textwrap.dedent(TOML))
    return V.load(path)


@pytest.fixture(scope="module")
def results(spec):
    return {case.name: V.run_case(case, spec.path, SEEDS) for case in spec.cases}


def test_noise_free_renders_recover_the_displacement(results):
    for name, result in results.items():
        for camera, err in result.info["noise_free_error_px"].items():
            assert np.all(np.abs(err) < 0.01), (name, camera, err)


def test_measured_scatter_matches_sqrt2_times_prediction(results):
    rows = [r for result in results.values() for r in result.rows]
    assert len(rows) == 6
    assert all(r["n_seeds"] == SEEDS for r in rows)
    sampling = 1 / math.sqrt(2 * (SEEDS - 1))
    assert sampling < 0.06
    for r in rows:
        assert 0.8 <= r["ratio"] <= 1.25, r
        assert math.isclose(r["sigma_expected_um"], math.sqrt(2) * r["sigma_predicted_um"])
    pooled = math.sqrt(np.mean([r["ratio"] ** 2 for r in rows]))
    assert 0.85 <= pooled <= 1.18, pooled
    # the correlation's own linear noise propagation agrees with what it measures
    for r in rows:
        assert 0.8 <= r["sigma_measured_um"] / r["sigma_linear_um"] <= 1.25, r


def test_one_camera_reports_in_plane_axes_only(spec, tmp_path):
    text = textwrap.dedent(TOML).replace(
        'cameras = [{name = "left", polar_deg = 12.5, azimuth_deg = 180}, {name = "right", '
        'polar_deg = 12.5, azimuth_deg = 0}]', "cameras = [{polar_deg = 0}]")
    path = tmp_path / "mono.toml"
    path.write_text(text)
    mono = V.load(path).cases[0]
    assert V.axes_reported(mono) == [0, 1]
    setup = V.build_setup(mono, path)
    sigma = V.predict_sigma(setup)
    assert np.isnan(sigma[2]) and np.all(np.isfinite(sigma[:2]))
    stereo = V.build_setup(spec.cases[0], spec.path)
    # two cameras at 12.5 deg carry about twice the in-plane information of one frontal camera
    assert sigma[0] / V.predict_sigma(stereo)[0] == pytest.approx(math.sqrt(2), rel=0.05)


def test_validate_writes_the_run_folder(spec, tmp_path):
    summary = validate_cases(spec, tmp_path / "run", seeds=3, cases=["stereo"])
    out = tmp_path / "run"
    for name in ("validation.csv", "validation.png", "summary.json", "estimates.csv",
                 "validation.toml", "images/stereo.png"):
        assert (out / name).is_file(), name
    lines = (out / "validation.csv").read_text().splitlines()
    assert lines[0].startswith("# ") and "sqrt(2)" in lines[0]
    rows = list(csv.DictReader(lines[1:]))
    assert [r["axis"] for r in rows] == ["x", "y", "z"]
    assert list(rows[0])[:6] == ["case", "axis", "sigma_predicted_um", "sigma_measured_um", "ratio",
                                 "n_seeds"]
    assert summary["seeds"] == 3 and summary["noise_free_passed"]


@pytest.mark.parametrize("edit, field", [
    (("dot_mm = 0.35", "dot_mm = -1"), 'case "stereo".dot_mm'),
    (("seed = 11", "seed = 11\nfocal = 3"), 'case "stereo".focal'),
    (("pixels = [120, 90]", "pixels = [40, 30]"), 'case "stereo".cameras[0]'),
    (("displacement_um = [31, -23, 37]", "displacement_um = [310, -23, 37]"),
     'case "stereo".displacement_um'),
])
def test_config_errors_name_the_field(tmp_path, edit, field):
    path = tmp_path / "bad.toml"
    path.write_text(textwrap.dedent(TOML).replace(*edit, 1))
    with pytest.raises(ConfigError) as info:
        V.load(path)
    assert info.value.field == field


# --------------------------------------------------------------------------------------------
# Strain: a homogeneous strain imposed on the rendered plate, one Q4 element, vdo.physics.strain's sigma
# --------------------------------------------------------------------------------------------
STRAIN_SEEDS = 100
STRAIN_TOML = TOML.replace('[[case]]\nname = "stereo"', '[[case]]\nname = "stereo"\n'
                           'strain_microstrain = [2000, -1000, 500]\npatch_mm = [6, 6]\n'
                           'pixels = [120, 100]', 1)


@pytest.fixture(scope="module")
def strain_result(tmp_path_factory):
    path = tmp_path_factory.mktemp("validate_strain") / "strain.toml"
    path.write_text(textwrap.dedent(STRAIN_TOML))
    case = V.load(path).cases[0]
    assert case.strain is not None and case.q4_mesh == (1, 1)
    return V.run_case(case, path, STRAIN_SEEDS)


def test_strain_scatter_matches_the_derived_sigma(strain_result):
    """The measured strain sigma over 100 seeds (relative sampling error 1/sqrt(2 x 99) = 7 %)
    against sqrt(2) x vdo.physics.strain's prediction for one Q4 element (F = 12 / h^4), per component
    (eps_uu, eps_vv, eps_uv) in [0.8, 1.25]; the correlation's own linear propagation agrees with
    the prediction within 5 % (the same information, computed from the images' gradients)."""
    rows = strain_result.rows
    assert [r["axis"] for r in rows] == ["eps_uu", "eps_vv", "eps_uv"]
    assert all(r["unit"] == "microstrain" for r in rows)
    for r in rows:
        assert 0.8 <= r["ratio"] <= 1.25, r
        assert r["sigma_linear_um"] / r["sigma_expected_um"] == pytest.approx(1.0, abs=0.05), r
    # noise-free: the imposed strain is recovered with an error below the noise
    err = np.abs(strain_result.info["noise_free_strain_error_microstrain"])
    assert np.all(err < [r["sigma_expected_um"] for r in rows]), err
    assert strain_result.info["noise_free_ok"]


@pytest.mark.parametrize("edit, field", [
    (('name = "stereo"', 'name = "stereo"\nq4_mesh = [2, 2]'), 'case "stereo".q4_mesh'),
    (('name = "stereo"', 'name = "stereo"\nstrain_microstrain = [1, 2]'),
     'case "stereo".strain_microstrain'),
    (('name = "stereo"', 'name = "stereo"\nstrain_microstrain = [1, 2, 3]\nq4_mesh = [0, 1]'),
     'case "stereo".q4_mesh'),
])
def test_strain_config_errors_name_the_field(tmp_path, edit, field):
    path = tmp_path / "bad.toml"
    path.write_text(textwrap.dedent(TOML).replace(*edit, 1))
    with pytest.raises(ConfigError) as info:
        V.load(path)
    assert info.value.field == field


SUBSET_SEEDS = 60
SUBSET_TOML = TOML.replace('[[case]]\nname = "stereo"', '[[case]]\nname = "stereo"\n'
                           'strain_microstrain = [2000, -1000, 500]\npatch_mm = [5, 5]\n'
                           'pixels = [120, 100]\nsubset_mm = 2.0\nstep_mm = 1.0\n'
                           'strain_window = 4', 1)


def test_subset_strain_scatter_matches_the_virtual_strain_gauge(tmp_path):
    """Subset DIC: 20 px translation subsets every 10 px (half overlapping), strain from the
    plane fit over 4 x 4 of them. 60 seeds: sampling error 1/sqrt(2 x 59) = 9 %. Treating the
    overlapping subsets as independent would predict a sigma 1.48x smaller (ratio ~1.5)."""
    import math as m

    from vdo.physics import strain
    path = tmp_path / "subsets.toml"
    path.write_text(textwrap.dedent(SUBSET_TOML))
    case = V.load(path).cases[0]
    assert case.subsets == pytest.approx((2e-3, 1e-3, 4))
    independent = 12 / ((2e-3) ** 2 * (1e-3) ** 2 * 16 * 15)
    assert m.sqrt(strain.vsg_factor(2e-3, 1e-3, 4) / independent) == pytest.approx(1.479, abs=1e-3)
    result = V.run_case(case, path, SUBSET_SEEDS)
    for r in result.rows:
        assert 0.8 <= r["ratio"] <= 1.25, r
    pooled = m.sqrt(np.mean([r["ratio"] ** 2 for r in result.rows]))
    assert 0.85 <= pooled <= 1.18, pooled
    assert result.info["noise_free_ok"]


def test_subset_case_errors_name_the_field(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(textwrap.dedent(SUBSET_TOML).replace("strain_window = 4", "strain_window = 6"))
    with pytest.raises(ConfigError) as info:
        V.load(path)
    assert info.value.field == 'case "stereo".strain_window'


SHIPPED = Path(__file__).resolve().parents[2] / "experiments" / "validation.toml"


@pytest.fixture(scope="module")
def subset_setup():
    spec = V.load(SHIPPED)
    case = next(c for c in spec.cases if c.subsets is not None)
    return V.build_setup(case, spec.path)


def test_sizes_equal_to_the_patch_up_to_rounding_fit(subset_setup):
    """The shipped subset case's patch (6 mm) measured back from its samples is 6 mm up to float
    rounding (the samples' extent plus one sample's side, closed form: the patch side); an
    element of exactly the patch side fits, one larger by 10x the named tolerance is refused, and
    the message states the tolerance."""
    from vdo.config.procedure import Analysis
    from vdo.physics import strain

    samples = V._samples(subset_setup, 5)
    side = min(subset_setup.case.patch)
    density = np.ones(len(samples))
    strain.check_regions(Analysis(element=side), samples, density, SHIPPED)
    with pytest.raises(ConfigError) as err:
        strain.check_regions(Analysis(element=side * (1 + 10 * tolerances.SIZE_TOLERANCE)), samples,
                             density, SHIPPED)
    assert err.value.field == "analysis.element_mm"
    assert f"relative tolerance {tolerances.SIZE_TOLERANCE:g}" in str(err.value)


def test_shipped_subset_case_is_predicted_as_subset_dic(subset_setup):
    """The shipped subset case (the one `vdo validate` stopped at): its experiment's analysis is
    its own subset DIC, and its strain prediction is the virtual strain gauge's closed form,
    sqrt(F / S_u) per component, with F = vdo.physics.strain.vsg_factor and S_u the patch's
    displacement information per area (computed here from the same prediction)."""
    from vdo.physics import strain

    case = subset_setup.case
    analysis = subset_setup.experiment.analysis
    assert (analysis.method, analysis.subset, analysis.step, analysis.strain_window) == (
        "subset", *case.subsets)
    sigma = V.predict_strain_sigma(subset_setup)
    pred = V._prediction(subset_setup, subset_setup.cameras, V.speckle_model_of(subset_setup), 5)
    area = case.patch[0] * case.patch[1]
    sigma_u = area * np.linalg.inv(pred.information.mean(axis=0))
    F = strain.vsg_factor(*case.subsets)
    t_u, t_v = subset_setup.patch.t_u, subset_setup.patch.t_v
    uu, vv = F * t_u @ sigma_u @ t_u, F * t_v @ sigma_u @ t_v
    assert sigma == pytest.approx(np.sqrt([uu, vv, (uu + vv) / 4]), rel=1e-9)
