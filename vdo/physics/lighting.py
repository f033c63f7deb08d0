"""The light model: irradiance and shadows on the surface samples, and the photometry of the images.

Shared by the renderer (`vdo.render`: its shadow map and photometry table) and the uncertainty
predictor (the contrast and noise that `vdo.objective` takes), so that both use one model.

Lights. Each [[light]] is a one-sided rectangular Lambertian emitter of radiance L (W sr^-1 m^-2, or
any unit the sensor's photons_per_unit is stated in), centred at `position`, its emitting side
facing `target` (normal n_l = (target - position) / |target - position|), of size (width, height)
along (e_1, e_2): e_1 = z x n_l normalised (horizontal; world x when n_l is vertical), e_2 = n_l x e_1.
This is how the built-in LED panel meshes are oriented (experiments/beam_column/make_meshes.py), and
the rectangle `vdo.render` gives Mitsuba.

Irradiance at a sample X (normal n) from one light, by the midpoint rule on an n x n grid of panel
points P_j (cell area ΔA = width height / n^2):

    E(X) = Σ_j  V_j L cosθ_s cosθ_l / r^2 ΔA          [W m^-2]

with r = |P_j - X|, cosθ_s = n . (P_j - X) / r (at the sample), cosθ_l = n_l . (X - P_j) / r (at the
panel), V_j = 1 when both cosines are positive and the segment X -> P_j is free (a Mitsuba
`ray_test` against the scene: meshes and camera bodies), else 0. The visible fraction of the light
is lit = mean_j V_j. The midpoint rule is accurate to O((size / r)^2 / n^2): below 0.1 % for a
0.3 m panel 1 m away with n = 8.

Ambient: a uniform sky of radiance L_amb gives

    E_amb(X) = L_amb ∫_sky cosθ dω = π L_amb S(X)                       [W m^-2]

with S in [0, 1] the cosine-weighted fraction of the hemisphere above X that sees the sky (not the
scene): S = mean_j V(ω_j) over SKY_GRID^2 directions ω_j drawn cosine-weighted at the centres of
a SKY_GRID x SKY_GRID grid of strata (Malley's method: u_1, u_2 stratum centres, r = sqrt(u_1),
φ = 2π u_2, ω = (r cos φ, r sin φ, sqrt(1 - u_1)) in the sample's frame), each a shadow ray
against the scene (the ambient occlusion, which the renderer has too). Sample i's grid is turned
about its normal by φ_i = 2π frac(i SKY_TURN) (a Weyl sequence), so that the fixed grid's error
at a sky's edge (up to ~5 % at one point) differs from sample to sample and averages out over a
region (beside a long wall of height h, 64 floor points at distance d: mean S within 1 % of the
closed form (1 + d / sqrt(d^2 + h^2)) / 2, `tests/physics/test_lighting.py`). A convex region in
the open keeps S = 1; a nozzle's wall beside its shell sees less sky (the pressure vessel's
nozzle: S = 0.76 on average, its rendered brightness 22 % below what S = 1 predicts).

Photometry. For a Lambertian surface of albedo ρ the renderer's linear pixel value is ρ E / π (the
reflected radiance; the camera's exposure is folded into the sensor's photons_per_unit). The speckle
paint has albedo ρ = ρ_b + (ρ_w - ρ_b) f, f in [0, 1] the pattern (1 = white). With
g = K QE photons_per_unit (DN per unit linear value) the image is b + c f̂ (f̂ = normalised pattern):

    b = sensor.mean_dn(<ρ> E / π)                       = g <ρ> E / π + offset    [DN]
    c = g (ρ_w - ρ_b) std(f) E / π                                                [DN]
    σ = sensor.noise_sigma_dn(<ρ> E / π)                                          [DN rms]

<ρ> = ρ_b + (ρ_w - ρ_b) mean(f). A camera that gathers k times the sensor's reference light
(its f-number and exposure time, `exposure_factors`) records k <ρ> E / π: b, c and σ above with
E -> k E. The pattern statistics are those of the unblurred texture; the
pixel's blur is the objective's business (g_f). For a Lambertian surface the image level does not
depend on the camera except through visibility; the arrays are (C, N) anyway, as the objective takes
them. Saturation is ignored (see `SensorModel.variance_dn`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vdo.core.backend import mitsuba
from vdo.config.rig import LightSpec, SpeckleSpec
from vdo.scene import SurfaceSamples, inside_mesh
from vdo.model.optics import exposure_factor
from vdo.model.sensor import SensorModel
from vdo.core.tolerances import RAY_OFFSET_M

EPSILON = RAY_OFFSET_M   # m: shadow rays start this far off the surface and stop this short of the panel
GRID = 8         # panel points per side for the irradiance integral
REACH = 0.5      # a light reaches a sample when at least this fraction of its panel is visible from it
SKY_GRID = 12    # sky directions per side of the stratified cosine-weighted hemisphere (144 rays a sample)
SKY_TURN = (math.sqrt(5) - 1) / 2   # sample i's directions turn by 2π frac(i SKY_TURN) about its normal


# --------------------------------------------------------------------------------------------
# Panels
# --------------------------------------------------------------------------------------------
def panel_frame(light: LightSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n_l, e_1, e_2): the emitting normal and the panel's width and height directions."""
    n = np.asarray(light.target, float) - np.asarray(light.position, float)
    n /= np.linalg.norm(n)
    e1 = np.cross([0.0, 0.0, 1.0], n)
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return n, e1, np.cross(n, e1)


