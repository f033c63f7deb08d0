"""σ_measured per sample (`vdo.physics.measured`): the propagation and the merging of stereo pairs
against a Monte-Carlo simulation of the cameras' image-plane errors, and `vdo evaluate` in both
processings on two experiments."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vdo.physics.measured import all_views, merge_pairs

DRAWS = 40_000            # Monte-Carlo draws: ~1 % sampling error on a standard deviation
MC_TOL = 0.04             # relative, 4 standard errors


def _views(rng, cameras=4):
    """Random cameras around one sample: sensitivities S_i (2x3), image-plane information W_i
    (2x2, SPD), measured image-plane covariances Σ_i = ν W_i⁻¹ + B_i."""
    S, W, Sig = [], [], []
    for i in range(cameras):
        angle = 2 * math.pi * i / cameras + rng.uniform(-0.3, 0.3)
        d = np.array([math.cos(angle), math.sin(angle), 1.0]) / math.sqrt(2)   # viewing direction
        a = np.cross(d, [0, 0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0, 0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        S.append(1e4 * np.stack([a, b]) * rng.uniform(0.5, 2.0))
        L = rng.normal(size=(2, 2))
        W.append(L @ L.T + np.eye(2) * 4.0)
        L = rng.normal(size=(2, 2)) * 0.3
        Sig.append(rng.uniform(1.5, 3.0) * np.linalg.inv(W[-1]) + L @ L.T)
    return np.array(S), np.array(W), np.array(Sig)


def _terms(S, W, Sig):
    C = np.einsum("cai,cab,cbj->cij", S, W, S)[:, None]                  # (C, 1, 3, 3)
    WS = W @ S
    M = np.einsum("cai,cab,cbj->cij", WS, Sig, WS)[:, None]
    return C, M


def _draws(rng, Sig):
    return np.stack([rng.multivariate_normal(np.zeros(2), s, size=DRAWS) for s in Sig])  # (C, D, 2)


def _estimate(S, W, x, cams):
    """The weighted least-squares 3D estimate from the image errors x of `cams` (D, 3)."""
    C = sum(S[i].T @ W[i] @ S[i] for i in cams)
    g = sum(x[i] @ (W[i] @ S[i]) for i in cams)
    return g @ np.linalg.inv(C)


def test_all_views_propagation_matches_monte_carlo():
    rng = np.random.default_rng(4)
    S, W, Sig = _views(rng)
    C, M = _terms(S, W, Sig)
    cov, ok = all_views(C, M)
    u = _estimate(S, W, _draws(rng, Sig), range(len(S)))
    assert ok[0]
    assert np.sqrt(np.diag(cov[0])) == pytest.approx(u.std(axis=0), rel=MC_TOL)


@pytest.mark.parametrize("merge", ["best", "fusion"])
def test_pair_merging_matches_monte_carlo(merge):
    # Pairs (0,1), (1,2), (2,3), (0,2): every pair shares a camera with another, so fused pairs
    # are correlated; the naive fusion (ignoring it) is optimistic.
    rng = np.random.default_rng(5)
    S, W, Sig = _views(rng)
    C, M = _terms(S, W, Sig)
    pairs = [(0, 1), (1, 2), (2, 3), (0, 2)]
    cand = np.ones((len(pairs), 1), dtype=bool)
    cov, ok, best, naive = merge_pairs(C, M, pairs, cand, merge)
    x = _draws(rng, Sig)
    per_pair = [_estimate(S, W, x, p) for p in pairs]
    if merge == "best":
        sig = [np.linalg.eigvalsh(np.cov(u.T))[-1] for u in per_pair]
        assert best[0] == int(np.argmin(sig))
        u = per_pair[best[0]]
    else:
        prec = [np.linalg.inv(np.cov(u.T)) for u in per_pair]
        total = np.linalg.inv(sum(prec))
        u = sum(v @ (total @ p).T for v, p in zip(per_pair, prec))
        assert naive[0] < 0.97 * math.sqrt(np.linalg.eigvalsh(cov[0])[-1])
    assert ok[0]
    assert np.sqrt(np.diag(cov[0])) == pytest.approx(u.std(axis=0), rel=MC_TOL)


def _evaluate(tmp_path, source, extra, name, spacing_mm):
    """`vdo evaluate` (the library call) of a copy of `source`'s folder with its [evaluation]
    sample spacing set to `spacing_mm` and `extra` TOML appended; returns (summary, out folder)."""
    import re
    import shutil

    from vdo.commands.evaluate import evaluate
    from vdo.config.experiment import load

    folder = tmp_path / f"{name}_src"
    shutil.copytree(source.parent, folder)
    path = folder / source.name
    text = re.sub(r"(\[evaluation\]\s*\nsample_spacing_mm = )[0-9.]+", rf"\g<1>{spacing_mm}",
                  source.read_text(), count=1)
    path.write_text(text + "\n" + extra)
    evaluate(load(path), tmp_path / name)
    return json.loads((tmp_path / name / "summary.json").read_text()), tmp_path / name


EXPERIMENTS = __import__("pathlib").Path(__file__).resolve().parents[2] / "experiments"
THIRD_PLATE_CAMERA = """
[[camera]]
name = "top"
sensor_mm = [8.4456, 7.0656]
pixels = [2448, 2048]
focal_mm = 25
position_m = [0.0, -0.62, 1.3]
target_m = [0, -0.0025, 1.0]
"""


def test_two_cameras_as_a_pair_measure_what_all_views_measure(tmp_path):
    # The holed plate's one stereo pair: pair processing and all views are the same correlation,
    # sample by sample; σ_measured exceeds the bound by the noise of two images at least. And the
    # interpolant is carried to σ_measured.
    source = EXPERIMENTS / "holed_plate" / "stereo.toml"
    allv, out = _evaluate(tmp_path, source, "", "all", 4)
    pair, _ = _evaluate(tmp_path, source, '[analysis]\nprocessing = "pairs"\npairs = "declared"\n',
                        "pair", 4)
    a, p = allv["measured"]["regions"]["front"], pair["measured"]["regions"]["front"]
    assert p["sigma_measured_um"]["p50"] == pytest.approx(a["sigma_measured_um"]["p50"], rel=1e-6)
    assert p["pairs"] == {"left+right": pytest.approx(1.0, abs=0.05)}
    assert a["ratio"]["p50"] > math.sqrt(2)
    assert (out / "maps" / "sigma_measured_max.png").exists()
    assert b'Name="sigma_measured_max"' in (out / "samples.vtp").read_bytes()
    # Keys' cubic convolution (a = -0.5) attenuates the speckle off the pixel grid far more than
    # the cubic B-spline (its model against correlation: tests/physics/test_measured.py): the
    # same plate measures worse with it, beside the same bound.
    keys, _ = _evaluate(tmp_path, source, '[analysis]\ninterpolant = "keys"\n', "keys", 4)
    k = keys["measured"]["regions"]["front"]
    assert keys["measured"]["interpolant"] == "keys"
    assert k["sigma_bound_um"]["p50"] == pytest.approx(a["sigma_bound_um"]["p50"], rel=1e-9)
    assert k["sigma_measured_um"]["p50"] > 2 * a["sigma_measured_um"]["p50"]


def test_pairs_on_three_cameras_best_and_fusion(tmp_path):
    source = EXPERIMENTS / "holed_plate" / "stereo.toml"
    allv, _ = _evaluate(tmp_path, source, THIRD_PLATE_CAMERA, "all3", 5)
    best, _ = _evaluate(tmp_path, source, THIRD_PLATE_CAMERA
                        + '[analysis]\nprocessing = "pairs"\nmax_pair_angle_deg = 40\n', "best", 5)
    fused, _ = _evaluate(tmp_path, source, THIRD_PLATE_CAMERA
                         + '[analysis]\nprocessing = "pairs"\nmerge = "fusion"\n', "fused", 5)
    a = allv["measured"]["regions"]["front"]["sigma_measured_um"]["p50"]
    b = best["measured"]["regions"]["front"]["sigma_measured_um"]["p50"]
    f = fused["measured"]["regions"]["front"]
    assert set(best["measured"]["regions"]["front"]["pairs"]) <= {"left+right", "left+top", "right+top"}
    assert b > a                       # one pair has less information than all three views
    assert f["sigma_fused_naive_um"]["p50"] < f["sigma_measured_um"]["p50"]   # shared cameras


def test_steel_beam_measured_beside_the_bound(tmp_path):
    source = EXPERIMENTS / "steel_beam" / "four_point_bending.toml"
    summary, out = _evaluate(tmp_path, source, '[analysis]\ninterpolant = "quintic"\n', "beam", 40)
    for name, r in summary["measured"]["regions"].items():
        if r["sigma_bound_um"]["p50"] is None:
            continue
        assert r["sigma_measured_um"]["p50"] > r["sigma_bound_um"]["p50"]
    assert summary["measured"]["interpolant"] == "quintic"
    assert all(row["f_number_assumed"] for row in summary["measured"]["per_camera"])


def test_a_declared_pair_that_shares_no_region_is_one_line(tmp_path):
    from vdo.core.errors import ConfigError

    away = THIRD_PLATE_CAMERA.replace("target_m = [0, -0.0025, 1.0]", "target_m = [0, -3, 1.3]")
    with pytest.raises(ConfigError, match="stereo_pair .'left', 'top'.: the two cameras share no"):
        _evaluate(tmp_path, EXPERIMENTS / "holed_plate" / "stereo.toml", away
                  + '[analysis]\nprocessing = "pairs"\npairs = "declared"\n'
                  '[[stereo_pair]]\ncameras = ["left", "top"]\n', "bad", 5)


def test_the_documented_analysis_table_loads(tmp_path):
    # docs/measured.md's [analysis] example, appended to the holed plate, is a valid file.
    import re
    import shutil

    from vdo.config.experiment import load

    doc = (EXPERIMENTS.parent / "docs" / "measured.md").read_text()
    snippet = re.search(r"```toml\n(.*?)```", doc, re.S).group(1)
    folder = tmp_path / "plate"
    shutil.copytree(EXPERIMENTS / "holed_plate", folder)
    path = folder / "stereo.toml"
    path.write_text((EXPERIMENTS / "holed_plate" / "stereo.toml").read_text() + "\n" + snippet)
    a = load(path).analysis
    assert (a.interpolant, a.processing, a.pairs, a.merge) == ("quintic", "pairs", "auto", "best")
    assert a.max_pair_angle == pytest.approx(math.radians(60))
