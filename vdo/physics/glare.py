"""Glare: the specular part of a satin finish, and the hot-spot check per camera and region.

Finish. A [[mesh]]'s `finish` is "matte" (default: Lambertian paint, `vdo.physics.lighting`) or
"satin": the paint under a smooth dielectric coat, whose specular lobe is a rough-dielectric
microfacet reflection (what Mitsuba's `roughplastic` adds to its diffuse base, and what
`vdo.render` gives satin regions):

    f_s(w_i, w_o) = F(w_i . h) D(h) G1(w_i) G1(w_o) / (4 cos_i cos_o)        [1/sr]

h = (w_i + w_o) / |w_i + w_o|, D the GGX (Trowbridge-Reitz) distribution of roughness alpha =
SATIN_ALPHA, G1 its Smith masking, F the exact dielectric Fresnel reflectance at index SATIN_IOR.

Specular radiance toward camera c at sample X (normal n) from a light panel (`panel_points`):

    L_s(X -> c) = sum_j lit L f_s(w_j, w_c) cos_s cos_l / r_j^2 dA         [radiance unit]

the irradiance's own midpoint rule (`vdo.physics.lighting`) weighted by the lobe, with the panel's
visible fraction `lit` standing for the shadow rays (a panel seen in part dims its reflection in
proportion).

Hot spots. The sensor sees the white paint at rho_w E / pi + L_s. A sample is a hot spot for a
camera when that saturates the sensor (`SensorModel.saturation_linear`), or when the reflection
outshines the speckle's own contrast, L_s > (rho_w - rho_b) E / pi (washed out: the exposure that
keeps the reflection below saturation leaves the pattern less than half its range). The check
gives per (camera, region) the area fraction of its seen samples that are hot spots and flags it
above HOT_SPOT_FRACTION.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from vdo.physics.lighting import panel_frame, panel_points

if TYPE_CHECKING:
    from vdo.config.rig import LightSpec, MeshSpec, RegionSpec, SpeckleSpec
    from vdo.model.sensor import SensorModel

SATIN_ALPHA = 0.1      # GGX roughness of a satin coat (semi-gloss: a lobe of about 6 deg)
SATIN_IOR = 1.5        # refractive index of the coat (clear lacquer)
HOT_SPOT_FRACTION = 0.01   # flag a camera-region pair when more than this area fraction is a hot spot


def fresnel(cos_i, eta: float = SATIN_IOR):
    """Unpolarised reflectance of a dielectric interface at incidence cosine cos_i (from outside,
    relative index eta)."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (1 - cos_i ** 2) / eta ** 2
    cos_t = np.sqrt(np.maximum(1 - sin_t2, 0.0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (rs * rs + rp * rp)


def ggx(cos_h, alpha: float = SATIN_ALPHA):
    """GGX normal distribution D(h) (1/sr) at cos_h = n . h."""
    c2 = cos_h * cos_h
    return np.where(cos_h > 0, alpha ** 2 / (np.pi * (c2 * (alpha ** 2 - 1) + 1) ** 2), 0.0)


def smith_g1(cos_v, alpha: float = SATIN_ALPHA):
    """Smith masking of GGX for a direction of cosine cos_v to the normal."""
    c2 = np.clip(cos_v * cos_v, 1e-12, 1.0)
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha ** 2 * (1 - c2) / c2))


def lobe(n, wi, wo, alpha: float = SATIN_ALPHA, eta: float = SATIN_IOR):
    """f_s(w_i, w_o) (1/sr) of the module docstring; n, wi, wo (..., 3) unit vectors (wi toward the
    light, wo toward the camera); 0 unless both lie above the surface."""
    ci, co = (wi * n).sum(-1), (wo * n).sum(-1)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    f = fresnel((wi * h).sum(-1), eta) * ggx((h * n).sum(-1), alpha) \
        * smith_g1(ci, alpha) * smith_g1(co, alpha) / (4 * np.maximum(ci * co, 1e-12))
    return np.where((ci > 0) & (co > 0), f, 0.0)


