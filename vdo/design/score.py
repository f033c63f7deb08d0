"""The score of a selection of candidate cameras (`Scorer`): what the selection of
`vdo.design.select` lowers and `vdo.design.bound` bounds.

Score. The information of a set S of cameras adds: C_S(n) = sum_{i in S} C_i(n), coverage
k_S(n) = sum_{i in S} w_i(n). The set is scored by the geometric mean of sigma, inflated by the
coverage deficit:

    score(S) = exp( sum_n omega_n ln(sigma_n / 1 um) + kappa P ) um,
    P = sum_n' a_n' h(max(0, k_region(n') - k_S(n'))) / sum_n' a_n',

sigma_n the smooth sigma_max of the regularised C_S (`vdo.objective`), omega = area x importance
over the scored regions ([optimize] regions, default all) normalised to sum 1, and the coverage
penalty P over EVERY region (a design must see the whole specimen, not only the scored part),
kappa = ln(prior_sigma / 1 um) = ln 1000 (`coverage_weight`) times [design] coverage_weight
(default 1), h the views missing at a sample
smoothed (`views_short`: Huber, linear beyond half a view, so that a second view counts about as
much as a first). Why not the optimizer's power mean
(q = 8, `vdo.objective.score`): a sample no camera pair measures sits at the prior's sigma (1 mm),
(1000 / 0.3)^8 ~ 1e28 times a measured sample's term, so while any sample of the specimen is
unmeasured (one that no candidate can measure, or the part an all-round layout cannot reach yet)
the power mean is flat in every measured sigma, to float64's last digit, and the selection only
adds views (the pressure vessel: 7 designed cameras at sigma p95 2.2-8x the hand layout's, 8 mm
lenses). In the logarithm every sample counts by its ratio: a second view of an area a (sigma from
1 mm to ~1 um: ln 1000 ~ 6.9, plus kappa from P) competes with halving sigma on ~20 a of
measured area (ln 2 each), and a sample that no selection can measure adds a constant. The score
is convex in (C_S, k_S) (`vdo.design.bound`).

With `[design] target_sigma_um` sigma_t, a sample above the target costs more, quadratically in
the logarithm of its excess:

    ln(sigma_n / 1 um)  ->  ln(sigma_n / 1 um) + kappa g(max(0, ln(sigma_n / sigma_t))),

g(x) = x^2 up to x = 1 and 2x - 1 beyond (`target_excess`), so that a region's worst samples are
no longer traded for typical ones (the geometric mean alone let the steel beam's 4-camera design
leave 30 % of one end at 2.3 um p95, against a 0.3 um target). The weight is the coverage
penalty's kappa: a sample at e times the target costs as much as one view missing there; the term
is 0 at or below the target, 3.3 at twice it (the default kappa, whatever [design]
coverage_weight). Beyond e times it grows linearly in ln sigma, so an
unmeasured sample (the prior's 1 mm) adds a bounded constant and the score's exponent stays finite
for any target. It is convex (a convex increasing function of ln sigma, itself convex in C_S), so
the score stays convex and the bound holds.

It is not submodular (one camera alone gains
nothing in sigma; pairs do), so lazy evaluation's bound does not hold: every step evaluates every
feasible candidate, which the sums make cheap (`Scorer.add`: the base's log-sum corrected at each
candidate's stored entries, one vectorised pass over them). `vdo design --refine` then minimises
the optimizer's own score (`vdo optimize`), which weighs the worst samples (q = 8).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from vdo import objective
from vdo.design.candidates import ENTRY_CHUNK, Candidates
from vdo.config.experiment import Experiment
from vdo.physics.predict import settings

TARGET_BEND = 1.0             # ln(sigma / target) where the target's term turns from square to linear
SHORT_SMOOTH = 0.5           # views: the coverage penalty is quadratic below this deficit, linear above (`views_short`)


class Scorer:
    """score(S) of the module docstring for sums of candidates' information and weights:

        score(S) = exp( sum_n omega_n c(sigma_n) + kappa P ) sigma_unit,

    omega_n normalised to sum 1. Adding one candidate changes only the samples it sees, so each
    candidate's score is the base set's sums corrected at its stored entries,

        score(S + k) = exp( L + sum_{n in k} omega_n [c(sigma'_n) - c(sigma_n)]
                            + kappa (H + sum_{n in k} [h'_n - h_n]) ) sigma_unit,

    c(sigma) = ln(sigma / sigma_unit) (plus the target term of the module docstring, `cost`),
    L = sum_n omega_n c(sigma_n), h_n = a_n h(max(0, k_region(n) - k_S(n))) (`views_short`), H their
    sum and the primes after the addition: each correction is a difference of logarithms at one
    sample (no cancellation against the whole sum), and the cost follows the stored entries, not
    candidates x samples."""

    def __init__(self, exp: Experiment, samples):
        st = settings(exp.evaluation)
        scored = np.ones(len(samples.region_names), bool) if exp.optimize.regions is None else \
            np.isin(samples.region_names, exp.optimize.regions)
        omega = samples.area * samples.region_importance[samples.region] * scored[samples.region]
        minimum = np.array([r.min_cameras for r in exp.regions])
        self.settings = st
        self.omega = omega / omega.sum()
        self.area = samples.area / samples.area.sum()
        self.minimum = minimum[samples.region].astype(float)
        self.target_weight = coverage_weight(st)          # the target's term: the default kappa
        self.kappa = self.target_weight * exp.design.coverage_weight
        target = exp.design.target_sigma_um
        self.log_target = None if target is None else math.log(target * 1e-6 / st.sigma_unit)
        self._sigma = jax.jit(lambda e: objective.smooth_sigma_max(tuple(e[:, k] for k in range(6)), st)
                              / st.sigma_unit)
        self._omega, self._area, self._minimum = (jnp.asarray(x) for x in (self.omega, self.area,
                                                                           self.minimum))
        self._terms = jax.jit(self._entry_terms)

    def sigma(self, info: np.ndarray) -> np.ndarray:
        """(M,) smooth sigma_max / sigma_unit of (M, 6) information, in chunks of ENTRY_CHUNK
        (the last one padded, so one compiled size)."""
        out = np.empty(len(info))
        for s in range(0, len(info), ENTRY_CHUNK):
            part = info[s:s + ENTRY_CHUNK]
            size = ENTRY_CHUNK if len(info) > ENTRY_CHUNK else 1 << max(len(part) - 1, 1).bit_length()
            pad = np.zeros((size, 6))
            pad[:len(part)] = part
            out[s:s + len(part)] = np.asarray(self._sigma(jnp.asarray(pad)))[:len(part)]
        return out

    def cost(self, log_sigma, xp):
        """A sample's term: ln(sigma / 1 um), plus kappa g(max(0, ln(sigma / sigma_t))) with a
        target (module docstring); xp: numpy or jax.numpy."""
        if self.log_target is None:
            return log_sigma
        return log_sigma + self.target_weight * target_excess(xp.maximum(log_sigma - self.log_target, 0.0), xp)

    def value(self, info, cover):
        """The score of summed information info (N, 6) float64 1/m^2 and coverage cover (N,): a
        traceable JAX function, convex in both (`vdo.design.bound`); `_score` on the host."""
        return jnp.exp(jnp.sum(self.term(info, cover, jnp.arange(len(self.omega)))))

    def term(self, info, cover, sample):
        """The score's logarithm sample by sample: score = exp(sum_n term_n) (class docstring),

            term_n = omega_n c(sigma_n) + kappa a_n h(max(0, k_region(n) - k_n)),

        of information info (M, 6) 1/m^2 and coverage cover (M,) at the samples `sample` (M,)
        (indices; a sample may repeat): traceable JAX, convex in (info, cover) and non-increasing
        as either grows (`vdo.design.bound`'s branching on a sample's views)."""
        st = self.settings
        sigma = objective.smooth_sigma_max(tuple(info[:, k] for k in range(6)), st) / st.sigma_unit
        short = jnp.maximum(self._minimum[sample] - cover, 0.0)
        return self._omega[sample] * self.cost(jnp.log(sigma), jnp) + \
            self.kappa * self._area[sample] * views_short(short, jnp)

    def _score(self, sigma, cover) -> float:
        short = np.maximum(self.minimum - cover, 0.0)
        return float(np.exp(np.sum(self.omega * self.cost(np.log(sigma), np))
                            + self.kappa * np.sum(self.area * views_short(short, np))))

    def _entry_terms(self, index, info, weight, base_info, base_cover, base_cost, h):
        """Per entry (one chunk, jitted): omega_n (c(sigma'_n) - c(sigma_n)) after adding the
        entry's information to the base at its sample n (c = `cost`), and h'_n - h_n (class
        docstring)."""
        st = self.settings
        sig = objective.smooth_sigma_max(tuple(base_info[index, k] + info[:, k] for k in range(6)),
                                          st) / st.sigma_unit
        short = jnp.maximum(self._minimum[index] - (base_cover[index] + weight), 0.0)
        return self._omega[index] * (self.cost(jnp.log(sig), jnp) - base_cost[index]), \
            self._area[index] * views_short(short, jnp) - h[index]

    def add(self, base_info, base_cover, cand: Candidates, rows) -> np.ndarray:
        """Scores of base + each candidate of `rows`: base (N, 6), (N,)."""
        rows = np.asarray(rows, dtype=int)
        if rows.size == 0:
            return np.zeros(0)
        cost = self.cost(np.log(self.sigma(base_info)), np)
        short = np.maximum(self.minimum - base_cover, 0.0)
        h = self.area * views_short(short, np)
        base = tuple(jnp.asarray(x) for x in (base_info, base_cover, cost, h))
        dl, dh = np.zeros(len(rows)), np.zeros(len(rows))
        # the stored entries of `rows`, row after row, ENTRY_CHUNK at a time: every per-entry
        # array lives for one chunk (the stored pairs are the only thing as large as all of them)
        ends = np.cumsum(cand.indptr[rows + 1] - cand.indptr[rows])
        total = int(ends[-1])
        for s in range(0, total, ENTRY_CHUNK):
            pos = np.arange(s, min(s + ENTRY_CHUNK, total))
            owner = np.searchsorted(ends, pos, side="right")
            e = cand.indptr[rows[owner]] + pos - (ends[owner] - (cand.indptr[rows + 1] - cand.indptr[rows])[owner])
            m = len(e)
            pad = lambda x: np.concatenate([x, np.zeros((ENTRY_CHUNK - m,) + x.shape[1:], x.dtype)])  # noqa: E731
            a, b = self._terms(jnp.asarray(pad(cand.index[e])), jnp.asarray(pad(cand.entry_info[e])),
                               jnp.asarray(pad(cand.entry_weight[e].astype(float))), *base)
            dl += np.bincount(owner, np.asarray(a)[:m], minlength=len(rows))
            dh += np.bincount(owner, np.asarray(b)[:m], minlength=len(rows))
        return np.exp(np.sum(self.omega * cost) + dl + self.kappa * (h.sum() + dh))

    def of(self, cand: Candidates, chosen) -> float:
        info, cover = cand.sums(list(chosen))
        return self._score(self.sigma(info), cover)


def views_short(short, xp):
    """The coverage penalty's cost of `short` views missing at a sample (module docstring): the
    Huber function, s^2 / (2 SHORT_SMOOTH) up to SHORT_SMOOTH views, s - SHORT_SMOOTH / 2 beyond:
    convex and smooth (the bound's gradient steps), and as linear as that allows, so that a
    sample's second view lowers it about as much as its first (a squared deficit rewarded the
    first view three times the second and spread two cameras over disjoint views). xp: numpy or
    jax.numpy."""
    return xp.where(short > SHORT_SMOOTH, short - SHORT_SMOOTH / 2, short * short / (2 * SHORT_SMOOTH))


def target_excess(x, xp):
    """g(x) of the target's term (module docstring) for x = max(0, ln(sigma / sigma_t)) >= 0: x^2
    up to TARGET_BEND and linear beyond (slope 2 TARGET_BEND): convex, increasing, smooth."""
    return xp.where(x > TARGET_BEND, 2 * TARGET_BEND * x - TARGET_BEND ** 2, x * x)


def coverage_weight(st: objective.Settings) -> float:
    """kappa of the score (module docstring): ln(prior_sigma / sigma_unit), so that a sample's
    whole area one camera short of its region's min_cameras raises the score's logarithm as much
    as a sample of the same weight going from a 1 um to an unmeasured sigma (the prior, 1 mm)."""
    return math.log(st.prior_sigma / st.sigma_unit)
