"""`vdo validate` with stereo-pair processing (`processing = "pairs"`): each pair correlated on its
own, the pairs' displacements merged as `vdo.physics.measured.pair_merge` defines it, the scatter
over seeds against the pair-mode prediction (`vdo.physics.measured.merge_pairs`).

Statistics: the measured σ of one axis from n seeds, s, has (n - 1) s² / σ² ~ χ²(n - 1); its 99 %
interval for the ratio s / (√2 σ_predicted) is [r √((n-1)/χ²_0.995), r √((n-1)/χ²_0.005)]. Jointly
over the three axes, with Σ the predicted covariance (3 x 3, one noisy image) and d_k the seeds'
deviations from their mean, T = Σ_k d_kᵀ (2Σ)⁻¹ d_k ~ χ²(3(n - 1)) (the trace of a Wishart matrix):
the same interval for r = √(T / 3(n - 1)) with 3(n - 1) degrees of freedom, tighter by √3. The
model itself is right to MODEL_BAND (the shipped 200-seed all-views table, docs/validation.md:
every displacement ratio in [0.92, 1.09]). A prediction AGREES when the interval meets
MODEL_BAND, and is REJECTED when the interval lies wholly above it. Each case is deterministic
(fixed seeds).

* Four cameras 20° from the normal at azimuths 0/90/180/270°, merge "best": the best pair is two
  opposite cameras, so the merged σ is ~√2 the all-views σ (z exactly √2: every camera carries the
  same depth information) and the all-views prediction must be rejected.
* Three cameras, merge "fusion" of the three pairs: every camera is in two pairs, so Σ_p C_p = 2 Σ_i C_i
  and the fused estimate is exactly the all-views one (A_p = (2C)⁻¹ C_p); the naive fusion that
  ignores the shared cameras, (Σ_p C_p)⁻¹, claims σ / √2 and must be rejected.
"""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from scipy.stats import chi2

from small_plate import DEFAULTS
from vdo.core.errors import ConfigError
from vdo.dic import validate as V
from vdo.physics.measured import merge_pairs, pair_merge

MODEL_BAND = (0.9, 1.1)
BEST_SEEDS = 200
FUSION_SEEDS = 100

TOML = """
[validation]
name = "pairs"
seeds = 4

""" + DEFAULTS + """
[[case]]
name = "quad_best"
cameras = [{name = "a", polar_deg = 20, azimuth_deg = 0}, {name = "b", polar_deg = 20, azimuth_deg = 90},
           {name = "c", polar_deg = 20, azimuth_deg = 180}, {name = "d", polar_deg = 20, azimuth_deg = 270}]
processing = "pairs"
merge = "best"
seed = 21

[[case]]
name = "tri_fusion"
cameras = [{polar_deg = 15, azimuth_deg = 90}, {polar_deg = 20, azimuth_deg = 200}, {polar_deg = 25, azimuth_deg = 330}]
processing = "pairs"
merge = "fusion"
seed = 22
"""


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    path = tmp_path_factory.mktemp("validate_pairs") / "pairs.toml"
    path.write_text(textwrap.dedent(TOML))
    return V.load(path)


@pytest.fixture(scope="module")
def quad(spec):
    return V.run_case(spec.cases[0], spec.path, BEST_SEEDS)


@pytest.fixture(scope="module")
def tri(spec):
    return V.run_case(spec.cases[1], spec.path, FUSION_SEEDS)


def interval(sigma_measured: float, sigma_predicted: float, n: int) -> tuple[float, float]:
    """The 99 % interval of s / (√2 σ_predicted) from n seeds (χ², n - 1 degrees of freedom)."""
    r = sigma_measured / (math.sqrt(2) * sigma_predicted)
    return r * math.sqrt((n - 1) / chi2.ppf(0.995, n - 1)), r * math.sqrt((n - 1) / chi2.ppf(0.005, n - 1))


def joint_interval(estimates: np.ndarray, covariance: np.ndarray) -> tuple[float, float]:
    """The 99 % interval of r = √(T / 3(n - 1)), T = Σ_k d_kᵀ (2Σ)⁻¹ d_k (module docstring)."""
    d = estimates - estimates.mean(axis=0)
    dof = 3 * (len(estimates) - 1)
    r = math.sqrt(np.einsum("ki,ij,kj->", d, np.linalg.inv(2 * covariance), d) / dof)
    return r * math.sqrt(dof / chi2.ppf(0.995, dof)), r * math.sqrt(dof / chi2.ppf(0.005, dof))


def agrees(lo_hi) -> bool:
    return lo_hi[0] <= MODEL_BAND[1] and lo_hi[1] >= MODEL_BAND[0]


def rejected(lo_hi) -> bool:
    return lo_hi[0] > MODEL_BAND[1]


