"""The per-pair block and its sums: for each listed pair (`vdo.information.views.ViewData`),
the 6 entries of Omega w |det A| C_i = k S^T T S (1/m^2, k = Omega w |det A| c^2 / sigma^2,
S the sensitivity, T the gradient tensor per unit contrast) and the weight w, summed per sample
(`sample_sums`, `per_sample`), with the score's gradient with respect to the cameras written out
by hand (`block_vjp`). `vdo.objective` builds the information, the sigma fields and the score on
these sums.

Reverse pass (`block_vjp`). The score's gradient with respect to the cameras is written out by
hand for the per-pair block: for per-pair cotangents Q (the symmetric 3x3 of the 6 entries, off-
diagonals halved) and c_w, L = k tr(T Y) + c_w w with Y = S Q S^T, so dL/dk = tr(T Y),
dL/dT = k Y, dL/dS = 2 k T S Q, then back through T = alpha I + beta (M - m I), the floored-gap
eigenvalues, the footprint, the soft weights and the projection to the camera, summed over each
camera-major block. For the rotation only its skew part is summed: R stays a rotation (dR = W R,
W skew), so dL/dR counts through the 3 entries of M - M^T, M = dL/dR R^T, and the block's dL/dR
is returned as S R with S = (M - M^T)/2 (the same derivative along every rotation, hence the same
pan, tilt and roll gradients). Width and height are pixel counts, not differentiated. Only the
cameras are differentiated: samples, view data and the energy are constants (zero cotangents).

How it runs on XLA:CPU (`sample_sums`, measured on 10 cameras x 100k samples, 2 cores;
figures in `benchmarks/README.md`). Both passes go over the pair list in chunks of `ViewData.chunk`
blocks (~32k pairs, `lax.map`), the reverse pass recomputing the forward. Within a chunk, values
used by several later steps are materialised (`materialise`): XLA:CPU duplicates cheap elementwise
producers into every consumer fusion, so without it each of the ~20 loops that end in a camera
column re-derived the forward chain (5,000 operations per pair in the reverse pass, 2,100 with
it). Materialising costs memory traffic, hence the chunks, which keep it in cache. Other facts
behind the code: reading an array with a stride (the columns of a (pairs, 7) gather of the
per-sample cotangents) stops vectorisation, so each of the 7 is gathered on its own (1.2x on
value + gradient); the block sums are one batched dot with ones (separate row sums: ~15 %
slower); a variadic `lax.reduce` compiles to scalar code (~7x slower); gathers inside the
per-pair chain (a sample-major layout) stop vectorisation (~4x slower forward). Each call's
temporaries (~130 MB before the chunks) come from malloc, and glibc maps and unmaps blocks that
large on every call: `vdo.core.memory.retain_freed_memory` keeps them in the heap instead (58 -> 47
ms per value + gradient).

Precision (`Settings.pair_dtype`). The per-pair work (projection, footprint, spectrum, table
lookup, weights and their reverse) can run in float32: f32 exp/log are ~5x faster than f64 on
XLA:CPU and AVX2 holds 8 f32 lanes against 4. The 6 entries k S^T T S (and their reverse,
Y and dL/dS) are assembled in float64 from the rounded S in either case, so that each pair's
matrix keeps the ray as its null vector to f64 precision: float32 rounding of the entries
leaves ~1e-7 |C_i| along the ray, far above the prior 1/prior_sigma^2 that alone fixes that
direction for a sample seen by one camera (it made sigma NaN there). Per-sample sums and the
score are float64. Measured on 10 cameras x 100k samples: value within ~4e-8 and gradient
within ~1e-5 (max |diff| / max |g|) of float64. The default stays float64 (the finite-
difference tests need it); `vdo.physics.predict.settings`, and so the optimizer, uses float32; the reports
(`vdo.objective.fields`, `information`, `camera_information`) always run float64.

Above `vdo.information.inputs`, `projection`, `tensor` and `views`; below `vdo.objective`."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from vdo.information.projection import (CAM_F, CAM_R, CAM_W, camera_table, dot, pairs_from,
                                        smoothstep, smoothstep_grad, weight_scales)
from vdo.information.tensor import phis_of, spectrum, tensor_from
from vdo.information.views import ViewData
from vdo.model.camera import distortion_curvature


@jax.custom_jvp
def materialise(x, one):
    """x, materialised: the identity x / one with `one` a per-element runtime 1.0 (an array, as
    XLA rewrites a division by a broadcast scalar into a multiplication). XLA:CPU duplicates cheap
    elementwise producers into every consumer fusion but not divisions, so this stores x once
    (forward) and, by the JVP rule, its cotangent once (backward); with a single consumer it is
    fused all the same. `lax.optimization_barrier` does not do this on CPU (it is removed before
    fusion). Where it pays: module docstring, "How it runs on XLA:CPU"."""
    return jax.tree.map(lambda a: a / one, x)


@materialise.defjvp
def _materialise_jvp(primals, tangents):
    x, one = primals
    tx, _ = tangents
    return materialise(x, one), jax.tree.map(lambda a: a / one, tx)


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # order of the 6 unique entries


def _f64(x):
    return jax.tree.map(lambda a: a.astype(jnp.float64), x)


def block_columns(ctab, dtype):
    """(B, 17) camera rows (22 with distortion) -> as many (B, 1) columns in the pair dtype."""
    return [ctab[:, k].astype(dtype)[:, None] for k in range(ctab.shape[1])]


def block_forward(cq, sq, occ, kc, one, energy, st, jacobian=False):
    """Per pair, from broadcastable components (cq the 17 camera columns, sq the 12 sample
    columns, occlusion, kc = Omega c^2 / sigma^2 in m^2, `one` a runtime 1.0 for `materialise`): ent,
    the 6 entries of k S^T T S in _SYM order (1/m^2, float64), with
    k = Omega w |det A| c^2/sigma^2 = kc w |det A|, and w (occlusion included); and the
    intermediates (geometry, spectrum, phis, T, beta, lam1 - lam2, k, and with `jacobian` the
    table lookup's d phi_i / d lam_j, else None)."""
    keep = lambda x: materialise(x, one)
    geo = pairs_from(cq, sq, st)
    w = geo.w * occ
    s0, s1, A, w = keep((geo.s0, geo.s1, geo.A, w))
    geo = geo._replace(s0=s0, s1=s1, A=A)
    sp = spectrum(geo.A, st.gap_eps)
    phis, jac = phis_of(energy, sp.lam1, sp.lam2, st.kappa, jacobian)
    T, beta, D = tensor_from(sp, *phis)
    *T, absdet = keep(T + (jnp.abs(sp.det),))
    # rooted at a divide: XLA:CPU materialises k once instead of re-deriving the weight chain
    # in every consumer fusion
    k = keep(kc * w * absdet)
    # the assembly k S^T T S runs in float64 whatever the pair dtype: each pair's matrix then
    # has the ray as its null vector to float64 precision (float32 rounding of the 6 entries
    # would leave an error ~1e-7 |C_i| along the ray, far above the prior 1/prior_sigma^2 that
    # alone measures that direction for a sample seen by one camera)
    s0, s1, (T00, T01, T11), k = _f64((geo.s0, geo.s1, tuple(T), k))
    k00, k01, k11 = k * T00, k * T01, k * T11
    ent = tuple(k00 * s0[a] * s0[b] + k11 * s1[a] * s1[b] + k01 * (s0[a] * s1[b] + s1[a] * s0[b])
                for a, b in _SYM)
    return ent, w, (geo, sp, phis, tuple(T), beta, D, k, jac)


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8, 9))
def sample_sums(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n):
    """Per-sample sums over the listed pairs of ent (6 entries) and of w: 7 arrays (n,) (float64).

    ctab (B, 17) (22 with distortion) is the camera row of each block (float64); geometry the
    12 sample columns, occ, kc, one and sample (B, block) per pair, in the pair dtype; B a
    multiple of `chunk`. The per-pair work (`block_forward`) runs over chunks of `chunk` blocks
    (`_chunked`).
    Differentiable with respect to ctab only (the other inputs are constants), by the
    hand-written `block_vjp`, which recomputes the forward chunk by chunk."""
    dt = occ.dtype

    def forward(ctab, geometry, occ, kc, one):
        ent, w, _ = block_forward(block_columns(ctab, dt), geometry, occ, kc, one, energy, st)
        return ent, w

    ent, w = _chunked(forward, (ctab, geometry, occ, kc, one), chunk)
    return tuple(per_sample(x, sample, n) for x in ent + (w,))


