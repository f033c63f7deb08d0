"""Rails: exact cases (polyline, NURBS quarter circle) and derivatives by finite differences."""

import numpy as np
import pytest

from vdo.model.rail import Rail


def test_polyline_is_piecewise_linear_with_uniform_knots():
    rail = Rail("l", np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0]]), degree=1)
    np.testing.assert_allclose(rail.position(np.array([0, 0.25, 0.5, 0.75, 1])),
                               [[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 0.5, 0], [2, 1, 0]], atol=1e-12)
    assert rail.arc_length(1.0) == pytest.approx(3.0, rel=1e-6)


def test_rational_quadratic_is_an_exact_quarter_circle():
    w = np.sqrt(0.5)
    rail = Rail("arc", np.array([[1, 0, 0], [1, 1, 0], [0, 1, 0]]), degree=2, weights=[1, w, 1])
    pts = np.asarray(rail.position(np.linspace(0, 1, 41)))
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 1.0, atol=1e-12)
    assert rail.arc_length(1.0) == pytest.approx(np.pi / 2, rel=1e-6)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_tangent_matches_finite_differences(degree):
    pts = np.array([[0, 0, 0], [1, 0.3, 0], [1.5, 1, 0.2], [1, 2, 0.5], [0, 2.5, 1]])
    rail = Rail("r", pts, degree=degree, weights=[1, 1.5, 0.7, 1.2, 1])
    for u in (0.1, 0.37, 0.62, 0.9):
        h = 1e-6
        fd = (np.asarray(rail.position(u + h)) - np.asarray(rail.position(u - h))) / (2 * h)
        np.testing.assert_allclose(rail.tangent(u), fd, rtol=1e-6, atol=1e-8)


def test_end_points_are_the_first_and_last_control_points():
    pts = np.array([[0, 0, 0], [1, 2, 0], [3, 1, 1], [4, 0, 2]])
    rail = Rail("r", pts, degree=3)
    np.testing.assert_allclose(rail.position(0.0), pts[0], atol=1e-12)
    np.testing.assert_allclose(rail.position(1.0), pts[-1], atol=1e-12)