def specular_radiance(lights, lit, points, normals, camera_positions) -> np.ndarray:
    """(C, N) specular radiance L_s of a satin finish toward each camera (module docstring);
    lit (L, N) the panels' visible fractions (`Illumination.lit`)."""
    X, n = np.asarray(points, float), np.asarray(normals, float)
    out = np.zeros((len(camera_positions), len(X)))
    for c, C in enumerate(np.asarray(camera_positions, float)):
        wo = C - X
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        for k, light in enumerate(lights):
            P, dA = panel_points(light)
            n_l = panel_frame(light)[0]
            for p in P:
                d = p - X
                r = np.linalg.norm(d, axis=1)
                wi = d / r[:, None]
                cos_s, cos_l = (wi * n).sum(1), -(wi @ n_l)
                g = np.where((cos_s > 0) & (cos_l > 0), cos_s * cos_l / r ** 2, 0.0)
                out[c] += lit[k] * light.radiance * dA * lobe(n, wi, wo) * g
    return out


def satin_samples(meshes: tuple[MeshSpec, ...], regions: tuple[RegionSpec, ...],
                  samples) -> np.ndarray:
    """(N,) True for the samples of regions on a [[mesh]] with finish = "satin" (`meshes` and
    `regions` the experiment's [[mesh]] and [[region]] tables)."""
    finish = {m.name: m.finish for m in meshes}
    satin = np.array([finish.get(r.mesh) == "satin" for r in regions])
    return satin[samples.region] if len(satin) else np.zeros(len(samples.region), bool)


def hot_spot_kinds(Ls, E, exposure, speckle: SpeckleSpec, sensor: SensorModel):
    """(saturated, washed), each (C, S) bool, of the module docstring's hot spots: per camera c
    and sample s of irradiance E (S,) and specular radiance Ls (C, S), saturated when
    k_c (rho_w E / pi + Ls) reaches `SensorModel.saturation_linear` (k (C,) the light each camera
    gathers, `exposure`; None: 1), washed out when Ls > (rho_w - rho_b) E / pi."""
    k = np.ones((len(Ls), 1)) if exposure is None else np.asarray(exposure, float)[:, None]
    saturated = k * (speckle.white_albedo * E / np.pi + Ls) >= sensor.saturation_linear()
    return saturated, Ls > (speckle.white_albedo - speckle.black_albedo) * E / np.pi


def hot_spots(meshes: tuple[MeshSpec, ...], regions: tuple[RegionSpec, ...],
              lights: tuple[LightSpec, ...], speckle: SpeckleSpec, sensor: SensorModel,
              cameras, samples, visible, illumination, exposure=None) -> list[dict]:
    """The hot-spot check (module docstring): one row per (camera, satin region) with seen samples,
    {"camera", "region", "hot_spot_fraction", "saturated_fraction", "max_specular_ratio", "flags"};
    max_specular_ratio the largest L_s / ((rho_w - rho_b) E / pi) over the seen samples. The
    tables: [[mesh]] and [[region]] (which are satin, `satin_samples`), [[light]], [speckle] (the
    paint's albedos) and [sensor]; `exposure` (C,) the light each camera gathers
    (`vdo.physics.lighting.exposure_factors`; None: the sensor's reference), which scales what
    saturates."""
    satin = satin_samples(meshes, regions, samples)
    if not satin.any() or not cameras:
        return []
    idx = np.flatnonzero(satin)
    E = illumination.irradiance[idx]
    Ls = specular_radiance(lights, illumination.lit[:, idx], samples.points[idx], samples.normals[idx],
                           [c.position for c in cameras])
    saturated, washed = hot_spot_kinds(Ls, E, exposure, speckle, sensor)
    contrast = (speckle.white_albedo - speckle.black_albedo) * E / np.pi
    ratio = Ls / np.maximum(contrast[None], 1e-300)
    rows = []
    for c, cam in enumerate(cameras):
        for k, region in enumerate(samples.region_names):
            seen = np.asarray(visible[c])[idx] & (samples.region[idx] == k)
            if not seen.any():
                continue
            a = samples.area[idx][seen]
            hot = float(a[(saturated[c] | washed[c])[seen]].sum() / a.sum())
            flags = []
            if hot > HOT_SPOT_FRACTION:
                flags.append(f"specular hot spot: {100 * hot:.1f} % of {region} saturated or washed out "
                             f"by a light's reflection (move the light or the camera off the mirror "
                             f"direction, or use a matte finish)")
            rows.append({"camera": cam.name, "region": region, "hot_spot_fraction": hot,
                         "saturated_fraction": float(a[saturated[c][seen]].sum() / a.sum()),
                         "max_specular_ratio": float(ratio[c][seen].max()), "flags": flags})
    return rows
