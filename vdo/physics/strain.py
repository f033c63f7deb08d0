"""Strain uncertainty from the mean-field information: global DIC (Q4 elements) and subset DIC
(subsets + a virtual strain gauge), derivation in docs/theory.md (sec. 8).

Per sample the objective gives C = Ω C_d (1/m^2), the information of a 3D displacement
measured over a patch of area Ω (`vdo.objective`), so C_d = C / Ω (1/m^4) is the information
per unit surface area and Σ_u = C_d^-1 = Ω C^-1 (m^4) its inverse. Over a measurement patch the
information density is taken as uniform and the surface as planar (the mean-field assumption, as
for the displacement). A displacement model u(ξ) = Σ_a N_a(ξ) q_a (ξ the face coordinates, m,
along t_u, t_v) then has the information matrix M ⊗ C_d with M_ab = ∫ N_a N_b dξ, so every
linear functional g·q of the nodal values has the covariance (gᵀ M⁻¹ g) Σ_u. The in-plane
gradient ∂u/∂ξ_k (a 3-vector, dimensionless) has covariance F_k Σ_u with F_k (1/m^4) from the
analysis:

global DIC, square Q4 elements of side h, the strain at the centre of an interior element of a
regular mesh (infinite in both directions; 1D mass matrix symbol (h/3)(2 + cos θ)):
    F = (d_∞ h^-3)(a_∞ h^-1),  d_∞ = 6(√3 - 1) (difference across the element),
    a_∞ = (3/2)(1 - 1/√3) (average along its edge):  F = (12√3 - 18) / h^4 = 2.785 / h^4.
  An isolated element (nodes not shared) gives 12 / h^4: the affine patch's value.
subset DIC, square subsets of side S with shape function "zero" or "affine" (both give the
subset centre's displacement the covariance Σ_u / S^2: for a centred uniform subset the affine
terms decouple), on a grid of step s, strain from a least-squares plane fit over a window of
n x n subset centres (virtual strain gauge). The subset errors are averages of one white
per-area score over each subset, so two subsets are correlated by their overlap fraction
ρ(Δ) = (1 - |Δ1|/S)+ (1 - |Δ2|/S)+. With x_i = s (i - (n-1)/2):
    F = (1/S^2) [Σ_ij x_i x_j ρ1(x_i - x_j) / (Σ_i x_i^2)^2] [Σ_ij ρ1(x_i - x_j) / n^2],
  ρ1(d) = (1 - |d|/S)+; without overlap (s >= S) F = 12 / (S^2 s^2 n^2 (n^2 - 1)).

The gradients along ξ1 and ξ2 are uncorrelated (for both cases by symmetry) and have the same F
on square elements/windows, so in the face frame (small strain, t_u, t_v of the sample):
    var ε_uu = F t_uᵀ Σ_u t_u,  var ε_vv = F t_vᵀ Σ_u t_v,
    var ε_uv = (F / 4)(t_uᵀ Σ_u t_u + t_vᵀ Σ_u t_v)   (ε_uv = γ_uv / 2, tensor shear).
Like the displacement sigmas these are the bound for ONE noisy image against a noise-free
reference (x √2 when both images are noisy).
"""

from __future__ import annotations

import math

import numpy as np

from vdo.core.tolerances import SIZE_TOLERANCE, fits

STRAIN_COMPONENTS = ("uu", "vv", "uv")        # ε_uu, ε_vv, ε_uv (tensor shear) in the face frame
Q4_INTERIOR = 12.0 * math.sqrt(3.0) - 18.0    # F h^4 at an interior element's centre
AFFINE_PATCH = 12.0                           # F L^4 of an affine patch / isolated element
Q4_INTERIOR_NODE = 3.0                        # var(node) = 3 Σ_u / h^2 (interior node)
SHAPE_FUNCTIONS = ("zero", "affine")


def mass_matrix_1d(n_elements: int, h: float) -> np.ndarray:
    """(n + 1, n + 1) mass matrix ∫ N_a N_b dx of linear 1D elements of length h (m)."""
    M = np.zeros((n_elements + 1, n_elements + 1))
    for e in range(n_elements):
        M[e:e + 2, e:e + 2] += h / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    return M