def _sample_sums_fwd(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n):
    sums = sample_sums(ctab, geometry, occ, kc, one, sample, energy, st, chunk, n)
    return sums, (ctab, geometry, occ, kc, one, sample, energy)


def _sample_sums_bwd(st, chunk, n, res, ct):
    ctab, geometry, occ, kc, one, sample, energy = res
    dt = occ.dtype

    def reverse(ctab, geometry, occ, kc, one, sample):
        c = [jnp.take(x, sample, mode="clip") for x in ct]
        return block_vjp(ctab, geometry, occ, kc, one, tuple(c[:6]), c[6].astype(dt), energy, st)

    g = _chunked(reverse, (ctab, geometry, occ, kc, one, sample), chunk)
    return g, None, None, None, None, None, None


sample_sums.defvjp(_sample_sums_fwd, _sample_sums_bwd)


def _chunked(fun, args, chunk):
    """fun(*args) for arrays whose leading axis is the B blocks, evaluated on chunks of `chunk`
    blocks in sequence (`lax.map`): the intermediates it materialises then stay in cache
    (measured 1.1-1.3x faster than one pass over all blocks)."""
    B = jax.tree.leaves(args)[0].shape[0]
    out = jax.lax.map(lambda x: fun(*x),
                      jax.tree.map(lambda x: x.reshape((B // chunk, chunk) + x.shape[1:]), args))
    return jax.tree.map(lambda x: x.reshape((B,) + x.shape[2:]), out)


def block_vjp(ctab, sq, occ, kc, one, c_ent, c_w, energy, st):
    """Cotangent of the (B, 17) (or 22) block camera rows ctab for per-pair cotangents c_ent
    (6, float64) of ent and c_w of w, written out by hand (module docstring, "Reverse pass").

    With Q the symmetric 3x3 of c_ent (off-diagonals halved), L = k tr(T Y) + c_w w with
    Y = S Q S^T: dL/dk = tr(T Y), dL/dT = k Y (dL/dT01 = 2 k Y01), dL/ds0 = 2k (T00 Q s0 + T01 Q s1)
    and dL/ds1 likewise; then back through the spectrum, the footprint, the weights and the
    projection to the camera columns, summed over each block (one camera per block): for R
    (9 columns) its rotation part only, R's skew cotangent S R; position, f, cx, cy; width and
    height are pixel counts, not differentiated (0). The
    forward is recomputed, with the table lookup's Jacobian d phi_i / d lam_j.

    Values used by several later steps are materialised (`materialise`), and `sample_sums` runs this
    on chunks that fit in cache (module docstring, "How it runs on XLA:CPU")."""
    keep = lambda x: materialise(x, one)
    cq = block_columns(ctab, sq[0].dtype)
    _, w, (geo, sp, _, T, beta, D, k, jac) = block_forward(cq, sq, occ, kc, one, energy, st,
                                                           jacobian=True)
    xn, yn, iz, g, p, d, rd, cos_inc, t_inc, t_img = keep(
        (geo.xn, geo.yn, geo.iz, geo.g, geo.p, geo.d, geo.rd, geo.cos_inc, geo.t_inc, geo.t_img))
    geo = geo._replace(xn=xn, yn=yn, iz=iz, g=g, p=p, d=d, rd=rd, cos_inc=cos_inc, t_inc=t_inc,
                       t_img=t_img)
    j11, j12, j21, j22 = jac
    s0, s1, (T00, T01, T11), k = _f64((geo.s0, geo.s1, T, k))
    c00, c11, c22, c01, c02, c12 = c_ent
    Q = ((c00, 0.5 * c01, 0.5 * c02), (0.5 * c01, c11, 0.5 * c12), (0.5 * c02, 0.5 * c12, c22))
    q0 = tuple(dot(Q[a], s0) for a in range(3))
    q1 = tuple(dot(Q[a], s1) for a in range(3))
    Y00, Y11, Y01 = dot(s0, q0), dot(s1, q1), dot(s0, q1)
    tau = T00 * Y00 + T11 * Y11 + 2.0 * T01 * Y01  # dL/dk
    g_s0 = [2.0 * k * (T00 * q0[b] + T01 * q1[b]) for b in range(3)]
    g_s1 = [2.0 * k * (T11 * q1[b] + T01 * q0[b]) for b in range(3)]
    g_T00, g_T11, g_T01 = k * Y00, k * Y11, 2.0 * k * Y01
    # from here on in the pair dtype
    dt = sq[0].dtype
    tau, g_s0, g_s1, g_T00, g_T11, g_T01, c_w = keep(jax.tree.map(
        lambda a: a.astype(dt), (tau, g_s0, g_s1, g_T00, g_T11, g_T01, c_w)))
    absdet = jnp.abs(sp.det)
    g_w = c_w + tau * kc * absdet
    g_absdet = tau * kc * w
    # T = alpha I + beta (M - m I), alpha = (phi1 + phi2)/2, beta = (phi1 - phi2)/D
    g_alpha = g_T00 + g_T11
    g_beta = (g_T00 - g_T11) * sp.h + g_T01 * sp.M01
    g_h = (g_T00 - g_T11) * beta
    g_M01 = g_T01 * beta
    g_phi1 = 0.5 * g_alpha + g_beta / D
    g_phi2 = 0.5 * g_alpha - g_beta / D
    g_D = -g_beta * beta / D
    g_lam1 = g_D + g_phi1 * j11 + g_phi2 * j21
    g_lam2 = -g_D + g_phi1 * j12 + g_phi2 * j22
    # lam2 = max(det^2 / lam1, 1e-12 lam1), lam1 = m + gap, gap = sqrt(h^2 + M01^2 + (eps m)^2)
    unfloored = sp.q > 1e-12 * sp.lam1
    g_q = jnp.where(unfloored, g_lam2, 0.0)
    g_lam1 = g_lam1 + jnp.where(unfloored, 0.0, 1e-12 * g_lam2) - g_q * sp.q / sp.lam1
    g_det = g_q * 2.0 * sp.det / sp.lam1 + g_absdet * jnp.sign(sp.det)
    g_gap = g_lam1 / sp.gap
    g_h = g_h + g_gap * sp.h
    g_M01 = g_M01 + g_gap * sp.M01
    g_m = jnp.where(sp.m_raw > jnp.finfo(sp.m.dtype).tiny,
                    g_lam1 + g_gap * (st.gap_eps ** 2) * sp.m, 0.0)
    g_M00 = 0.5 * (g_m + g_h)
    g_M11 = 0.5 * (g_m - g_h)
    A00, A01, A10, A11 = geo.A
    g_A = (2.0 * A00 * g_M00 + A10 * g_M01 + A11 * g_det,
           2.0 * A01 * g_M00 + A11 * g_M01 - A10 * g_det,
           2.0 * A10 * g_M11 + A00 * g_M01 - A01 * g_det,
           2.0 * A11 * g_M11 + A01 * g_M01 + A00 * g_det)
    tu, tv = sq[6:9], sq[9:12]
    g_A = keep(g_A)
    g_s0, g_s1 = keep(([g_s0[b] + g_A[0] * tu[b] + g_A[1] * tv[b] for b in range(3)],
                       [g_s1[b] + g_A[2] * tu[b] + g_A[3] * tv[b] for b in range(3)]))
    # weights: w = [front] S(t_inc) S(t_1) S(t_2) S(t_3) S(t_4) occ, S' = 30 t^2 (1 - t)^2
    g_raw = jnp.where(geo.front, g_w * occ, 0.0)
    ts = (geo.t_inc,) + geo.t_img
    S = keep([smoothstep(t) for t in ts])
    dS = keep([smoothstep_grad(t) for t in ts])
    prod = lambda xs: functools.reduce(lambda a, b: a * b, xs)
    g_t = keep([g_raw * dS[i] * prod(S[:i] + S[i + 1:]) for i in range(5)])
    _, inc_scale, mg = weight_scales(st)
    g_cos = g_t[0] * inc_scale
    g_u, g_v = mg * (g_t[1] - g_t[2]), mg * (g_t[3] - g_t[4])
    # projection: s0 = g (R0 - xn R2), s1 = g (R1 - yn R2), g = f iz, u = f xn + cx, v = f yn + cy
    R = [cq[3 * a:3 * a + 3] for a in range(3)]
    f = cq[CAM_F]
    if geo.lens is not None:
        # s0 = g (a e0 + b e1), s1 = g (b e0 + d e1), e0 = R0 - xn R2, e1 = R1 - yn R2, D = [[a, b],
        # [b, d]] a function of (xn, yn), u = f x_d + cx, v = f y_d + cy: the pinhole chain below
        # with the cotangents D (g_s0, g_s1) of e0/g, e1/g, plus D's and (x_d, y_d)'s own
        # dependence on (xn, yn) (`vdo.model.camera.distortion_curvature`)
        coefficients, xd, yd, (jxx, jxy, jyy) = geo.lens
        e0 = [R[0][b] - geo.xn * R[2][b] for b in range(3)]
        e1 = [R[1][b] - geo.yn * R[2][b] for b in range(3)]
        g_jxx, g_jyy = geo.g * dot(g_s0, e0), geo.g * dot(g_s1, e1)
        g_jxy = geo.g * (dot(g_s0, e1) + dot(g_s1, e0))
        g_s0, g_s1 = ([jxx * g_s0[b] + jxy * g_s1[b] for b in range(3)],
                      [jxy * g_s0[b] + jyy * g_s1[b] for b in range(3)])
        d_xxx, d_xxy, d_xyy, d_yyy = distortion_curvature(geo.xn, geo.yn, coefficients)
        g_xd, g_yd = f * g_u, f * g_v
        lens_xn = jxx * g_xd + jxy * g_yd + g_jxx * d_xxx + g_jxy * d_xxy + g_jyy * d_xyy
        lens_yn = jxy * g_xd + jyy * g_yd + g_jxx * d_xxy + g_jxy * d_xyy + g_jyy * d_yyy
        lens_f = g_u * xd + g_v * yd
    g_e0 = [geo.g * x for x in g_s0]
    g_e1 = [geo.g * x for x in g_s1]
    g_g = (dot(g_s0, [R[0][b] - geo.xn * R[2][b] for b in range(3)])
           + dot(g_s1, [R[1][b] - geo.yn * R[2][b] for b in range(3)]))
    h = [[dot(g_e, R[c]) for c in range(3)] for g_e in (g_e0, g_e1)]  # camera-frame components
    if geo.lens is None:
        g_xn = f * g_u - h[0][2]
        g_yn = f * g_v - h[1][2]
        g_f = g_u * geo.xn + g_v * geo.yn + g_g * geo.iz
    else:
        g_xn = lens_xn - h[0][2]
        g_yn = lens_yn - h[1][2]
        g_f = lens_f + g_g * geo.iz
    g_iz = g_g * f + g_xn * geo.p[0] + g_yn * geo.p[1]
    g_p = keep((g_xn * geo.iz, g_yn * geo.iz, jnp.where(geo.front, -g_iz * geo.iz * geo.iz, 0.0)))
    # cos_inc = -n.d / |d|, p = R d, d = X - P
    nrm = sq[3:6]
    g_d = [g_cos * geo.rd * (-nrm[b] - geo.cos_inc * geo.rd * geo.d[b]) + dot(g_p, [R[a][b] for a in range(3)])
           for b in range(3)]
    # rotation: R stays a rotation (dR = W R, W skew), so only the skew part of M = dL/dR R^T
    # counts; M_ac = h_a[c] + g_p[a] p[c] with h_a the camera-frame components of the cotangent
    # of row a of R (h_2 = -(xn h_0 + yn h_1)), and per pair we keep M_ac - M_ca
    h.append([-(geo.xn * h[0][c] + geo.yn * h[1][c]) for c in range(3)])
    M = lambda a, c: h[a][c] + g_p[a] * geo.p[c]
    cols = [M(0, 1) - M(1, 0), M(0, 2) - M(2, 0), M(1, 2) - M(2, 1)] + [-x for x in g_d] + [
        g_f, g_u, g_v]
    # the block sums as one batched dot with ones (float64 accumulation): value + gradient ~15 %
    # faster than with separate row sums
    cols = jnp.stack(jnp.broadcast_arrays(*cols), 1)  # (blocks, 9, block)
    sums = jnp.einsum("gkl,l->gk", cols, jnp.ones(cols.shape[-1], cols.dtype),
                      preferred_element_type=ctab.dtype)
    # dL/dR of the block as S R, S = (M - M^T)/2 summed: the same dL for every rotation of R
    u01, u02, u12 = sums[:, 0], sums[:, 1], sums[:, 2]
    zero = jnp.zeros_like(u01)
    S = 0.5 * jnp.stack([jnp.stack([zero, u01, u02], -1), jnp.stack([-u01, zero, u12], -1),
                         jnp.stack([-u02, -u12, zero], -1)], -2)
    g_R = jnp.einsum("gab,gbc->gac", S, ctab[:, CAM_R].reshape(-1, 3, 3)).reshape(-1, 9)
    # W, H and the distortion coefficients: constants
    constants = jnp.zeros((sums.shape[0], ctab.shape[1] - CAM_W), sums.dtype)
    return jnp.concatenate([g_R, sums[:, 3:], constants], -1)


def pair_inputs(cam, vd: ViewData, st, dt):
    """The per-pair inputs: the camera row of each block (B, 17, or 22 with distortion) (float64)
    and, as (B, block)
    arrays in dtype dt, the 12 sample columns of the pairs' geometry, the occlusion,
    kc = Omega c^2 / sigma^2 (m^2) and a runtime 1.0 (`materialise`)."""
    L = vd.block
    B = vd.camera.shape[0] // L
    occ, cn, nz = (jax.lax.stop_gradient(x).reshape(B, L)
                   for x in (vd.occlusion, vd.contrast, vd.noise))
    kc = st.patch_area * cn * cn / (nz * nz)  # m^2
    one = (nz / nz).astype(dt)  # 1.0 (noise > 0) per pair, unknown to XLA
    ctab = camera_table(cam)[vd.camera.reshape(B, L)[:, 0]]
    geometry = [x.astype(dt) for x in jax.lax.stop_gradient(vd.geometry)]
    return ctab, geometry, occ.astype(dt), kc.astype(dt), one


def pair_terms(cam, vd: ViewData, energy, st):
    """Per listed pair, as (B, block) arrays of the camera-major list, for the reports (float64
    whatever `st.pair_dtype`; not differentiated): ent, w and the geometry (`block_forward`)."""
    ctab, geometry, occ, kc, one = pair_inputs(cam, vd, st, jnp.float64)
    ent, w, (geo, *_) = block_forward(block_columns(ctab, jnp.float64), geometry, occ, kc, one,
                                      energy, st)
    return ent, w, geo


def per_sample(x, sample, n):
    """Sum a per-pair array over the pairs of each sample (`sample` its indices, same shape),
    in float64: (n,)."""
    return jax.ops.segment_sum(x.reshape(-1).astype(jnp.float64), sample.reshape(-1), n)
