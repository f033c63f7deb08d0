"""What an interpolating correlation measures on a speckle pattern: the interpolation floor
(`interpolation_error`) and the per-footprint error model of a translation's correlation
(`correlation_error`: the bias over sub-pixel positions, its patch-to-patch scatter and the noise
through the interpolant, against the Cramér-Rao bound), for the cubic and quintic B-splines and
Keys' cubic convolution (`INTERPOLANTS`). The pattern's spectrum comes from
`vdo.model.speckle.blocked_spectrum`; the derivations are in docs/theory.md, section 8a.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse

from vdo.core.memo import Memo, digest
from vdo.model.realized_scatter import cumulant_factor
from vdo.model.speckle import blocked_spectrum
from vdo.model.spline_response import INTERPOLANTS, PHASES, phase_pairs, responses


INTERPOLATION_ORDER = 3        # the cubic B-spline of `vdo.dic.images.SplineImage`
TEXEL_IMAGES = 2               # texel-grid images k + m / h, |m| <= this, per axis


def interpolation_error(pattern_normalised, texel_m: float, pixel_sides,
                        order: int = INTERPOLATION_ORDER, phase=(0.5, 0.5),
                        optics=None) -> np.ndarray:
    """RMS error (K,) of the image-correlation interpolation on the box-pixel image of the
    normalised pattern f̂ (variance 1 before averaging), for K pixel footprints `pixel_sides`
    (K, 2, 2) m (as `pixel_averaged_std`): the difference between the B-spline interpolant of the
    image of the pattern moved by `phase` pixels, read at the pixel centres moved back, and the
    image of the unmoved pattern read at the pixel centres. A correlation that interpolates the
    deformed image (`vdo.dic.correlate`) sees this error as a fixed, motion-dependent gray-level
    pattern: not noise, a bias.

    The rendered texture is the texel samples (spectrum F(k), periodic in k with period 1/h)
    filtered by bilinear interpolation (sinc²(k_u h) sinc²(k_v h)), so it has energy at every
    k + m/h; the box pixel multiplies by sinc(k.a_1) sinc(k.a_2); sampling at the pixel centres
    aliases whatever lies above the pixel Nyquist frequency, which no interpolation can undo.
    With ω_j = 2π k.a_j and K_d(ω) the interpolant's shift response (`vdo.model.spline_response`, `_SplineSpectrum.shift`:
    K_d(ω) = Σ_l β̂(ω + 2πl) exp(2πi l d) / Σ_l β̂(ω + 2πl), β̂(ω) = sinc^(order+1)(ω / 2π), |l| <= _ALIAS_TERMS),

        err² = Σ_k Σ_m |F(k)|² sinc⁴(k'_u h) sinc⁴(k'_v h) sinc²(k'.a_1) sinc²(k'.a_2)
               |K_d1(ω_1) K_d2(ω_2) - 1|²,      k' = k + m / h, |m_u|, |m_v| <= TEXEL_IMAGES

    (checked against map_coordinates on supersampled box-pixel images, tests/model/test_speckle.py).
    The half-pixel phase is the worst: about the largest error over sub-pixel motions. The
    spectrum is summed over blocks of side // 64 frequencies (`blocked_spectrum`; 0.3 % off the
    full sum for the built-in 1024-texel tile): one FFT of the tile per call, then about 0.02 s
    per footprint; pass all footprints at once. `optics`: K `vdo.model.optics.OpticsBlur` (None
    entries or None: no lens blur), whose MTF²(|q|) multiplies each term (q = (k'.a_1, k'.a_2)
    cycles per pixel)."""
    f = np.asarray(pattern_normalised)
    w, ku, kv = blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 64))
    m = np.arange(-TEXEL_IMAGES, TEXEL_IMAGES + 1) / texel_m
    shape = (m.size, m.size, ku.size)                                  # (m_u, m_v, blocks)
    qu = np.broadcast_to(ku[None, None, :] + m[:, None, None], shape).reshape(-1, ku.size)
    qv = np.broadcast_to(kv[None, None, :] + m[None, :, None], shape).reshape(-1, kv.size)
    weight = w * (np.sinc(qu * texel_m) * np.sinc(qv * texel_m)) ** 4
    keep = weight.sum(axis=1) >= 1e-6 * w.sum()           # far texel images: < 1e-6 of the variance
    qu, qv, weight = qu[keep], qv[keep], weight[keep]
    sides = np.asarray(pixel_sides, dtype=np.float64).reshape(-1, 2, 2)
    optics = [None] * len(sides) if optics is None else list(optics)
    out = np.empty(len(sides))
    for i, (a, opt) in enumerate(zip(sides, optics)):
        k1, k2 = qu * a[0, 0] + qv * a[1, 0], qu * a[0, 1] + qv * a[1, 1]
        box = (np.sinc(k1) * np.sinc(k2)) ** 2
        if opt is not None:
            box = box * opt.mtf(np.hypot(k1, k2)) ** 2
        K = (responses(2 * np.pi * k1.ravel(), order).shift(np.array([phase[0]]))[0]
             * responses(2 * np.pi * k2.ravel(), order).shift(np.array([phase[1]]))[0]).reshape(k1.shape)
        out[i] = math.sqrt(float(np.sum(weight * box * np.abs(K - 1.0) ** 2)))
    return out


# --------------------------------------------------------------------------------------------
# What an interpolating correlation measures: noise through the interpolant, and its bias
# --------------------------------------------------------------------------------------------
FOLD_BINS = 32              # bins per axis of the folded pixel spectrum (scatter of the bias)
PHASE_CHUNK = 8             # sub-pixel positions computed together (`correlation_error`: (8, M) arrays)


@dataclass(frozen=True, eq=False)
class CorrelationError:
    """What a B-spline interpolating correlation of a translation measures on K footprints, per
    unit-variance pattern f̂ (`correlation_error`); image axes (x, y), pixels.

    gradient  (K, 2, 2) H₁ = <∇f ∇fᵀ> per pixel, ∇ the spline's derivative at the pixel centres
    noise     (K, 2, 2) mean over sub-pixel positions of H₁⁻¹ N_d H₁⁻¹: the noise covariance for
              a noise std σ (in units of the pattern's std) and P pixels is σ² noise / P (px²)
    bias      (K, 2, 2) mean over sub-pixel positions of b(d) b(d)ᵀ: the systematic bias (px²)
    scatter   (K, 2, 2) mean over sub-pixel positions of H₁⁻¹ V_d H₁⁻¹: the bias's variation from
              patch to patch of the pattern is scatter / P (px²)
    bound     (K, 2, 2) (Σ_k w |2πq|² q̂ q̂ᵀ)⁻¹: the Cramér-Rao bound of one noisy image with the
              true gradient (σ² bound / P), for the ratio
    bound_sharp (K, 2, 2) the same without the optics' MTF (the image the bound of
              `vdo.objective` describes)
    phases    ((n₁,), (n₂,)) the sub-pixel positions d₁, d₂ averaged over
    bias_curve (K, n₁, n₂, 2) b(d₁, d₂) in px
    """

    gradient: np.ndarray
    noise: np.ndarray
    bias: np.ndarray
    scatter: np.ndarray
    bound: np.ndarray
    bound_sharp: np.ndarray
    phases: tuple
    bias_curve: np.ndarray

    def covariance(self, sigma, pixels) -> np.ndarray:
        """(K, 2, 2) px²: σ² noise / P + scatter / P + bias, σ (K,) or scalar in pattern stds."""
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(len(self.noise))
        p = np.asarray(pixels, dtype=float) * np.ones(len(self.noise))
        return (s2[:, None, None] * self.noise + self.scatter) / p[:, None, None] + self.bias

    def ratio(self, sigma, pixels, sharp: bool = False) -> np.ndarray:
        """(K, 2) per image axis: sqrt(measured variance / the bound's σ² bound / P); `sharp`:
        against the bound of the image without the optics (`bound_sharp`)."""
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(len(self.noise))
        p = np.asarray(pixels, dtype=float) * np.ones(len(self.noise))
        crb = s2[:, None] * np.diagonal(self.bound_sharp if sharp else self.bound,
                                        axis1=1, axis2=2) / p[:, None]
        return np.sqrt(np.diagonal(self.covariance(sigma, pixels), axis1=1, axis2=2) / crb)


MODEL_CACHE_SIZE = 4096      # footprints whose `correlation_error` terms are kept (about 2 kB each)
_MODEL_CACHE = Memo(MODEL_CACHE_SIZE)  # (pattern digest, settings, footprint, optics) -> its terms


def correlation_error(pattern_normalised, texel_m: float, pixel_sides, order: int | str = 3,
                      optics=None, noisy_reference: bool = True,
                      texel_filter: str = "bilinear", phases=None,
                      fourth_moments: bool = True) -> CorrelationError:
    """The error of an interpolating correlation of a translation (`order`: 3 or 5, the B-spline;
    KEYS, Keys' cubic convolution, `_KeysSpectrum`) on the
    box-pixel image of the pattern f̂ at K footprints `pixel_sides` (K, 2, 2) m (as
    `pixel_averaged_std`), after the optics' MTF (`optics`: K `vdo.model.optics.OpticsBlur`, or
    None for none). The correlation (`vdo.dic.correlate`) reads the reference at its pixel centres
    n with the spline's gradient there, and interpolates the deformed image at n + u; d = frac(u).

    Every pattern frequency k (cycles/m, with its texel images k + m/h as `interpolation_error`)
    lands in the image at q_j = k.a_j cycles per pixel, ω = 2πq, with the weight
    w(k) = |F(k)|² T(k) sinc²(q₁) sinc²(q₂) MTF²(|q|) (T the texel filter: bilinear sinc⁴ per axis,
    box sinc²). With R_d(ω) the interpolant's shift response (the interpolated over the true value,
    `_SplineSpectrum.shift`, `_KeysSpectrum.shift`), D(ω) its derivative response (`.derivative`),
    E = R_{d₁}(ω₁) R_{d₂}(ω₂) - 1 the interpolation error and ω̄ the frequency folded into
    [-π, π) (where the sampled noise lives), over a patch of P pixels and for a pattern with
    independent random phases:

        H₁  = Σ_k w D Dᵀ                          (gradient per pixel)
        b(d) = -H₁⁻¹ Σ_k w D Im E                   (the systematic bias, px)
        N_d = Σ_k w D Dᵀ (|R_{d₁}(ω̄₁) R_{d₂}(ω̄₂)|² + r)   (r = 1: a noisy reference)
        V_d = ∫ [S_DD(q̄) S_EE(q̄) + Re S_DE(q̄) S_DE(q̄)ᵀ] dq̄   (Gaussian fourth moments)

    with S_DD, S_EE, S_DE the folded spectra (Σ of w DDᵀ, w|E|², w i D Ē over the k that fold to
    q̄, binned FOLD_BINS² over the unit cell). Then û - u = b(d) + noise + scatter with
    Cov = σ² H₁⁻¹ N_d H₁⁻¹ / P + H₁⁻¹ V_d H₁⁻¹ / P: the mean over d on a PHASES² grid is returned
    (docs/theory.md, "What the lab measures"); `phases` = (d₁ values, d₂ values) replaces that
    grid (e.g. ([0, 1/8, ...], [0]) for shifts along x only).
    V_d holds for a Gaussian field; a real pattern's fourth cumulant changes it (binary dots at
    50 % fill are platykurtic: less scatter). With `fourth_moments` (the default) the scatter is
    scaled per image axis a by kappa_a of `cumulant_factor`, the realized over the Gaussian
    scatter on the image of this tile at the rectangular footprint of the same pixel sides
    (|a_1| along image x, |a_2| along y, snapped; the footprint's shear and its orientation to
    the texel grid left out): scatter_ab <- sqrt(kappa_a kappa_b) scatter_ab (px²; kappa about 1
    for a Gaussian field, about 0.6 on y for 2 px binary dots; tests/physics/test_measured.py).
    `texel_filter`: "bilinear" (Mitsuba's bitmap), "box" (nearest texel) or "ideal" (the texels'
    band-limited interpolant: no texel filter, no texel images).
    Each footprint's terms are kept (`MODEL_CACHE_SIZE` of them, keyed by the pattern's digest, the
    settings, the footprint and the optics), so the design checks and σ_measured, which meet the
    same footprints, compute them once per process; the factor is kept per canonical footprint
    and snapped optics (`cumulant_factor`: about 0.3 s for each new one, in memory and on disk)."""
    if order not in INTERPOLANTS.values():
        raise ValueError(f"order: expected one of {list(INTERPOLANTS.values())}, got {order!r}")
    f = np.asarray(pattern_normalised)
    w, ku, kv = blocked_spectrum(f, texel_m, texel_filter=False, block=max(1, min(f.shape) // 256))
    m = np.arange(-TEXEL_IMAGES, TEXEL_IMAGES + 1) / texel_m
    shape = (m.size, m.size, ku.size)
    qu = np.broadcast_to(ku[None, None, :] + m[:, None, None], shape).reshape(-1)
    qv = np.broadcast_to(kv[None, None, :] + m[None, :, None], shape).reshape(-1)
    if texel_filter == "ideal":     # the texels' band-limited (trigonometric) interpolant
        m = np.zeros(1)
        shape = (1, 1, ku.size)
        qu, qv = ku, kv
    power = {"bilinear": 4, "box": 2, "ideal": 0}[texel_filter]
    weight = np.broadcast_to(w, shape).reshape(-1) * (np.sinc(qu * texel_m) * np.sinc(qv * texel_m)) ** power
    keep = weight >= 1e-9 * w.sum()
    qu, qv, weight = qu[keep], qv[keep], weight[keep]
    sides = np.asarray(pixel_sides, dtype=np.float64).reshape(-1, 2, 2)
    optics = [None] * len(sides) if optics is None else list(optics)
    grid = np.arange(PHASES) / PHASES
    px, py = (grid, grid) if phases is None else (np.atleast_1d(np.asarray(p, dtype=float))
                                                  for p in phases)
    out = {k: np.empty((len(sides), 2, 2))
           for k in ("gradient", "noise", "bias", "scatter", "bound", "bound_sharp")}
    curves = np.empty((len(sides), px.size, py.size, 2))
    r = 1.0 if noisy_reference else 0.0
    pairs = phase_pairs(px, py)
    common = (digest(np.asarray(f, dtype=np.float64)), float(texel_m), order, noisy_reference,
              texel_filter, px.tobytes(), py.tobytes(), fourth_moments)
    for i, (a, opt) in enumerate(zip(sides, optics)):
        key = common + (a.tobytes(), opt)
        if key in _MODEL_CACHE:
            for name, value in _MODEL_CACHE[key].items():
                (curves if name == "bias_curve" else out[name])[i] = value
            continue
        q1, q2 = qu * a[0, 0] + qv * a[1, 0], qu * a[0, 1] + qv * a[1, 1]
        wk = weight * (np.sinc(q1) * np.sinc(q2)) ** 2
        qn = np.stack([q1, q2]) / np.maximum(np.hypot(q1, q2), 1e-300)
        out["bound_sharp"][i] = np.linalg.inv(np.einsum("m,am,bm->ab", wk * (2 * np.pi) ** 2
                                                        * (q1 ** 2 + q2 ** 2), qn, qn))
        if opt is not None:
            wk = wk * opt.mtf(np.hypot(q1, q2)) ** 2
        big = wk >= 1e-9 * wk.sum()
        q1, q2, wk = q1[big], q2[big], wk[big]
        om1, om2 = 2 * np.pi * q1, 2 * np.pi * q2
        sp1, sp2 = responses(om1, order), responses(om2, order)
        D = np.stack([sp1.derivative(), sp2.derivative()])                             # (2, M)
        H1 = np.einsum("m,am,bm->ab", wk, D, D)
        qn = np.stack([q1, q2]) / np.maximum(np.hypot(q1, q2), 1e-300)
        out["bound"][i] = np.linalg.inv(np.einsum("m,am,bm->ab", wk * (om1 ** 2 + om2 ** 2), qn, qn))
        R1, R2 = sp1.shift(px), sp2.shift(py)
        G1, G2 = sp1.derivative_shift(px), sp2.derivative_shift(py)
        fold1, fold2 = (q1 + 0.5) % 1.0 - 0.5, (q2 + 0.5) % 1.0 - 0.5
        A1 = np.abs(responses(2 * np.pi * fold1, order).shift(px)) ** 2
        A2 = np.abs(responses(2 * np.pi * fold2, order).shift(py)) ** 2
        nb = FOLD_BINS * FOLD_BINS

        def bin_of(f1, f2):
            return (np.minimum((f1 + 0.5) * FOLD_BINS, FOLD_BINS - 1).astype(np.int64) * FOLD_BINS
                    + np.minimum((f2 + 0.5) * FOLD_BINS, FOLD_BINS - 1).astype(np.int64))

        # The spectrum is one-sided (k stands for ±k): half of each weight at +q̄, half at -q̄,
        # where a real field's cross-spectrum is the conjugate (D odd, E(-q) = conj E(q)).
        plus, minus = bin_of(fold1, fold2), bin_of(-fold1, -fold2)

        # binning as sparse (nb, M) matrices: even and odd parts of the two half weights
        cols = np.arange(q1.size)
        Bp, Bm = (scipy.sparse.csr_matrix((np.full(q1.size, 0.5), (rows, cols)), shape=(nb, q1.size))
                  for rows in (plus, minus))
        even, odd = Bp + Bm, Bp - Bm
        Dw = D * wk                                                              # (2, M)
        wDD = (Dw[:, None, :] * D[None, :, :]).reshape(4, -1)                    # (4, M)
        s_dd = (even @ wDD.T).T.reshape(2, 2, nb)
        noise = np.zeros((2, 2))
        bias = np.zeros((2, 2))
        scatter = np.zeros((2, 2))
        # the sub-pixel positions PHASE_CHUNK at a time, as (c, M) arrays
        for s in range(0, len(pairs), PHASE_CHUNK):
            part = pairs[s:s + PHASE_CHUNK]
            i1, i2 = (np.array([p[k] for p in part]) for k in (0, 1))
            count = np.array([p[3] for p in part], dtype=float)
            R1c, R2c = R1[i1], R2[i2]
            E = R1c * R2c - 1.0
            # the Jacobian the iteration meets: Σ ∇ref ∇(interpolated deformed)ᵀ at n + d
            Hd = np.stack([(G1[i1] * R2c).real @ Dw.T, (R1c * G2[i2]).real @ Dw.T], -1)  # (c, a, b)
            Hi = np.linalg.inv(Hd)
            b = -np.einsum("cab,cb->ca", Hi, E.imag @ Dw.T)
            for k, (p1, p2, twin, _) in enumerate(part):
                curves[i, p1, p2] = b[k]
                if twin is not None:
                    curves[i, twin[0], twin[1]] = -b[k]
            bias += np.einsum("c,ca,cb->ab", count, b, b)
            Nd = ((A1[i1] * A2[i2] + r) @ wDD.T).reshape(-1, 2, 2)
            noise += np.einsum("c,cab,cbd,ced->ae", count, Hi, Nd, Hi)
            s_ee = (even @ (wk * (E.real ** 2 + E.imag ** 2)).T).T                # (c, nb)
            # i D conj(E), (2, c, nb): real part even, imaginary part odd in q̄
            re, im = ((B @ (Dw[:, None, :] * x).reshape(-1, x.shape[-1]).T).T.reshape(2, -1, nb)
                      for B, x in ((even, E.imag), (odd, E.real)))
            V = nb * (np.einsum("abq,cq->cab", s_dd, s_ee)
                      + np.einsum("acq,bcq->cab", re, re) - np.einsum("acq,bcq->cab", im, im))
            scatter += np.einsum("c,cab,cbd,ced->ae", count, Hi, V, Hi)
        n_ph = px.size * py.size
        out["gradient"][i], out["noise"][i] = H1, noise / n_ph
        kappa = np.ones(2) if not fourth_moments else np.sqrt(cumulant_factor(
            f, texel_m, np.linalg.norm(a, axis=0), order, (px, py), opt, texel_filter,
            digest=common[0]).kappa)
        out["bias"][i], out["scatter"][i] = bias / n_ph, kappa[:, None] * scatter * kappa / n_ph
        _MODEL_CACHE.put(key, {**{k: v[i].copy() for k, v in out.items()}, "bias_curve": curves[i].copy()})
    return CorrelationError(phases=(px, py), bias_curve=curves, **out)