def q4_centre_gradient_factors(nx: int, ny: int, i: int, j: int, hx: float,
                               hy: float) -> tuple[float, float]:
    """(F_1, F_2) in 1/m^4: var(∂u/∂ξ_k) = F_k Σ_u at the centre of element (i, j) of an nx x ny
    Q4 mesh with elements hx x hy (m), uniform information density. The centre gradient along ξ1
    is the tensor product of the difference d = (-1, 1)/hx over the element's nodes in x and the
    average a = (1/2, 1/2) in y, and M = M_x ⊗ M_y, so F_1 = (dᵀ M_x⁻¹ d)(aᵀ M_y⁻¹ a)."""
    if not (0 <= i < nx and 0 <= j < ny):
        raise ValueError(f"element ({i}, {j}) is outside the {nx} x {ny} mesh")

    def quad(n, h, e, vec):
        g = np.zeros(n + 1)
        g[e:e + 2] = vec
        return float(g @ np.linalg.solve(mass_matrix_1d(n, h), g))

    d = lambda h: np.array([-1.0, 1.0]) / h
    a = np.array([0.5, 0.5])
    return (quad(nx, hx, i, d(hx)) * quad(ny, hy, j, a),
            quad(nx, hx, i, a) * quad(ny, hy, j, d(hy)))


def vsg_shape(n: int, overlap: float) -> tuple[float, float]:
    """The dimensionless sums of the virtual-strain-gauge factor for n points per side at step s
    and subsets of side S, overlap = S / s: (G, A) with
    G = Σ_ij x_i x_j ρ1 / (Σ x^2)^2 in units of 1/s^2 and A = Σ_ij ρ1 / n^2 (module docstring)."""
    x = np.arange(n) - (n - 1) / 2.0                      # in steps
    rho = np.clip(1.0 - np.abs(x[:, None] - x[None, :]) / overlap, 0.0, None)
    return float(x @ rho @ x / (x @ x) ** 2), float(rho.sum() / n ** 2)


def vsg_factor(subset, step, n: int):
    """F (1/m^4) of the plane-fit gradient for subsets of side `subset` (m) on a grid of `step`
    (m), n x n points; arrays broadcast. Exact for any overlap (the overlap kernel is piecewise
    linear in S / s, so it is evaluated per distinct ratio)."""
    subset, step = np.broadcast_arrays(np.asarray(subset, float), np.asarray(step, float))
    ratio = subset / step
    out = np.empty(subset.shape)
    for r in np.unique(ratio):
        G, A = vsg_shape(n, float(r))
        sel = ratio == r
        out[sel] = G * A / (subset[sel] ** 2 * step[sel] ** 2)
    return out


def covariance_per_area(information: np.ndarray, patch_area: float, measured: np.ndarray):
    """Σ_u = Ω C⁻¹ (N, 3, 3) in m^4 from the per-sample information C (1/m^2) of a patch of area
    Ω (m^2); NaN where the displacement is not measured."""
    C = np.asarray(information, dtype=float)
    out = np.full(C.shape, np.nan)
    ok = np.asarray(measured, dtype=bool)
    out[ok] = patch_area * np.linalg.inv(C[ok])
    return out


def strain_sigma(sigma_u: np.ndarray, t_u: np.ndarray, t_v: np.ndarray, factor,
                 factor_v=None) -> np.ndarray:
    """(N, 3) σ of (ε_uu, ε_vv, ε_uv) (dimensionless; x 1e6 for µε) from Σ_u (N, 3, 3) m^4, the
    face frame t_u, t_v (N, 3) and the gradient factors (1/m^4, scalars or (N,)): F_1 = `factor`
    of ∂u/∂ξ1 and F_2 = `factor_v` of ∂u/∂ξ2 (default F_1: square elements/windows), the two
    gradients uncorrelated: var ε_uu = F_1 t_uᵀΣt_u, var ε_vv = F_2 t_vᵀΣt_v,
    var ε_uv = (F_2 t_uᵀΣt_u + F_1 t_vᵀΣt_v) / 4. NaN where Σ_u is."""
    F1 = np.asarray(factor, dtype=float)
    F2 = F1 if factor_v is None else np.asarray(factor_v, dtype=float)
    vu = np.einsum("ni,nij,nj->n", t_u, sigma_u, t_u)
    vv = np.einsum("ni,nij,nj->n", t_v, sigma_u, t_v)
    return np.sqrt(np.stack([F1 * vu, F2 * vv, (F2 * vu + F1 * vv) / 4.0], axis=-1))


