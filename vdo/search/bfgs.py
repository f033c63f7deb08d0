"""The solver's step: optimistix's BFGS with a backtracking Armijo line search that remembers its
accepted step (`RememberingArmijo`), and a way to start a solve from a known inverse Hessian
(`with_inverse_hessian`), so that a round continues the last one's curvature estimate."""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


# --------------------------------------------------------------------------------------------
# The solver: BFGS with a line search that remembers its step
# --------------------------------------------------------------------------------------------
class _SearchState(eqx.Module):
    step_size: jax.Array


class RememberingArmijo(optx.AbstractSearch):
    """Backtracking Armijo line search that starts each step where the last one was accepted.

    A trial y_eval = y + α d (d the quasi-Newton direction) is accepted when
    f(y_eval) - f(y) <= slope · ∇f(y)·(y_eval - y) with ∇f(y)·(y_eval - y) <= 0. After a
    rejection α ← t α, t the minimiser of the parabola through f(y), its slope along the step and
    f(y_eval) (Δ = f(y_eval) - f(y), p = ∇f(y)·(y_eval - y): t = -p / (2 (Δ - p))), kept within
    [`shrink`, `decrease`] (safeguarded quadratic backtracking); after an acceptance
    α ← min(1, `increase` α), where optimistix's `BacktrackingArmijo` restarts from α = 1.

    Why remember: the penalties of `vdo.constraints` are 0 on the feasible side and rise steeply
    behind it (a camera body entering a light's cone), which BFGS's curvature model, built from
    accepted points where they vanish, cannot see; every full step then runs into a wall and is
    halved 4-12 times (measured on the built-in experiment: 7 of 40
    steps accepted in a penalty round; with this search 18 of 40, and a lower score). The
    parabola matters after a visibility refresh: a stiff penalty term (the shadow penalty, just
    active) dominates the gradient, and the first step overshoots by a factor ~1000: halving took
    13 rejections there (measured on the built-in experiment; with the parabola, 28 of the first
    penalty round's 40 steps are accepted, against 16)."""

    decrease: float = 0.5
    shrink: float = 0.1
    increase: float = 2.0
    slope: float = 0.1

    def init(self, y, f_info_struct):
        del f_info_struct
        # strongly typed, like the step size every step returns: a weakly typed 1.0 would make
        # the first step's state differ from the later ones' and compile the step twice
        return _SearchState(jnp.ones((), dtype=jax.tree_util.tree_leaves(y)[0].dtype))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        predicted = f_info.compute_grad_dot(jax.tree_util.tree_map(lambda a, b: a - b, y_eval, y))
        change = f_eval_info.as_min() - f_info.as_min()
        armijo = change <= self.slope * predicted
        accept = first_step | (armijo & (predicted <= 0))
        # after a rejection: the minimiser of the parabola through f(y), its slope and f(y_eval),
        # as a fraction of the step, kept within [shrink, decrease]
        curvature = change - predicted
        fraction = jnp.where((predicted < 0) & (curvature > 0),
                             -predicted / (2 * jnp.where(curvature > 0, curvature, 1.0)), self.decrease)
        fraction = jnp.clip(fraction, self.shrink, self.decrease)
        step_size = jnp.where(accept, jnp.minimum(1.0, self.increase * state.step_size),
                              fraction * state.step_size)
        return step_size, accept, optx.RESULTS.successful, _SearchState(step_size)


def with_inverse_hessian(state, inverse_hessian):
    """BFGS's state from `init` (`BFGS`) with its inverse-Hessian estimate replaced by
    `inverse_hessian` (n, n) instead of the identity. The first step keeps it (its update sees
    y_eval - y = 0 and leaves the estimate alone), so the second evaluates y - H ∇f(y)."""
    dtype = state.f_info.hessian_inv.pytree.dtype
    return eqx.tree_at(lambda s: s.f_info.hessian_inv.pytree, state,
                       jnp.asarray(inverse_hessian, dtype=dtype))


class BFGS(optx.AbstractBFGS):
    """optimistix's BFGS (inverse-Hessian update, Newton direction) with `RememberingArmijo`."""

    rtol: float
    atol: float
    norm: object
    use_inverse: bool
    descent: optx.NewtonDescent
    search: RememberingArmijo
    verbose: object

    def __init__(self, rtol: float, atol: float):
        self.rtol, self.atol, self.norm, self.use_inverse = rtol, atol, optx.max_norm, True
        self.descent = optx.NewtonDescent()
        self.search = RememberingArmijo()
        self.verbose = lambda **kwargs: None
