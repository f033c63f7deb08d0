"""Global multi-view correlation (paper sec. 4): one set of 3D displacement unknowns, all cameras at once.

Used to check the predicted uncertainty (`vdo.objective`) against correlation on rendered images.
This module holds the option types, the result, the solver and `correlate` itself; the patch and
its integration points are `vdo.dic.patch`, the image interpolants `vdo.dic.images`, and many
square subsets solved at once (the same steps, vectorised) `vdo.dic.subsets`.

Formulation
-----------
The surface is a planar patch X(ξ) = origin + ξ1 t_u + ξ2 t_v, ξ in [0, size] (metres), the same face
coordinates (u, v) as `vdo.scene.RegionFaces.uv`. Cameras are known `vdo.model.camera.Camera` objects
(OpenCV frame, pixel (u, v) = (column, row), pixel centres at integer coordinates). The displacement
U(ξ) is expressed in the world (specimen) frame and is either a rigid translation (`Translation()`,
3 unknowns) or a bilinear Q4 finite-element field on an nx × ny mesh of the patch (`Q4(nx, ny)`, 3 dof per
node, dof index 3 * node + component, node = j * (nx + 1) + i with i along t_u).

For integration points ξ_p and cameras i the residual is

    r_ip = f_i^def(P_i(X(ξ_p) + U(ξ_p))) - (b_i + c_i g_i(ξ_p))

with g_i the reference seen by camera i:

* `ImageReference(images)`: g_i(ξ) = f_i^ref(P_i(X(ξ))), each camera against its own reference image
  (the classic choice). Both images are noisy, so the residual noise variance is σ_def² + c_i² σ_ref²,
  i.e. **twice the single-image (Cramér–Rao) bound** when σ_ref = σ_def and c ≈ 1: the covariance of
  U is ≈ 2σ² H⁻¹, not σ² H⁻¹.
* `AverageReference(images)`: the paper's eq. 3, g(ξ) = mean_j k_j (f_j^ref(P_j X(ξ)) - m_j), each
  reference normalised to zero mean / unit variance over the integration points, shared by all cameras.
* `TextureReference(texture, texel, pixel)`: the true texture f̂(ξ) (a callable of ξ (..., 2) in metres, or a pattern
  array + texel size mapped as `vdo.render` maps it: texel (row i, column j) has its centre at
  ξ = ((j + ½) h, (i + ½) h), bilinear, periodic) blurred by the camera's pixel: the box pixel is
  transported to the surface through the local Jacobian A_i = ∂x_i/∂ξ and averaged over
  `supersample`² sub-pixel points (`BoxPixel(supersample)`), or a Gaussian of std `sigma_px`
  (`GaussianPixel(sigma_px)`, Gauss–Hermite points). Only the deformed image is noisy: σ² H⁻¹.

Brightness / contrast (b_i, c_i) per camera are **unknowns solved alongside U** in the same
Gauss–Newton system (columns -1 and -g_i of the Jacobian), initialised by a linear least-squares fit
at the starting U. Their coupling to U is therefore in H, and `hessian_U` (the Schur complement, b
and c eliminated) is the Hessian whose inverse is the covariance of U.

The functional is Σ_i Σ_p w_ip r_ip² with w_ip = |det A_i(ξ_p)| × (surface area per integration
point): the number of camera-i pixels an integration point stands for, so that the sum approximates
the paper's sum over image pixels whatever the integration density (`Weights.PIXEL`; or
`Weights.UNIFORM`, w = 1). With this weighting H = Σ w JᵀJ is on the pixel-noise scale and σ² H⁻¹ is
the covariance for white pixel noise of variance σ² (in the continuum limit; spline interpolation of
the noise makes the true value a few percent off, see tests/dic/test_correlate.py).

Gauss–Newton on gray levels: J_ip = ∇f(x) · s_i(X) · N(ξ_p) with s_i = ∂x/∂X (`Camera.sensitivity`)
and N the shape functions. Images are interpolated (`vdo.dic.images`) by cubic B-splines
(`scipy.ndimage.spline_filter` once per image, `map_coordinates(order=3, prefilter=False)`); the
gradient is the spline's exact derivative (cubic weights and their derivatives on the 4 × 4
support). `order` picks the quintic B-spline (5) or Keys' cubic convolution (`KEYS`: the samples
weighed by k(x - m) directly, no prefilter; ∇f from k'). ∇f is taken from
* the reference image at its own pixel centres (`Gradient.REFERENCE`, default for images):
  a modified Gauss–Newton, J = c_i ∇f_i^ref(x) s_i(X) N, fixed but for c_i. At pixel centres the
  noise gradient is uncorrelated with the noise itself, so this has no noise-induced bias;
* the deformed image at the current position (`Gradient.DEFORMED`, default for texture and
  average): exact Gauss–Newton, J = ∇f_i^def(P_i(X + U)) s_i(X + U) N. Off the pixel grid the
  variance of spline-interpolated noise depends on the sub-pixel phase, E[∇n n] ≠ 0, and the mean
  estimate drifts by ~σ²-proportional amounts (measured ~0.002 px at σ = 0.02 of a 0.8 contrast;
  see tests/dic/test_correlate.py). (With the texture reference and the texture's own gradient, the sharp
  speckle's spline misfit biased noise-free results by ~0.05 px, so that is not the default.)

Integration: by default (`PixelIntegration`) each camera is integrated over its own reference pixel centres
on the patch (weight 1 each: the paper's sum over image pixels exactly, and the reference image
is read at its samples, not interpolated). A shared ξ grid (`GridIntegration`) makes every reference image
be interpolated off its pixel grid, which for sharp box-pixel speckle gives an interpolation bias
of ~0.015-0.03 px at 0.3 px shifts (measured), against ~0.003 px on the pixel centres.

Rank deficiency: the normal equations are solved by an eigen-decomposition, scaled so that the U dofs
(all metres) share one scale and b, c each have their own; directions with scaled eigenvalue
< `rcond` × the largest are dropped (pseudo-inverse: those
combinations keep their starting value), reported by `rank`, `rank_deficient` and
`null_directions`. A translation seen by one camera is determined along the viewing direction only
through perspective: H is not singular but badly conditioned; `uncertainty_ratio` (sqrt of the
eigenvalue ratio of `hessian_U`, in metres for every dof) and `weakest_direction` say so, and a
caller can pass a larger `Solver(rcond=...)` to drop it.

Every choice is a small option object (`ImageReference`, `Q4`, `GridIntegration`, `Gradient`,
`Solver`, ...), so a call states what it means and a wrong combination fails at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Callable, Sequence

import numpy as np

from vdo.dic.images import SPLINE_ORDER, TextureSampler, WindowedImage
from vdo.dic.patch import Patch, footprint, integration_points, pixel_points, q4_shape_functions

__all__ = ["CorrelationResult", "correlate", "ImageReference", "AverageReference", "TextureReference",
           "BoxPixel", "GaussianPixel", "Translation", "Q4", "PixelIntegration", "GridIntegration",
           "Weights", "Gradient", "Solver"]


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class CorrelationResult:
    """U: (3,) for `Translation`, (nodes, 3) for `Q4` (metres, world frame). b, c: (n_cameras,).
    hessian: the full Gauss–Newton Hessian Σ w JᵀJ (U dofs first, then b_0, c_0, b_1, c_1, ...), at
    the solution; hessian_U: its Schur complement on the U dofs (b, c eliminated)."""

    U: np.ndarray
    b: np.ndarray
    c: np.ndarray
    iterations: int
    residual_rms: float
    converged: bool
    hessian: np.ndarray
    hessian_U: np.ndarray
    rank: int
    rank_deficient: bool
    null_directions: np.ndarray      # (k, n_dofs) unit vectors in dof space that were dropped
    uncertainty_ratio: float         # sqrt(λ_max / λ_min) of hessian_U
    weakest_direction: np.ndarray    # eigenvector of hessian_U with the smallest eigenvalue
    xi: list                         # integration points per camera, each (N_i, 2)
    residual_rms_per_camera: np.ndarray
    reference: str                   # the reference's name: "images", "average" or "texture"
    model: str                       # "translation" or "q4"
    _camera_hessians: list = field(default_factory=list, repr=False)
    _reference_noise: np.ndarray | None = field(default=None, repr=False)
    _solve_inverse: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_u(self) -> int:
        return self.U.size

    def covariance(self, sigma, sigma_ref=None) -> np.ndarray:
        """Noise-propagated covariance of the U dofs (n_u × n_u, m²) for white Gaussian pixel noise of
        std `sigma` in the deformed images and `sigma_ref` in the reference images (default: the
        same; ignored for a TextureReference); each a scalar or one value per camera, in the gray
        levels of the images. Linear propagation H⁺ (Σ_i σ_i² H_i + σ_ref² M_ref) H⁺ with b, c
        solved alongside; for an ImageReference, σ_ref = σ and c = 1 this is 2σ² hessian_U⁻¹."""
        n = len(self._camera_hessians)
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,))
        M = sum(si ** 2 * Hi for si, Hi in zip(s, self._camera_hessians))
        if self._reference_noise is not None:
            sr = s if sigma_ref is None else np.broadcast_to(np.asarray(sigma_ref, dtype=float), (n,))
            M = M + sum(sr[i] ** 2 * self._reference_noise[i] for i in range(n))
        P = self._solve_inverse
        cov = P @ M @ P
        return cov[: self.n_u, : self.n_u]


# --------------------------------------------------------------------------------------------
# Solver
# --------------------------------------------------------------------------------------------
def _pinv_solve(H, rcond, nu):
    """Scaled eigen pseudo-inverse of symmetric H; returns (H⁺, rank, null directions).

    The U dofs (all in metres) share one scale, sqrt of the mean of their diagonal, so that a weak
    *physical* direction (e.g. along a single camera's viewing ray) shows as a small eigenvalue; each
    b, c dof gets its own (Jacobi) scale. Eigenvalues below rcond × the largest are dropped."""
    diag = np.clip(np.diag(H), 0, None)
    d = np.sqrt(diag)
    d[:nu] = np.sqrt(diag[:nu].mean()) if nu else 1.0
    d = np.where(d > 0, d, 1.0)
    Hs = H / d[:, None] / d[None, :]
    lam, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    keep = lam > rcond * lam.max()
    inv = (V[:, keep] / lam[keep]) @ V[:, keep].T
    Hp = inv / d[:, None] / d[None, :]
    null = (V[:, ~keep] / d[:, None]).T
    if len(null):
        null = null / np.linalg.norm(null, axis=1, keepdims=True)
    return Hp, int(keep.sum()), null


def _box_offsets(supersample):
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(o, o, indexing="xy")
    return np.stack([du.ravel(), dv.ravel()], 1), np.full(du.size, 1.0 / du.size)


def _gauss_offsets(sigma_px, order=5):
    t, w = np.polynomial.hermite_e.hermegauss(order)
    w = w / w.sum()
    du, dv = np.meshgrid(t * sigma_px, t * sigma_px, indexing="xy")
    return np.stack([du.ravel(), dv.ravel()], 1), np.outer(w, w).ravel()


def _texture_reference(texture, cam, patch, xi, offsets, weights, step_px=1e-3):
    """Texture blurred by the camera pixel, ĝ(ξ) = Σ_k w_k f̂(ξ + A⁻¹ δ_k) (A at each point), and its
    image gradient ∇_x ĝ = A⁻ᵀ ∇_ξ ĝ (central differences of step `step_px` pixels, footprint
    held fixed). Returns (ĝ (N,), ∇_x ĝ (N, 2))."""
    A = footprint(cam, patch, patch.points(xi))                  # (N, 2, 2)
    Ainv = np.linalg.inv(A)
    dxi = np.einsum("nij,kj->nki", Ainv, offsets)                # (N, K, 2)

    def at(x):
        return texture(x[:, None, :] + dxi) @ weights

    grad = np.zeros((len(xi), 2))
    for a in range(2):      # derivative along image axis a: ξ moves by A⁻¹ e_a
        h = step_px * Ainv[:, :, a]
        grad[:, a] = (at(xi + h) - at(xi - h)) / (2 * step_px)
    return at(xi), grad


# --------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ImageReference:
    """Each camera against its own reference image `images[i]` (gray levels, (height, width)).
    Both images noisy: the residual noise variance is σ_def² + c_i² σ_ref²."""

    images: Sequence
    name = "images"


@dataclass(frozen=True, eq=False)
class AverageReference:
    """The paper's eq. 3: one reference shared by all cameras, the mean of the `images`
    normalised to zero mean and unit variance over the integration points (needs a shared grid,
    `GridIntegration`)."""

    images: Sequence
    name = "average"


@dataclass(frozen=True)
class BoxPixel:
    """A camera's box pixel, averaged over `supersample`² sub-pixel points."""

    supersample: int = 4


@dataclass(frozen=True)
class GaussianPixel:
    """A Gaussian pixel of std `sigma_px` pixels (Gauss–Hermite points)."""

    sigma_px: float = 0.5


@dataclass(frozen=True, eq=False)
class TextureReference:
    """The true texture f̂(ξ): a callable of ξ (..., 2) in metres, or a pattern array mapped as
    `vdo.render` maps it (`TextureSampler`, `texel` metres), blurred by the camera's `pixel`.
    Only the deformed image is noisy."""

    texture: Callable | np.ndarray
    texel: float | None = None
    pixel: BoxPixel | GaussianPixel = BoxPixel()
    name = "texture"

    def sampler(self) -> Callable:
        if callable(self.texture):
            return self.texture
        if self.texel is None:
            raise ValueError("TextureReference with a pattern array: expected `texel`")
        return TextureSampler(self.texture, self.texel)


Reference = ImageReference | AverageReference | TextureReference


@dataclass(frozen=True)
class Translation:
    """A rigid translation of the patch: U (3,), world frame, metres."""

    name = "translation"


@dataclass(frozen=True)
class Q4:
    """A bilinear field on an nx × ny element mesh of the patch: U (nodes, 3), node
    j * (nx + 1) + i with i along t_u."""

    nx: int = 1
    ny: int = 1
    name = "q4"

    def __post_init__(self):
        if int(self.nx) < 1 or int(self.ny) < 1:
            raise ValueError(f"Q4: expected nx, ny >= 1, got ({self.nx}, {self.ny})")


class Weights(Enum):
    """The weight of a grid integration point: the camera pixels it stands for
    (|det A_i| × cell area), or 1."""

    PIXEL = "pixel"
    UNIFORM = "uniform"


@dataclass(frozen=True, eq=False)
class PixelIntegration:
    """Each camera integrated over its own reference pixel centres on the patch (weight 1 each),
    keeping those that every camera sees at least `margin_px` inside its image; or the given
    per-camera points `xi` (one (N_i, 2) array per camera, e.g. `result.xi` of an earlier call)."""

    xi: Sequence | None = None
    margin_px: float = 3.0


@dataclass(frozen=True, eq=False)
class GridIntegration:
    """One ξ grid shared by all cameras: `integration_points(patch, cameras, spacing, density,
    margin_px)`, or the given `xi` (N, 2) with its `cell_area` (m², needed with pixel weights)."""

    xi: np.ndarray | None = None
    cell_area: float | None = None
    spacing: float | None = None
    density: float = 1.0
    margin_px: float = 3.0
    weights: Weights = Weights.PIXEL


class Gradient(Enum):
    """Where the Gauss–Newton image gradient comes from (module docstring): the reference at its
    own points (modified Gauss–Newton, fixed J), or the deformed image at the current position."""

    REFERENCE = "reference"
    DEFORMED = "deformed"


@dataclass(frozen=True)
class Solver:
    """Stop when max |ΔU| < `tol` (metres) or after `max_iter` iterations; drop the directions of
    the scaled normal matrix with eigenvalue < `rcond` × the largest (`_pinv_solve`)."""

    tol: float = 1e-6
    max_iter: int = 30
    rcond: float = 1e-10


def _integration_points_and_weights(integration, cameras, patch):
    """Per camera: the integration points ξ (N_i, 2) and their weights (N_i,)."""
    nc = len(cameras)
    if isinstance(integration, GridIntegration):
        if isinstance(integration.xi, (list, tuple)):
            raise ValueError("GridIntegration needs one `xi` array shared by all cameras")
        cell_area = integration.cell_area
        if integration.xi is None:
            xi, cell_area = integration_points(patch, cameras, integration.spacing,
                                               integration.density, integration.margin_px)
        else:
            xi = np.asarray(integration.xi, dtype=float).reshape(-1, 2)
            if cell_area is None and integration.weights is Weights.PIXEL:
                raise ValueError("correlate: given `xi` with Weights.PIXEL needs `cell_area`")
        pixel = integration.weights is Weights.PIXEL
        return [xi] * nc, [np.abs(np.linalg.det(footprint(cam, patch, patch.points(xi)))) * cell_area
                           if pixel else np.ones(len(xi)) for cam in cameras]
    if not isinstance(integration, PixelIntegration):
        raise ValueError(f"integration: expected PixelIntegration or GridIntegration, got {integration!r}")
    if integration.xi is not None:      # e.g. `result.xi` of an earlier run on the same images
        if len(integration.xi) != nc:
            raise ValueError("correlate: PixelIntegration.xi needs one array per camera")
        xis = [np.asarray(x, dtype=float).reshape(-1, 2) for x in integration.xi]
    else:
        xis = [pixel_points(patch, cameras, i, integration.margin_px) for i in range(nc)]
    return xis, [np.ones(len(x)) for x in xis]


DENSE_NODES = 16    # meshes of up to this many nodes keep their shape functions dense


def _scale_rows(N, v):
    """diag(v) N for a dense or a SciPy sparse N."""
    return N.multiply(v[:, None]) if hasattr(N, "multiply") else N * v[:, None]


def _dense(M) -> np.ndarray:
    return M.toarray() if hasattr(M, "toarray") else np.asarray(M)


def _transpose_times(N):
    """X -> Nᵀ X for a dense or a SciPy sparse N (dense: einsum, several times faster than matmul's
    path for a (points, 1) N)."""
    if hasattr(N, "tocsr"):
        NT = N.T.tocsr()
        return lambda X: NT @ X
    return lambda X: np.einsum("pn,pk->nk", N, X)


def correlate(cameras: Sequence, deformed: Sequence, patch: Patch, reference: Reference, *,
              model: Translation | Q4 = Translation(),
              integration: PixelIntegration | GridIntegration | None = None,
              gradient: Gradient | None = None, U0=None,
              solver: Solver = Solver(), order: int = SPLINE_ORDER) -> CorrelationResult:
    """Global multi-view Gauss–Newton correlation of `deformed` images (one per camera, gray levels,
    (height, width)) on `patch`; see the module docstring for the formulation.

    reference    `ImageReference(images)` (each camera against its own reference image),
                 `AverageReference(images)` (paper eq. 3) or `TextureReference(texture, texel,
                 pixel=BoxPixel(4) | GaussianPixel(0.5))`
    model        `Translation()` (U (3,)) or `Q4(nx, ny)` (U (nodes, 3))
    integration  `PixelIntegration()` (each camera's own reference pixel centres on the patch,
                 weight 1; the default for images and texture) or `GridIntegration()` (one grid ξ
                 shared by all cameras, pixel or uniform weights; the default, and only choice,
                 for the average reference). Either way only points that every camera sees at
                 least `margin_px` inside its image are kept.
    gradient     `Gradient.REFERENCE` (J from the reference: c_i ∇g_i(x) · s_i(X) N, modified
                 Gauss–Newton; the default for images and texture) or `Gradient.DEFORMED`
                 (∇f_i^def at the current position; the default, and only choice, for average)
    U0           starting U (3,) (broadcast to every node of a Q4 mesh) or (nodes, 3)
    solver       `Solver(tol, max_iter, rcond)`
    order        the B-spline order of the image interpolation (`SplineImage`), read on windows
                 around the points (`WindowedImage`)
    """
    cameras = list(cameras)
    nc = len(cameras)
    if nc == 0 or len(deformed) != nc:
        raise ValueError("correlate: expected one deformed image per camera")
    if not isinstance(reference, (ImageReference, AverageReference, TextureReference)):
        raise ValueError("reference: expected ImageReference(images), AverageReference(images) or "
                         f"TextureReference(texture, texel), got {type(reference).__name__}")
    if not isinstance(model, (Translation, Q4)):
        raise ValueError(f"model: expected Translation() or Q4(nx, ny), got {model!r}")
    averaged = isinstance(reference, AverageReference)
    if integration is None:
        integration = GridIntegration() if averaged else PixelIntegration()
    if averaged and not isinstance(integration, GridIntegration):
        raise ValueError("AverageReference needs GridIntegration (one ξ shared by all cameras)")
    on_pixels = isinstance(integration, PixelIntegration)
    if gradient is None:
        gradient = Gradient.REFERENCE if isinstance(reference, ImageReference) else Gradient.DEFORMED
    if gradient is Gradient.REFERENCE and averaged:
        raise ValueError("Gradient.REFERENCE is not available with AverageReference")
    tol, max_iter, rcond = solver.tol, solver.max_iter, solver.rcond

    xis, ws = _integration_points_and_weights(integration, cameras, patch)
    for i, x in enumerate(xis):
        if len(x) < 4:
            raise ValueError(f"correlate: only {len(x)} integration points for camera "
                             f"{cameras[i].name!r} are seen by every camera")
    Xs = [patch.points(x) for x in xis]

    # Kinematics: N (points × nodes) per camera; sparse for large meshes, dense for a few nodes
    # (where SciPy's per-call overhead would cost more than the arithmetic).
    if isinstance(model, Translation):
        Ns = [np.ones((len(x), 1)) for x in xis]
    else:
        Ns = [q4_shape_functions(x, patch.size, int(model.nx), int(model.ny)) for x in xis]
        if Ns[0].shape[1] <= DENSE_NODES:
            Ns = [N.toarray() for N in Ns]
    nn = Ns[0].shape[1]
    nu = 3 * nn
    ndof = nu + 2 * nc

    # Reference gray levels g_i at camera i's points.
    k = np.ones(nc)
    if not isinstance(reference, TextureReference) and len(reference.images) != nc:
        raise ValueError(f"{type(reference).__name__}: expected one reference image per camera")
    if isinstance(reference, ImageReference):
        g = []
        for cam, im, X in zip(cameras, reference.images, Xs):
            im = np.asarray(im, dtype=float)
            if on_pixels:      # the rays of pixel centres: read the samples directly
                x = np.rint(cam.project(X)).astype(int)
                g.append(im[x[:, 1], x[:, 0]])
            else:
                g.append(WindowedImage(im, order=order)(cam.project(X)))
    elif averaged:
        g = [WindowedImage(im, order=order)(cam.project(Xs[0])) for cam, im in zip(cameras, reference.images)]
        mean = np.array([gi.mean() for gi in g])
        k = 1.0 / np.array([gi.std() for gi in g])
        avg = sum(k[i] * (g[i] - mean[i]) for i in range(nc)) / nc
        g = [avg] * nc
    else:
        texture = reference.sampler()
        if isinstance(reference.pixel, BoxPixel):
            offs, ow = _box_offsets(int(reference.pixel.supersample))
        elif isinstance(reference.pixel, GaussianPixel):
            offs, ow = _gauss_offsets(float(reference.pixel.sigma_px))
        else:
            raise ValueError(f"TextureReference.pixel: expected BoxPixel or GaussianPixel, got "
                             f"{reference.pixel!r}")
        g, ref_grad = zip(*[_texture_reference(texture, cam, patch, x, offs, ow)
                            for cam, x in zip(cameras, xis)])
        g = list(g)

    if gradient is Gradient.REFERENCE:
        # G0_i = ∇_x g_i · s_i(X) (points, 3), fixed; the U columns of J are c_i G0_i.
        if isinstance(reference, ImageReference):
            ref_grad = [WindowedImage(im, order=order).gradient(cam.project(X))
                        for cam, im, X in zip(cameras, reference.images, Xs)]
        G0 = [np.einsum("nj,nja->na", gr, cam.sensitivity(X))
              for gr, cam, X in zip(ref_grad, cameras, Xs)]

    splines = [WindowedImage(im, order=order) for im in deformed]

    p = np.zeros(ndof)
    if U0 is not None:
        U0 = np.asarray(U0, dtype=float)
        p[:nu] = np.broadcast_to(U0, (nn, 3)).ravel() if isinstance(model, Q4) else U0.reshape(3)

    def evaluate(p):
        """Per camera: residual r, U-gradient rows G (points, 3) = ∇f · s, image values f."""
        Un = p[:nu].reshape(nn, 3)
        out = []
        for i, (cam, sp) in enumerate(zip(cameras, splines)):
            Xd = Xs[i] + Ns[i] @ Un
            if gradient is Gradient.REFERENCE:
                f = sp(cam.project(Xd))
                G = p[nu + 2 * i + 1] * G0[i]
            else:
                f, grad = sp.value_and_gradient(cam.project(Xd))
                G = np.einsum("nj,nja->na", grad, cam.sensitivity(Xd))
            r = f - p[nu + 2 * i] - p[nu + 2 * i + 1] * g[i]
            out.append((r, G, f))
        return out

    # Initial b, c by linear least squares at the starting U.
    for i, (r, G, f) in enumerate(evaluate(p)):
        sw = np.sqrt(ws[i])
        Aab = np.stack([np.ones(len(f)), g[i]], 1) * sw[:, None]
        p[nu + 2 * i: nu + 2 * i + 2] = np.linalg.lstsq(Aab, f * sw, rcond=None)[0]

    def jacobian(i, G):
        """Dense (points, ndof) Jacobian of camera i's residuals."""
        N = Ns[i]
        J = np.zeros((N.shape[0], ndof))
        J[:, :nu] = np.stack([_dense(_scale_rows(N, G[:, a])) for a in range(3)], 2).reshape(-1, nu)
        J[:, nu + 2 * i] = -1.0
        J[:, nu + 2 * i + 1] = -g[i]
        return J

    def assemble(ev):
        H = np.zeros((ndof, ndof))
        rhs = np.zeros(ndof)
        Hcams = []
        for i, (r, G, f) in enumerate(ev):
            N, wi = Ns[i], ws[i]
            Nt_times = _transpose_times(N)
            Hi = np.zeros((ndof, ndof))
            blocks = np.zeros((nn, 3, nn, 3))
            for a in range(3):             # H[(n,a),(m,b)] = Σ_p w G_a G_b N_n N_m
                for bb in range(a, 3):
                    Mab = _dense(Nt_times(_scale_rows(N, wi * G[:, a] * G[:, bb])))
                    blocks[:, a, :, bb] = Mab
                    blocks[:, bb, :, a] = Mab
            Hi[:nu, :nu] = blocks.reshape(nu, nu)
            jc = -g[i]
            ib, ic = nu + 2 * i, nu + 2 * i + 1
            Hi[:nu, ib] = Hi[ib, :nu] = -Nt_times(wi[:, None] * G).reshape(nu)
            Hi[:nu, ic] = Hi[ic, :nu] = Nt_times(wi[:, None] * G * jc[:, None]).reshape(nu)
            Hi[ib, ib] = np.sum(wi)
            Hi[ic, ic] = np.sum(wi * jc * jc)
            Hi[ib, ic] = Hi[ic, ib] = -np.sum(wi * jc)
            rhs[:nu] -= Nt_times(wi[:, None] * G * r[:, None]).reshape(nu)
            rhs[ib] += np.sum(wi * r)
            rhs[ic] -= np.sum(wi * jc * r)
            H += Hi
            Hcams.append(Hi)
        return H, rhs, Hcams

    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        H, rhs, _ = assemble(evaluate(p))
        Hp, rank, null = _pinv_solve(H, rcond, nu)
        dp = Hp @ rhs
        p += dp
        if np.max(np.abs(dp[:nu])) < tol:
            converged = True
            break

    # Final state: residuals and Hessian at the solution.
    ev = evaluate(p)
    H, rhs, Hcams = assemble(ev)
    Hp, rank, null = _pinv_solve(H, rcond, nu)
    sq = np.array([np.sum(ws[i] * ev[i][0] ** 2) for i in range(nc)])
    wsum = np.array([np.sum(wi) for wi in ws])
    rms_cam = np.sqrt(sq / wsum)
    rms = float(np.sqrt(sq.sum() / wsum.sum()))

    # Schur complement on U (b, c eliminated).
    HU = H[:nu, :nu] - H[:nu, nu:] @ np.linalg.pinv(H[nu:, nu:]) @ H[nu:, :nu]
    HU = 0.5 * (HU + HU.T)
    lam, V = np.linalg.eigh(HU)
    ratio = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")

    # Reference-noise matrices (unit σ_ref per camera), for `covariance`.
    ref_noise = None
    if isinstance(reference, ImageReference):
        ref_noise = [p[nu + 2 * i + 1] ** 2 * Hcams[i] for i in range(nc)]
    elif averaged:
        # Noise n_j of reference j enters every residual through g = Σ_j k_j n_j / nc; its
        # contribution to the gradient is a_jp n_j(x_jp) with a_jp = (k_j / nc) Σ_i c_i w_ip J_ip.
        # Pixel-sampled white noise summed over camera j's pixels: Var = σ² Σ_p a_jp a_jpᵀ / w_jp.
        S = sum(p[nu + 2 * i + 1] * ws[i][:, None] * jacobian(i, ev[i][1]) for i in range(nc))
        ref_noise = [((k[j] / nc) ** 2) * (S / ws[j][:, None]).T @ S for j in range(nc)]

    U = p[:nu].reshape(nn, 3)
    return CorrelationResult(
        U=U[0].copy() if isinstance(model, Translation) else U.copy(),
        b=p[nu::2].copy(), c=p[nu + 1::2].copy(), iterations=it, residual_rms=rms,
        converged=converged, hessian=H, hessian_U=HU, rank=rank, rank_deficient=rank < ndof,
        null_directions=null, uncertainty_ratio=ratio, weakest_direction=V[:, 0].copy(),
        xi=xis, residual_rms_per_camera=rms_cam, reference=reference.name, model=model.name,
        _camera_hessians=Hcams, _reference_noise=ref_noise, _solve_inverse=Hp)