def panel_points(light: LightSpec, grid: int = GRID) -> tuple[np.ndarray, float]:
    """Centres of the grid x grid cells of the panel (grid^2, 3) and the cell area ΔA (m^2)."""
    _, e1, e2 = panel_frame(light)
    w, h = light.size
    s = (np.arange(grid) + 0.5) / grid - 0.5
    a, b = np.meshgrid(s * w, s * h, indexing="ij")
    pts = np.asarray(light.position, float) + a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2
    return pts, w * h / grid**2


# --------------------------------------------------------------------------------------------
# Irradiance and shadows
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Illumination:
    """Per light and sample: lit (L, N) visible fraction of the panel in [0, 1], direct (L, N)
    irradiance in W m^-2 (radiance unit x sr); `ambient` π L_amb (W m^-2), the irradiance of the
    open sky; `sky` (N,) the cosine-weighted fraction S of each sample's hemisphere that sees the
    sky (module docstring; None: S = 1 everywhere, no ambient occlusion)."""

    light_names: tuple[str, ...]
    lit: np.ndarray
    direct: np.ndarray
    ambient: float = 0.0
    sky: np.ndarray | None = None

    @property
    def sky_irradiance(self) -> np.ndarray:
        """The ambient sky's irradiance at each sample (N,), π L_amb S, W m^-2."""
        return self.ambient * (np.ones(self.direct.shape[1]) if self.sky is None else self.sky)

    @property
    def irradiance(self) -> np.ndarray:
        """Total irradiance E (N,) in W m^-2: all lights plus the ambient sky, π L_amb S."""
        return self.direct.sum(axis=0) + self.sky_irradiance

    @property
    def sampling_cv2(self) -> np.ndarray:
        """(N,) the squared coefficient of variation V / E² of the sampled render mode's one-sample
        estimate of E (`vdo.rendering.scene`'s `vdo_panels`: one point per panel, one
        BSDF-sampled sky direction, a shadow ray each), 0 where E = 0. Each panel's term is
        E_l / lit_l times a Bernoulli of its visible fraction lit_l, the sky's π L_amb times a
        Bernoulli of S; the cosθ/r² variation over a panel (about 1 % per sample) is left out:

            V = Σ_l E_l² (1 - lit_l) / lit_l + (π L_amb)² S (1 - S)              [W² m^-4]"""
        lit = self.lit
        panels = np.where(lit > 0, self.direct ** 2 * (1 - lit) / np.where(lit > 0, lit, 1.0), 0.0).sum(axis=0)
        S = np.ones(self.direct.shape[1]) if self.sky is None else self.sky
        V = panels + self.ambient ** 2 * S * (1 - S)
        E = self.irradiance
        return np.where(E > 0, V / np.where(E > 0, E, 1.0) ** 2, 0.0)

    @property
    def lights_reaching(self) -> np.ndarray:
        """Number of lights of which at least half the panel (REACH) is visible, per sample (N,)."""
        return (self.lit >= REACH).sum(axis=0)


