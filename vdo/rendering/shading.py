"""The light each hit reflects towards the camera in the DIC render mode (`vdo.rendering.dic`), by
quadrature: the lights' panels (probed by shadow rays, then a Gauss rule where lit, the midpoints
where partly shadowed) and the ambient sky (docs/render.md, "The DIC render mode"). `dscene` is a
`vdo.rendering.dic.DicScene`; a hit is Mitsuba's SurfaceInteraction."""

from __future__ import annotations

import numpy as np

__all__ = ["LIGHT_POINTS", "PROBE_GRID", "LIT_POINTS", "AMBIENT_POINTS", "SHADE_LANES", "quadrature", "shade"]

LIGHT_POINTS = 8             # midpoint rule of LIGHT_POINTS^2 points on each light panel (a
                             # penumbra moves in steps of 1 / LIGHT_POINTS^2 of the panel)
PROBE_GRID = (0, 2, 5, 7)    # the rows and columns of each panel's points probed first: a shadow
                             # ray per point only where the front probes disagree (a straight
                             # shadow edge across the panel always splits them; a strip thinner
                             # than the probes' gaps can pass between them)
LIT_POINTS = 4               # a panel whose probes are all in front of the hit and all visible (lit)
                             # takes LIT_POINTS^2 Gauss-Legendre points instead (no shadow rays;
                             # the integrand is smooth there). On the built-in's cam1, against a
                             # 24 x 24 Gauss rule: 7e-8 of the light scale on average (max 2e-5),
                             # the 8 x 8 midpoints 1e-4 (max 4e-4)
AMBIENT_POINTS = 8           # AMBIENT_POINTS^2 BSDF-sampled directions for the ambient sky
SHADE_LANES = 1 << 19        # (hit, light point) pairs per shadow-ray batch (memory bound)


_QUADRATURES: dict = {}


def quadrature(dscene, rule: str = "midpoint"):
    """The lights' quadrature: points P (Q, 3), panel normals (Q, 3) and weights (Q,) L A w_a w_b,
    per panel the LIGHT_POINTS^2 midpoints (w = 1 / LIGHT_POINTS each way) or, with rule
    "gauss", the LIT_POINTS^2 Gauss-Legendre points on the panel's [-1/2, 1/2]^2. Kept for the
    last lights asked (a render shades some thirty batches under the same lights)."""
    key = (id(dscene.lights), rule)
    kept = _QUADRATURES.get(key)
    if kept is not None and kept[0] is dscene.lights:
        return kept[1]
    if len(_QUADRATURES) > 8:
        _QUADRATURES.clear()
    out = _quadrature(dscene.lights, rule)
    _QUADRATURES[key] = (dscene.lights, out)
    return out


def _quadrature(lights, rule: str):
    if rule == "gauss":
        x, w = np.polynomial.legendre.leggauss(LIT_POINTS)
        mid, w = x / 2, w / 2
    else:
        mid = (np.arange(LIGHT_POINTS) + 0.5) / LIGHT_POINTS - 0.5
        w = np.full(LIGHT_POINTS, 1.0 / LIGHT_POINTS)
    a, b = (t.ravel()[:, None] for t in np.meshgrid(mid, mid, indexing="ij"))
    wab = np.outer(w, w).ravel()
    P, N, W = [], [], []
    for c, e1, e2, normal, radiance in lights:
        P.append(c + a * e1 + b * e2)
        N.append(np.broadcast_to(normal, (len(wab), 3)))
        W.append(radiance * float(np.linalg.norm(np.cross(e1, e2))) * wab)
    if not P:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(P), np.concatenate(N), np.concatenate(W)


