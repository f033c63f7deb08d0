"""vdo.physics.strain against things we did not write: the finite Q4 mesh solved as a matrix (the
infinite-mesh constant comes from a Fourier integral), the virtual strain gauge against an exact
pixel-level least-squares propagation (no overlap kernel), the strain combination against Monte
Carlo; the [analysis] config errors name their field."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from vdo.config import experiment as config
from vdo.physics import strain
from vdo.core.errors import ConfigError


def test_q4_interior_element_matches_a_large_finite_mesh():
    assert strain.q4_centre_gradient_factors(1, 1, 0, 0, 1.0, 1.0) == pytest.approx(
        (strain.AFFINE_PATCH, strain.AFFINE_PATCH))
    F1, F2 = strain.q4_centre_gradient_factors(41, 41, 20, 20, 2e-3, 2e-3)
    assert F1 == pytest.approx(strain.Q4_INTERIOR / 2e-3 ** 4, rel=1e-9)
    assert F2 == pytest.approx(F1)
    # a corner element of a mesh knows less than an interior one
    assert strain.q4_centre_gradient_factors(5, 5, 0, 0, 1.0, 1.0)[0] > strain.Q4_INTERIOR


def _pixel_vsg_variance(S: int, s: int, n: int) -> float:
    """Var of the plane-fit slope along x for white unit-variance pixels: subsets are S x S pixel
    means, their centres on a step s grid, the slope a least-squares fit; propagated exactly."""
    size = S + (n - 1) * s
    x = (np.arange(n) - (n - 1) / 2) * s
    w = np.zeros((n, n))               # slope = sum_ij w_ij u_ij (i along x)
    w[:, :] = (x / (n * (x @ x)))[:, None]
    coeff = np.zeros((size, size))
    for i in range(n):
        for j in range(n):
            coeff[i * s:i * s + S, j * s:j * s + S] += w[i, j] / S ** 2
    return float(np.sum(coeff ** 2))


@pytest.mark.parametrize("S, s, n", [(21, 5, 5), (15, 7, 4), (9, 9, 3), (5, 11, 6), (31, 1, 3)])
def test_virtual_strain_gauge_matches_pixel_level_propagation(S, s, n):
    assert strain.vsg_factor(float(S), float(s), n) == pytest.approx(_pixel_vsg_variance(S, s, n),
                                                                     rel=1e-9)


def test_affine_patch_limit():
    """Subsets that tile a square of side L (step = subset) give the affine patch's 12 / L^4."""
    n, S = 40, 1e-3
    assert strain.vsg_factor(S, S, n) * (n * S) ** 4 == pytest.approx(12.0, rel=2e-3)


def test_strain_sigma_against_monte_carlo():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    sigma_u = A @ A.T * 1e-20                                 # m^4
    t_u, t_v = np.array([1.0, 0, 0]), np.array([0, 0.6, 0.8])
    F1, F2 = 2.0e10, 5.0e10
    L = np.linalg.cholesky(sigma_u)
    g1 = math.sqrt(F1) * rng.normal(size=(200_000, 3)) @ L.T    # du/dxi1
    g2 = math.sqrt(F2) * rng.normal(size=(200_000, 3)) @ L.T
    eps = np.stack([g1 @ t_u, g2 @ t_v, 0.5 * (g2 @ t_u + g1 @ t_v)], 1)
    pred = strain.strain_sigma(sigma_u[None], t_u[None], t_v[None], F1, F2)[0]
    assert eps.std(axis=0) == pytest.approx(pred, rel=0.01)


def test_global_strain_sigma_scales_as_the_element_size_squared():
    """At a fixed pixel density Σ_u is fixed: σ_u of a node ∝ 1/h and σ_ε ∝ 1/h^2."""
    info = np.diag([4e12, 3e12, 1e12])[None]
    smp = type("S", (), {"tangent_u": np.array([[1.0, 0, 0]]),
                         "tangent_v": np.array([[0, 1.0, 0]])})()
    out = {}
    for h in (2e-3, 4e-3, 8e-3):
        a = config.Analysis(method="global", element=h)
        out[h] = strain.analysis_fields(a, np.ones(1), smp, info, np.array([True]), 1e-4)
    for h in (4e-3, 8e-3):
        assert out[h][0] == pytest.approx(out[2e-3][0] * (2e-3 / h) ** 2)
        assert out[h][1] == pytest.approx(out[2e-3][1] * (2e-3 / h))