def illuminate(scene, lights, samples: SurfaceSamples, ambient_radiance: float = 0.0,
               grid: int = GRID, batch_rays: int = 4_000_000) -> Illumination:
    """Irradiance and visible fraction of every light at every sample (module docstring).

    `scene` is a Mitsuba scene for shadow rays (vdo.scene.build_scene of the meshes and camera
    bodies); it must not hold the emitters themselves. All shadow rays of a light go to Mitsuba's
    `ray_test` in batches of at most `batch_rays`. With `ambient_radiance` > 0 each sample's sky
    fraction S is cast too (SKY_GRID^2 shadow rays a sample, `_sky`)."""
    X, nrm = np.asarray(samples.points, float), np.asarray(samples.normals, float)
    lit, direct = _cast(scene, lights, X, nrm, grid, batch_rays)
    sky = _sky(scene, X, nrm, batch_rays) if ambient_radiance > 0 else None
    return Illumination(tuple(lt.name for lt in lights), lit, direct, float(np.pi * ambient_radiance),
                        sky)


def relight(scene, lights, samples: SurfaceSamples, unobstructed: Illumination,
            occluders: list[np.ndarray], grid: int = GRID, batch_rays: int = 4_000_000) -> Illumination:
    """`illuminate(scene, lights, samples)` for a scene that is the scene of `unobstructed` (the
    same lights and samples) plus the `occluders` (vertex arrays (V, 3), e.g. camera bodies),
    casting again only the samples whose shadow rays an occluder may cross; the others keep
    their values from `unobstructed`, which is exact: an added obstacle can only block rays it
    meets. A sample x is cast again, for a light with panel centre P_c and grid points within ρ
    of it, when some occluder's bounding sphere (centre c, radius R) comes within R + ρ of the
    segment x -> P_c (every shadow ray x -> P_j lies within ρ of that segment). On the built-in
    experiment's 13,488 samples and 10 camera bodies, a few percent of the samples. The sky
    fraction S is cast again for the samples that have some occluder's bounding sphere above
    their tangent plane (n.(c - x) > -R - EPSILON: only then can a sky ray meet it)."""
    X = np.asarray(samples.points, float)
    lit, direct = unobstructed.lit.copy(), unobstructed.direct.copy()
    spheres = [((v.max(axis=0) + v.min(axis=0)) / 2, v) for v in map(np.asarray, occluders) if len(v)]
    spheres = np.array([[*c, np.linalg.norm(v - c, axis=1).max()] for c, v in spheres]).reshape(-1, 4)
    for k, light in enumerate(lights):
        P, _ = panel_points(light, grid)
        centre = P.mean(axis=0)
        rho = np.linalg.norm(P - centre, axis=1).max() + EPSILON
        seg = centre - X                                                   # (N, 3)
        t = np.clip(((spheres[None, :, :3] - X[:, None]) @ seg[..., None])[..., 0]
                    / np.maximum((seg * seg).sum(axis=1), 1e-12)[:, None], 0.0, 1.0)   # (N, K)
        gap = np.linalg.norm(X[:, None] + t[..., None] * seg[:, None] - spheres[None, :, :3], axis=-1)
        near = np.flatnonzero((gap <= spheres[None, :, 3] + rho).any(axis=1))
        if near.size:
            lit_k, direct_k = _cast(scene, [light], X[near], np.asarray(samples.normals, float)[near],
                                    grid, batch_rays)
            lit[k, near], direct[k, near] = lit_k[0], direct_k[0]
    sky = unobstructed.sky
    if sky is not None and len(spheres):
        nrm = np.asarray(samples.normals, float)
        above = ((spheres[None, :, :3] - X[:, None]) * nrm[:, None]).sum(axis=-1) > -spheres[None, :, 3] - EPSILON
        near = np.flatnonzero(above.any(axis=1))
        sky = sky.copy()
        if near.size:
            sky[near] = _sky(scene, X[near], nrm[near], batch_rays, near)
    return Illumination(unobstructed.light_names, lit, direct, unobstructed.ambient, sky)