def shade(dscene, si) -> np.ndarray:
    """The light reflected towards the camera at each hit ((n,) float64, luminance), the integral
    of the sampled mode's estimator (`vdo.rendering.scene`'s `vdo_panels` integrator) by
    quadrature: Σ over lights and the LIGHT_POINTS^2 midpoints P of each panel of f(ω_i, ω_o)
    cosθ_s L cosθ_l (A / LIGHT_POINTS^2) / r^2 where P is visible (shadow ray), plus the ambient
    sky through AMBIENT_POINTS^2 stratum-centre BSDF samples that escape. 0 where the ray missed.
    First the panel's PROBE_GRID^2 probe points: a panel whose probes are all in front of the hit
    and visible is lit, and is integrated by LIT_POINTS^2 Gauss-Legendre points instead (the same
    integral, no shadow rays); one with no probe both in front and visible adds nothing (its
    corners are probes: a panel behind the hit's tangent plane, or a straight shadow edge leaves
    it dark); otherwise the midpoints, with the shadow rays cast only where the front probes
    disagree (where they agree, every point in front takes their answer). The hits go in batches
    of at most SHADE_LANES / (probes + ambient directions) (small kernels, compiled once)."""
    import drjit as dr

    from vdo.core.backend import mitsuba

    mi = mitsuba()
    n = dr.width(si)
    dr.eval(si)
    P, normals, weights = quadrature(dscene)
    m = AMBIENT_POINTS if dscene.ambient > 0 else 0
    mid = (np.arange(m) + 0.5) / max(m, 1)
    samples = np.stack(np.meshgrid(mid, mid), -1).reshape(-1, 2)
    Q = len(P) + len(samples)
    out = np.zeros(n)
    if Q == 0:
        return out
    table = [mi.Point3f(*(np.ascontiguousarray(x[:, k]) for k in range(3))) for x in (P, normals)]
    per_point = LIGHT_POINTS * LIGHT_POINTS                      # quadrature points a panel
    panels = len(P) // per_point
    grid = np.array(PROBE_GRID)
    probes = (np.arange(panels)[:, None] * per_point
              + (grid[:, None] * LIGHT_POINTS + grid[None, :]).ravel()[None, :]).ravel()
    per_panel = len(grid) ** 2
    probe_index = mi.UInt32(probes.astype(np.uint32))
    w_light = mi.Float(weights) if len(P) else None
    if len(P):
        G, G_normals, G_weights = quadrature(dscene, "gauss")
        gauss = ([mi.Point3f(*(np.ascontiguousarray(x[:, k]) for k in range(3))) for x in (G, G_normals)],
                 mi.Float(G_weights), LIT_POINTS * LIT_POINTS)
    S = mi.Point2f(*(np.ascontiguousarray(samples[:, k]) for k in range(2))) if m else None
    ctx = mi.BSDFContext()
    chunk = max(1, SHADE_LANES // Q)
    for start in range(0, n, chunk):
        count = min(chunk, n - start)
        total = mi.Float(0.0)
        if len(P):
            # The probes: PROBE_GRID^2 of each panel's midpoints, a shadow ray each.
            lane = dr.arange(mi.UInt32, count * len(probes))
            hit = dr.gather(type(si), si, start + lane // len(probes))
            k = dr.gather(mi.UInt32, probe_index, lane % len(probes))
            point, normal = (dr.gather(mi.Point3f, t, k) for t in table)
            d = dr.normalize(point - hit.p)
            front = hit.is_valid() & (-dr.dot(d, mi.Vector3f(normal)) > 0) & (dr.dot(d, hit.n) > 0)
            seen = front & ~dscene.shadows.ray_test(hit.spawn_ray_to(point), front)
            n_front = dr.block_sum(mi.Float(dr.select(front, 1.0, 0.0)), per_panel)
            n_seen = dr.block_sum(mi.Float(dr.select(seen, 1.0, 0.0)), per_panel)
            # Lit: every probe in front and visible: LIT_POINTS^2 Gauss-Legendre points without
            # shadow rays. Mixed (some probe in front and visible, not all): the midpoints, a
            # shadow ray each where the front probes disagree. The rest (no probe in front or
            # none visible: the corners are probes) adds nothing.
            lit = n_seen == per_panel
            mixed = (n_seen > 0) & ~lit
            total = dr.zeros(mi.Float, count)
            for which, (quad_table, quad_w, points) in ((lit, gauss), (mixed, (table, w_light, per_point))):
                pairs = dr.compress(which)
                if dr.width(pairs) == 0:
                    continue
                lane = dr.arange(mi.UInt32, dr.width(pairs) * points)
                pair = dr.gather(mi.UInt32, pairs, lane // points)
                local = pair // panels
                hit = dr.gather(type(si), si, start + local)
                k = (pair % panels) * points + lane % points
                point, normal = (dr.gather(mi.Point3f, t, k) for t in quad_table)
                d = point - hit.p
                dist2 = dr.squared_norm(d)
                d = d * dr.rsqrt(dist2)
                cos_l = -dr.dot(d, mi.Vector3f(normal))
                ok = hit.is_valid() & (cos_l > 0) & (dr.dot(d, hit.n) > 0)
                if points == per_point:
                    test = ok & (dr.gather(mi.Float, n_seen, pair) != dr.gather(mi.Float, n_front, pair))
                    ok &= ~(test & dscene.shadows.ray_test(hit.spawn_ray_to(point), test))
                f = hit.bsdf().eval(ctx, hit, hit.to_local(d), ok)
                value = mi.luminance(dr.select(ok, f * (dr.gather(mi.Float, quad_w, k) * cos_l / dist2), 0.0))
                dr.scatter_reduce(dr.ReduceOp.Add, total, value, local)
        if m:
            lane = dr.arange(mi.UInt32, count * len(samples))
            hit = dr.gather(type(si), si, start + lane // len(samples))
            valid = hit.is_valid()
            bs, w = hit.bsdf().sample(ctx, hit, 0.5, dr.gather(mi.Point2f, S, lane % len(samples)), valid)
            ok = valid & (bs.pdf > 0)
            ok &= ~dscene.shadows.ray_test(hit.spawn_ray(hit.to_world(bs.wo)), ok)
            value = mi.luminance(dr.select(ok, w * dr.opaque(mi.Float, dscene.ambient / len(samples)), 0.0))
            total = total + dr.block_sum(value, len(samples))
        out[start:start + count] = np.array(total, dtype=np.float64)
    return out