BASE = """
[experiment]
name = "x"
[[mesh]]
name = "plate"
file = "plate.stl"
unit = "mm"
role = "specimen"
[[region]]
name = "top"
mesh = "plate"
normal = [0, 0, 1]
[[camera]]
name = "c"
sensor_mm = [22.2, 14.8]
pixels = [600, 400]
focal_mm = 24
position_m = [0, 0, 1.5]
target_m = [0, 0, 0]
{camera_extra}
{analysis}
"""


@pytest.mark.parametrize("analysis, camera_extra, field", [
    ("[analysis]\nmethod = 'subset'\nstep_px = 0", "", "analysis.step_px"),
    ("[analysis]\nstep_mm = -1", "", "analysis.step_mm"),
    ("[analysis]\nstrain_window = 1", "", "analysis.strain_window"),
    ("[analysis]\nmethod = 'local'", "", "analysis.method"),
    ("[analysis]\nsubset_px = 21\nsubset_mm = 2", "", "analysis.subset_px"),
    ("", "f_number = 0\nfocus_m = 1.5", 'camera "c".f_number'),
])
def test_bad_analysis_names_the_field(tmp_path, analysis, camera_extra, field):
    from conftest import write_box
    write_box(tmp_path / "plate.stl", [100, 100, 10])
    path = tmp_path / "x.toml"
    path.write_text(textwrap.dedent(BASE.format(analysis=analysis, camera_extra=camera_extra)))
    with pytest.raises(ConfigError) as err:
        config.load(path)
    assert err.value.field == field, err.value


def test_subset_larger_than_the_region(plate_experiment):
    from conftest import raycast
    path = plate_experiment(spacing=50)
    exp, samples, cams, _, vis = raycast(path)
    density = strain.pixel_density(cams, vis.visible, samples.points, samples.tangent_u,
                                   samples.tangent_v)
    ok = config.Analysis(method="subset", subset=0.5, subset_px=None)
    strain.check_regions(ok, samples, density, path)
    with pytest.raises(ConfigError) as err:
        strain.check_regions(config.Analysis(method="subset", subset_px=800.0), samples, density,
                             path)
    assert err.value.field == "analysis.subset_px"
    with pytest.raises(ConfigError) as err:
        strain.check_regions(config.Analysis(method="global", element=1.5), samples, density, path)
    assert err.value.field == "analysis.element_mm"


def test_evaluate_writes_strain_sigma_and_design_checks(plate_experiment, tmp_path):
    """samples.vtp carries the strain sigma; on the horizontal plate (t_u = x, t_v = y)
    sigma_strain_uu = sqrt(F Ω) sigma_x with the interior-Q4 F (element 20 mm, patch 10 mm)."""
    import json

    from conftest import DOWN_CAMERA
    from conftest import read_vtp
    from vdo.commands.cli import main

    cams = DOWN_CAMERA.format(name="a", focal=24, u=0.4) + DOWN_CAMERA.format(name="b", focal=35, u=0.6)
    path = plate_experiment(spacing=50, cameras=cams + "\n[render]\nambient_radiance = 1.0\n"
                            "[analysis]\nelement_mm = 20\n")
    out = tmp_path / "run"
    assert main(["evaluate", str(path), "--out", str(out), "--quiet"]) == 0
    _, _, arrays = read_vtp(out / "samples.vtp")
    ok = np.isfinite(arrays["sigma_x"])
    assert ok.sum() > 50
    F = strain.Q4_INTERIOR / 0.02 ** 4
    np.testing.assert_allclose(arrays["sigma_strain_uu"][ok],
                               np.sqrt(F * 1e-4) * arrays["sigma_x"][ok], rtol=1e-4)
    np.testing.assert_allclose(arrays["sigma_strain_vv"][ok],
                               np.sqrt(F * 1e-4) * arrays["sigma_y"][ok], rtol=1e-4)
    summary = json.loads((out / "summary.json").read_text())
    top = summary["regions"]["top"]
    assert top["sigma_strain_microstrain"]["eps_uu"]["p50"] == pytest.approx(
        np.median(arrays["sigma_strain_uu"][ok]), rel=1e-3)
    assert top["sigma_axis_um"]["x"]["p95"] == pytest.approx(
        np.percentile(arrays["sigma_x"][ok], 95), rel=1e-3)
    assert summary["settings"]["analysis"]["element_mm"] == 20
    assert [(r["camera"], r["region"]) for r in summary["design_checks"]] == [("a", "top"),
                                                                             ("b", "top")]
    assert (out / "maps" / "sigma_strain_uu.png").is_file()