def dark_lights(illumination: Illumination, lights, meshes) -> list[str]:
    """One line per light of `lights` that reaches no sample of `illumination` (no sample sees
    REACH of its panel, as in `Illumination.lights_reaching`: the panel faces away from every
    sample, or something blocks it; not "no ray at all", since a shadow ray can slip between two
    triangles of a closed mesh at their shared edge), naming the mesh of `meshes`
    (`vdo.scene.SceneMesh`) that its panel centre lies inside (`vdo.scene.inside_mesh`, tested
    only for such a light and the meshes whose bounding box holds its centre), and the fix."""
    out = []
    for k, light in enumerate(lights):
        if np.any(illumination.lit[k] >= REACH):
            continue
        centre = np.asarray(light.position, dtype=float)
        holder = next((m.name for m in meshes if np.all(centre >= m.vertices.min(axis=0))
                       and np.all(centre <= m.vertices.max(axis=0))
                       and inside_mesh(centre[None], m.vertices, m.faces)[0]), None)
        out.append(f"light {light.name!r} lights no region sample " + (
            f"(its centre is inside mesh {holder!r}): move it (position_m) out of the mesh"
            if holder else "(it faces away from them, or something blocks it): aim it at the "
                           "regions (target_m) or move it (position_m)"))
    return out


def _sky(scene, X: np.ndarray, nrm: np.ndarray, batch_rays: int, index=None) -> np.ndarray:
    """(N,) the cosine-weighted fraction S of the hemisphere above each point X (normal nrm) whose
    ray escapes the scene (module docstring): SKY_GRID^2 stratified cosine-weighted directions in
    the frame (t, b, n) of each point, point i's turned by 2π frac(i SKY_TURN) about n (i its
    sample `index`, default 0..N-1), shadow rays from X + EPSILON n in batches of `batch_rays`."""
    mi = mitsuba()
    u = (np.arange(SKY_GRID) + 0.5) / SKY_GRID
    u1, u2 = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    r = np.sqrt(u1)
    index = np.arange(len(X)) if index is None else np.asarray(index)
    phi = 2 * np.pi * (u2[None, :] + (index * SKY_TURN % 1.0)[:, None])     # (N, G)
    cos_phi, sin_phi, up = r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)
    t = np.cross(nrm, [0.0, 0.0, 1.0])
    flat = np.linalg.norm(t, axis=1) < 1e-6                     # normal along z: any tangent
    t[flat] = np.cross(nrm[flat], [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(nrm, t)
    G = len(u1)
    out = np.empty(len(X))
    per = max(1, batch_rays // G)
    for start in range(0, len(X), per):
        sl = slice(start, start + per)
        d = (cos_phi[sl, :, None] * t[sl, None] + sin_phi[sl, :, None] * b[sl, None]
             + up[None, :, None] * nrm[sl, None]).reshape(-1, 3)
        o = np.repeat(X[sl] + EPSILON * nrm[sl], G, axis=0)
        ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(o[:, a], np.float32)) for a in range(3))),
                       mi.Vector3f(*(mi.Float(np.ascontiguousarray(d[:, a], np.float32)) for a in range(3))))
        blocked = scene.ray_test(ray).numpy().reshape(-1, G)
        out[sl] = 1.0 - blocked.mean(axis=1)
    return out