def test_best_pair_scatter_matches_the_pair_prediction_not_all_views(quad, spec):
    info, rows = quad.info, quad.rows
    assert info["processing"] == "pairs (best)" and len(info["pairs_serving"]) == 6
    assert len(info["pairs_used"]) == 1 and info["noise_free_ok"]
    a, b = info["pairs_used"][0].split("+")
    assert {a, b} in ({"a", "c"}, {"b", "d"})            # two opposite cameras, 40° apart
    # the noise-free check in the cameras that measure (the pair's), within 0.01 px
    assert set(info["noise_free_error_px"]) == {a, b}
    assert [r["axis"] for r in rows] == ["x", "y", "z"]
    for r in rows:
        assert agrees(interval(r["sigma_measured_um"], r["sigma_predicted_um"], BEST_SEEDS)), r
        # one pair: the correlation's own linear propagation of that pair
        assert r["sigma_measured_um"] / r["sigma_linear_um"] == pytest.approx(1.0, abs=0.2), r
    assert agrees(joint_interval(quad.estimates, quad.pairs.covariance))
    assert rejected(joint_interval(quad.estimates, quad.pairs.all_views))
    # z: two of four cameras with the same depth information -> exactly √2
    z = rows[2]
    assert z["sigma_predicted_um"] / z["sigma_predicted_all_views_um"] == pytest.approx(math.sqrt(2), rel=2e-3)
    # the all-views bound from the per-camera information (objective.camera_information, patch
    # mean) against the all-views prediction of predict (objective.fields, 1 / mean(1 / σ²))
    all_views = V.predict_sigma(quad.setup) * 1e6
    assert [r["sigma_predicted_all_views_um"] for r in rows] == pytest.approx(all_views, rel=0.01)


def test_fused_pairs_scatter_matches_the_true_fusion_not_the_naive_one(tri):
    info, rows = tri.info, tri.rows
    assert info["processing"] == "pairs (fusion)" and len(info["pairs_used"]) == 3
    assert info["noise_free_ok"]
    # every camera in two of the three pairs: the fused estimate is the all-views one, and the
    # naive fusion claims half its covariance, (Σ_p C_p)⁻¹ = (2C)⁻¹
    pred = tri.pairs
    assert pred.covariance == pytest.approx(pred.all_views, rel=1e-9)
    assert pred.naive == pytest.approx(pred.covariance / 2, rel=1e-9)
    for k, r in enumerate(rows):
        assert info["sigma_fused_naive_um"][k] == pytest.approx(r["sigma_predicted_um"] / math.sqrt(2))
        assert agrees(interval(r["sigma_measured_um"], r["sigma_predicted_um"], FUSION_SEEDS)), r
        assert math.isnan(r["sigma_linear_um"])      # pairs share cameras: not propagated by correlate
    assert agrees(joint_interval(tri.estimates, pred.covariance))
    assert rejected(joint_interval(tri.estimates, pred.naive))
    # the merged estimates are the weights' combination of the pairs' (A_p = (2C)⁻¹ C_p sums to I)
    assert pred.weights.sum(axis=0) == pytest.approx(np.eye(3), abs=1e-9)
    assert np.array(info["pair_weights"]) == pytest.approx(pred.weights, abs=1e-6)


# --------------------------------------------------------------------------------------------
# The merge arithmetic, by hand: three cameras, pairs (0, 1) and (1, 2) sharing camera 1
# --------------------------------------------------------------------------------------------
def test_merge_of_two_pairs_matches_the_closed_form():
    # diagonal information per camera (x, y, z), M_i = C_i: per axis scalars c_i
    c = np.array([[1.0, 2.0, 2.0], [2.0, 2.0, 2.0], [3.0, 2.0, 4.0]])      # [camera, axis]
    C = np.array([np.diag(ci) for ci in c])[:, None]                         # (3, 1, 3, 3)
    pairs = [(0, 1), (1, 2)]
    cand = np.ones((2, 1), dtype=bool)
    # by hand, per axis: c01 = c0 + c1, c12 = c1 + c2; Cov_p = 1 / c_p; fusion weights
    # A_p = c_p / (c01 + c12); var = A01² / c01 + A12² / c12 + 2 A01 A12 c1 / (c01 c12)
    #   x: c01 = 3, c12 = 5: A = 3/8, 5/8; var = 3/64 + 5/64 + 4/64 = 3/16; naive 1/8
    #   y: c01 = 4, c12 = 4: A = 1/2, 1/2; var = 1/16 + 1/16 + 1/16 = 3/16; naive 1/8
    #   z: c01 = 4, c12 = 6: A = 2/5, 3/5; var = 1/25 + 3/50 + 1/25 = 7/50; naive 1/10
    m = pair_merge(C, C, pairs, cand, "fusion")
    assert np.diagonal(m.weights[:, 0], axis1=-2, axis2=-1) == pytest.approx(
        np.array([[3 / 8, 1 / 2, 2 / 5], [5 / 8, 1 / 2, 3 / 5]]))
    cov, ok, best, naive = merge_pairs(C, C, pairs, cand, "fusion")
    assert ok[0] and best[0] == -1
    assert np.diag(cov[0]) == pytest.approx([3 / 16, 3 / 16, 7 / 50])
    assert np.diag(m.naive[0]) == pytest.approx([1 / 8, 1 / 8, 1 / 10])
    assert naive[0] == pytest.approx(math.sqrt(1 / 8))
    u01, u12 = np.array([1.0, 2.0, 3.0]), np.array([5.0, -2.0, 8.0])
    assert V.merged_displacement(m.weights[:, 0], [u01, u12]) == pytest.approx(
        [3 / 8 * 1 + 5 / 8 * 5, 0.5 * 2 - 0.5 * 2, 2 / 5 * 3 + 3 / 5 * 8])
    # best: pair (0, 1) has Cov diag(1/3, 1/4, 1/4) (σ_max² 1/3), pair (1, 2) diag(1/5, 1/4, 1/6)
    # (σ_max² 1/4): the second serves, and the merged displacement is its own
    b = pair_merge(C, C, pairs, cand, "best")
    cov, ok, best, naive = merge_pairs(C, C, pairs, cand, "best")
    assert best[0] == 1 and b.best[0] == 1 and naive is None
    assert np.diag(cov[0]) == pytest.approx([1 / 5, 1 / 4, 1 / 6])
    assert V.merged_displacement(b.weights[:, 0], [u01, u12]) == pytest.approx(u12)