def pixel_density(cameras, visible: np.ndarray, points, t_u, t_v) -> np.ndarray:
    """(N,) linear pixel density sqrt|det A| (pixel/m) of the finest camera that sees each sample
    (A = s [t_u t_v]; `visible` (C, N) bool, `vdo.physics.visibility.Visibility.visible`); 0 where none.
    The subset and step in pixels are taken in this camera's image (the reference camera of
    subset DIC)."""
    best = np.zeros(len(points))
    T = np.stack([t_u, t_v], axis=-1)
    for i, cam in enumerate(cameras):
        ok = np.asarray(visible[i], dtype=bool)
        if ok.any():
            A = cam.sensitivity(points[ok]) @ T[ok]
            best[ok] = np.maximum(best[ok], np.sqrt(np.abs(np.linalg.det(A))))
    return best


def sizes(analysis, density: np.ndarray):
    """Per sample (subset side S, step s) in metres for subset DIC: the mm settings as they are,
    the px settings through the finest camera's pixel density (pixel/m); NaN where unseen."""
    with np.errstate(divide="ignore"):
        per_px = np.where(density > 0, 1.0 / density, np.nan)
    S = np.full(density.shape, analysis.subset) if analysis.subset else analysis.subset_px * per_px
    s = np.full(density.shape, analysis.step) if analysis.step else analysis.step_px * per_px
    return S, s


def analysis_factors(analysis, density: np.ndarray):
    """Per sample (F_strain (1/m^4), F_displacement (1/m^2)): var ∂u/∂ξ = F_strain Σ_u and the
    analysis' displacement covariance F_displacement Σ_u (an interior Q4 node, or a subset)."""
    if analysis.method == "global":
        h = analysis.element
        n = np.ones(density.shape)
        return n * Q4_INTERIOR / h ** 4, n * Q4_INTERIOR_NODE / h ** 2
    S, s = sizes(analysis, density)
    ok = np.isfinite(S) & np.isfinite(s)
    Fs = np.full(density.shape, np.nan)
    Fs[ok] = vsg_factor(S[ok], s[ok], analysis.strain_window)
    return Fs, 1.0 / S ** 2


def check_regions(analysis, samples, density: np.ndarray, path) -> None:
    """ConfigError when the element (global) or the subset (subset DIC; its median size over the
    region's seen samples for a size in pixels) is larger than a region's smaller side (the
    extent of its samples' face coordinates plus one sample's side), beyond the relative
    `SIZE_TOLERANCE` (`fits`)."""
    from vdo.core.errors import ConfigError

    if analysis.method == "global":
        size, field = np.full(len(density), analysis.element), "analysis.element_mm"
    else:
        size = sizes(analysis, density)[0]
        field = "analysis.subset_mm" if analysis.subset else "analysis.subset_px"
    for k, name in enumerate(samples.region_names):
        mask = samples.region == k
        uv = samples.uv[mask]
        side = float((uv.max(axis=0) - uv.min(axis=0)).min()) + math.sqrt(samples.area[mask].mean())
        seen = size[mask][np.isfinite(size[mask])]
        if seen.size and not fits(float(np.median(seen)), side):
            raise ConfigError(path, field, f"is {np.median(seen) * 1e3:.6g} mm on the surface, "
                                           f"larger than region {name!r} ({side * 1e3:.6g} mm "
                                           f"across, relative tolerance {SIZE_TOLERANCE:g}): "
                                           "choose a smaller one")


def analysis_fields(analysis, density, samples, information, measured, patch_area):
    """Per sample: strain σ (N, 3) (ε_uu, ε_vv, ε_uv) and the analysis' displacement σ along its
    worst direction (N,) m, +inf where the displacement is not measured (one noisy image against
    a noise-free reference, as `vdo.physics.predict`). `density` from `pixel_density`."""
    sigma_u = covariance_per_area(information, patch_area, measured)
    Fs, Fd = analysis_factors(analysis, density)
    ok = np.asarray(measured, dtype=bool)
    lam = np.full(len(sigma_u), np.nan)
    lam[ok] = np.linalg.eigvalsh(sigma_u[ok])[:, -1]
    eps = strain_sigma(sigma_u, samples.tangent_u, samples.tangent_v, Fs)
    disp = np.sqrt(Fd * lam)
    eps[~(np.isfinite(eps).all(axis=1) & ok)] = np.inf
    return eps, np.where(np.isfinite(disp) & ok, disp, np.inf)