def _cast(scene, lights, X: np.ndarray, nrm: np.ndarray, grid: int, batch_rays: int):
    """(lit, direct), each (L, N), of the points X with normals nrm (`illuminate`). One Dr.Jit
    kernel per light and batch: ray k is sample k // G to panel point k % G, its geometry in
    float64 (rays in float32, as Mitsuba traces them), the sums over the G panel points by
    `drjit.block_sum`."""
    import drjit as dr

    mi = mitsuba()
    F64 = mi.Float64
    n_s = len(X)
    lit = np.zeros((len(lights), n_s))
    direct = np.zeros((len(lights), n_s))
    for k, light in enumerate(lights):
        P, dA = panel_points(light, grid)
        G = len(P)
        n_l, _, _ = panel_frame(light)
        per = max(1, batch_rays // G)
        panel = [F64(np.ascontiguousarray(P[:, a])) for a in range(3)]
        for start in range(0, n_s, per):
            x, nn = X[start:start + per], nrm[start:start + per]
            ray = dr.arange(mi.UInt32, len(x) * G)
            sample, point = ray // G, ray % G
            xs = [dr.gather(F64, F64(np.ascontiguousarray(x[:, a])), sample) for a in range(3)]
            ns = [dr.gather(F64, F64(np.ascontiguousarray(nn[:, a])), sample) for a in range(3)]
            ps = [dr.gather(F64, panel[a], point) for a in range(3)]
            d = [p - q for p, q in zip(ps, xs)]                    # sample -> panel point
            r = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            cos_s = (d[0] * ns[0] + d[1] * ns[1] + d[2] * ns[2]) / r
            cos_l = -(d[0] * n_l[0] + d[1] * n_l[1] + d[2] * n_l[2]) / r
            front = (cos_s > 0) & (cos_l > 0)
            origin = [q + EPSILON * n for q, n in zip(xs, ns)]
            seg = [p - o for p, o in zip(ps, origin)]
            dist = dr.sqrt(seg[0] * seg[0] + seg[1] * seg[1] + seg[2] * seg[2])
            shadow = mi.Ray3f(mi.Point3f(*(mi.Float(o) for o in origin)),
                              mi.Vector3f(*(mi.Float(s / dist) for s in seg)))
            shadow.maxt = mi.Float(dr.maximum(dist - EPSILON, 0.0))
            clear = front & ~scene.ray_test(shadow, front)
            lit[k, start:start + per] = dr.block_sum(dr.select(clear, F64(1.0), F64(0.0)), G).numpy() / G
            direct[k, start:start + per] = light.radiance * dA * dr.block_sum(
                dr.select(clear, cos_s * cos_l / (r * r), F64(0.0)), G).numpy()
    return lit, direct


# --------------------------------------------------------------------------------------------
# Photometry
# --------------------------------------------------------------------------------------------
def pattern_stats(pattern: np.ndarray) -> tuple[float, float]:
    """(mean f, std f) of a [0, 1] pattern (1 = white), over the whole tile."""
    f = np.asarray(pattern, dtype=np.float64)
    return float(f.mean()), float(f.std())


@dataclass(frozen=True, eq=False)
class Photometry:
    """Image level, contrast and noise per (camera, sample), all (C, N), in DN (module docstring):
    image = brightness + contrast f̂ + noise of std `noise`; `linear` (N,) is the renderer's mean
    linear value <ρ> E / π."""

    brightness: np.ndarray
    contrast: np.ndarray
    noise: np.ndarray
    linear: np.ndarray


def exposure_factors(camera_specs, sensor: SensorModel) -> np.ndarray:
    """(C,) k_c = (t_c / t_ref) (8 / N_c)^2 of each [[camera]] spec: the light it gathers against
    the sensor's reference exposure t_ref ([sensor] exposure_ms at f/8;
    `vdo.model.optics.exposure_factor`; no f_number: f/8, no exposure_ms: t_ref)."""
    return np.array([exposure_factor(s.f_number, s.exposure_time, sensor.exposure_ms * 1e-3)
                     for s in camera_specs], dtype=float)


def photometry(illumination: Illumination, speckle: SpeckleSpec, sensor: SensorModel,
               pattern_mean: float, pattern_std: float, n_cameras: int,
               exposure: np.ndarray | None = None) -> Photometry:
    """b, c and σ (DN) at every sample for each of `n_cameras` cameras, from the irradiance E:
    b = sensor.mean_dn(k <ρ> E/π), c = K QE p (ρ_w - ρ_b) std(f) k E/π,
    σ = sensor.noise_sigma_dn(k <ρ> E/π) with <ρ> = ρ_b + (ρ_w - ρ_b) mean(f), K QE p the
    sensor's DN per unit linear value and k (C,) the cameras' `exposure` factors
    (`exposure_factors`; None: 1). `linear` is <ρ> E/π at k = 1."""
    E = illumination.irradiance
    rho_b, rho_w = speckle.black_albedo, speckle.white_albedo
    mean_rho = rho_b + (rho_w - rho_b) * pattern_mean
    linear = mean_rho * E / np.pi
    dn_per_unit = sensor.dn_per_unit
    k = np.ones((n_cameras, 1)) if exposure is None else np.asarray(exposure, float).reshape(-1, 1)
    shape = (n_cameras, len(E))
    return Photometry(
        brightness=np.broadcast_to(sensor.mean_dn(k * linear), shape).copy(),
        contrast=np.broadcast_to(dn_per_unit * (rho_w - rho_b) * pattern_std * k * E / np.pi,
                                 shape).copy(),
        noise=np.broadcast_to(sensor.noise_sigma_dn(k * linear), shape).copy(),
        linear=linear)