def test_fusion_of_disjoint_pairs_is_the_all_views_estimate():
    # pairs (0, 1) and (2, 3) share no camera; with M_i = C_i the fused estimate is the
    # least-squares one of all four: A_p = (Σ C)⁻¹ C_p, Cov = (Σ C)⁻¹ (full 3 x 3 matrices)
    rng = np.random.default_rng(3)
    L = rng.normal(size=(4, 3, 3))
    C = (L @ np.swapaxes(L, -1, -2) + np.eye(3))[:, None]
    pairs = [(0, 1), (2, 3)]
    m = pair_merge(C, C, pairs, np.ones((2, 1), dtype=bool), "fusion")
    cov, ok, _, _ = merge_pairs(C, C, pairs, np.ones((2, 1), dtype=bool), "fusion")
    total = np.linalg.inv(C[:, 0].sum(axis=0))
    assert cov[0] == pytest.approx(total, rel=1e-9)
    assert m.weights[0, 0] == pytest.approx(total @ (C[0, 0] + C[1, 0]), rel=1e-9)


# --------------------------------------------------------------------------------------------
# Bad input: one line naming the file, the case's field and the fix, before any render
# --------------------------------------------------------------------------------------------
QUAD = ('cameras = [{name = "a", polar_deg = 20, azimuth_deg = 0}, {name = "b", polar_deg = 20, '
        'azimuth_deg = 90},\n           {name = "c", polar_deg = 20, azimuth_deg = 180}, {name = "d", '
        'polar_deg = 20, azimuth_deg = 270}]')


@pytest.mark.parametrize("edit, field, says", [
    ((QUAD, 'cameras = [{name = "a", polar_deg = 0}]'), 'case "quad_best".processing', "two cameras"),
    (('merge = "best"', 'merge = "average"'), 'case "quad_best".merge', "best, fusion"),
    (('merge = "best"', 'merge = "best"\npairs = "declared"\nstereo_pairs = [["a", "c"], ["b", "e"]]'),
     'case "quad_best".stereo_pairs[1]', "no camera named 'e'"),
    (('merge = "best"', 'merge = "best"\npairs = "declared"'), 'case "quad_best".stereo_pairs', "needs"),
    (('merge = "best"', 'merge = "best"\nstereo_pairs = [["a", "c"]]'), 'case "quad_best".stereo_pairs',
     'pairs = "declared"'),
    (('processing = "pairs"\nmerge = "best"', 'pairs = "declared"'), 'case "quad_best".pairs',
     'processing = "pairs"'),
    (('merge = "best"', 'merge = "best"\nstrain_microstrain = [1000, 0, 0]'), 'case "quad_best".processing',
     "displacement"),
    # the pair rule at the patch (25 mm lens: rays at least 20.6° apart, at most 60°)
    (('merge = "best"', 'merge = "best"\nmax_pair_angle_deg = 25'), 'case "quad_best".processing',
     "the rule [20.6, 25] deg"),
    (('merge = "best"', 'merge = "best"\npairs = "declared"\nstereo_pairs = [["a", "b"], ["a", "c"]]\n'
                        'max_pair_angle_deg = 35'), 'case "quad_best".stereo_pairs[1]', "40.0 deg"),
])
def test_bad_pair_inputs_are_one_line(tmp_path, edit, field, says):
    path = tmp_path / "bad.toml"
    text = textwrap.dedent(TOML)
    assert edit[0] in text
    path.write_text(text.replace(*edit, 1))
    with pytest.raises(ConfigError) as info:
        V.load(path)
    assert info.value.field == field
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)) and says in message, message
