"""Benchmark of vdo.objective: value + gradient of the score, 10 cameras x 100k samples.

Times the jitted JAX score (value only, and value + gradient w.r.t. all camera parameters) after
compilation (median of the 2nd..nth calls, `block_until_ready`) beside a plain vectorised NumPy
evaluation of the same value on the dense (C, N) inputs, measured in the same run. The JAX score
runs over a sparse pair list (`ViewData`): once with every pair whose occlusion is > 0 (what the
dense path computed, exact for any camera parameters) and once with the pairs the geometric
selection keeps at these cameras (`ViewData.from_dense(..., samples, cameras)`), in float64 and
with float32 per-pair work (`Settings(pair_dtype="float32")`, what `vdo.physics.predict.settings` and so
the optimizer use), and with lens distortion on every camera (`CameraParams.distortion`, the
coefficients `LENS`) beside the pinhole rows. Checks that the values agree with NumPy (which
applies the distortion with `vdo.model.camera.distort` and its Jacobian), that both pair lists give the
same gradient and how far the float32 gradient is from the float64 one. Prints the kernel time and
page faults per value + gradient call too: by default the script keeps freed memory in the heap
(`vdo.core.memory.retain_freed_memory`, what the command line does); `--default-malloc` measures
without it.
Run: .venv/bin/python benchmarks/objective.py [--samples N] [--repeat K] [--default-malloc]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import resource
import statistics
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from vdo import objective as ob
from vdo.model.camera import distort, distortion_jacobian, rotation
from vdo.model.pose import look_at_angles
from vdo.core.configure import configure
from vdo.core.memory import retain_freed_memory
from vdo.model.speckle import generate_pattern, gradient_energy_table, normalise


LENS = (-0.12, 0.05, 2e-4, -1e-4, 0.0)   # k1, k2, p1, p2, k3: a typical 12-25 mm lens


@dataclass
class Dense:
    """(C, N) per-pair constants as the ray cast and the photometry deliver them."""

    occlusion: np.ndarray
    contrast: np.ndarray
    noise: np.ndarray


def build(n_samples: int, n_cameras: int = 10, seed: int = 0):
    rng = np.random.default_rng(seed)
    # a box-like specimen: top face and two side faces of a 1.2 m x 0.12 m x 0.12 m beam
    faces = [  # (origin, t_u, t_v) with normal = t_u x t_v
        (np.array([-0.6, -0.06, 0.06]), np.array([1.2, 0, 0]), np.array([0, 0.12, 0])),
        (np.array([-0.6, -0.06, -0.06]), np.array([1.2, 0, 0]), np.array([0, 0, 0.12])),
        (np.array([-0.6, 0.06, 0.06]), np.array([1.2, 0, 0]), np.array([0, 0, -0.12])),
    ]
    per = np.array_split(np.arange(n_samples), len(faces))
    pts, nrm, tu, tv, reg = [], [], [], [], []
    for r, ((o, a, b), idx) in enumerate(zip(faces, per)):
        uv = rng.uniform(0, 1, (idx.size, 2))
        pts.append(o + uv[:, :1] * a + uv[:, 1:] * b)
        ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
        nrm.append(np.tile(np.cross(ua, ub), (idx.size, 1)))
        tu.append(np.tile(ua, (idx.size, 1)))
        tv.append(np.tile(ub, (idx.size, 1)))
        reg.append(np.full(idx.size, 1 if r == 0 else 0))
    pts, nrm, tu, tv, reg = map(np.concatenate, (pts, nrm, tu, tv, reg))
    area = np.full(n_samples, 3 * 1.2 * 0.12 / n_samples)
    smp = ob.Samples(*(jnp.asarray(x) for x in (pts, nrm, tu, tv, area, reg)),
                     jnp.asarray([1.0, 3.0]), jnp.asarray([2.0, 3.0]))
    ang = np.linspace(0, 2 * np.pi, n_cameras, endpoint=False)
    pos = np.c_[0.5 * np.cos(ang) * 1.2, 0.9 * np.sin(ang), 0.8 + 0.2 * np.sin(3 * ang)]
    pos[:, 1] = np.where(np.abs(pos[:, 1]) < 0.3, np.sign(pos[:, 1] + 1e-9) * 0.3, pos[:, 1])
    angles = [look_at_angles(p, [0.3 * np.cos(a), 0, 0]) for p, a in zip(pos, ang)]
    pan, tilt = map(np.asarray, zip(*angles))
    c = n_cameras
    cam = ob.CameraParams(jnp.asarray(pos), jnp.asarray(pan), jnp.asarray(tilt), jnp.zeros(c),
                          jnp.full(c, 4000.0), jnp.full(c, 1223.5), jnp.full(c, 1023.5),
                          jnp.full(c, 2448.0), jnp.full(c, 2048.0))
    occl = (rng.uniform(size=(c, n_samples)) > 0.05).astype(float)
    pho = Dense(occl, rng.uniform(500, 900, (c, n_samples)), rng.uniform(3, 8, (c, n_samples)))
    h = 1e-4
    table = gradient_energy_table(normalise(generate_pattern(256, h, 8 * h, 0.5, 5, 1)), h, n=64)
    return cam, smp, pho, table


# --------------------------------------------------------------------------------------------
# Plain NumPy reference of the same value (vectorised, no JAX)
# --------------------------------------------------------------------------------------------
def _smooth(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6 * t - 15) + 10)


def _lookup(table, lp, lq):
    grid = np.asarray(table.log_l)
    logg = np.log(np.asarray(table.g_aniso))
    n = grid.size
    step = (np.log(grid[-1]) - np.log(grid[0])) / (n - 1)

    def pos(l):
        u = np.clip((np.log(np.clip(l, grid[0], grid[-1])) - np.log(grid[0])) / step, 0, n - 1)
        i = np.clip(np.floor(u), 0, n - 2).astype(np.int64)
        return i, u - i

    i, s = pos(lp)
    j, t = pos(lq)
    return np.exp((1 - s) * (1 - t) * logg[i, j] + s * (1 - t) * logg[i + 1, j]
                  + (1 - s) * t * logg[i, j + 1] + s * t * logg[i + 1, j + 1])


def numpy_score(cam, smp, pho, table, st: ob.Settings):
    P = np.asarray(cam.position)
    R = np.asarray(rotation(cam.pan, cam.tilt, cam.roll))
    X = np.asarray(smp.points)
    d = X[None] - P[:, None]  # (C, N, 3)
    p = np.einsum("cab,cnb->cna", R, d)
    front = p[..., 2] > st.near
    z = np.where(front, p[..., 2], 1.0)
    f = np.asarray(cam.focal_px)[:, None]
    xn, yn = p[..., 0] / z, p[..., 1] / z
    e0 = R[:, None, 0] - xn[..., None] * R[:, None, 2]
    e1 = R[:, None, 1] - yn[..., None] * R[:, None, 2]
    if cam.distortion is None:
        da, db, dd, xd, yd = 1.0, 0.0, 1.0, xn, yn
    else:
        coefficients = tuple(np.asarray(cam.distortion)[:, k, None] for k in range(5))
        xd, yd = distort(xn, yn, coefficients)
        da, db, _, dd = distortion_jacobian(xn, yn, coefficients)
        da, db, dd = (np.asarray(x)[..., None] for x in (da, db, dd))
    u = f * xd + np.asarray(cam.cx)[:, None]
    v = f * yd + np.asarray(cam.cy)[:, None]
    s0 = (f / z)[..., None] * (da * e0 + db * e1)
    s1 = (f / z)[..., None] * (db * e0 + dd * e1)
    tu, tv = np.asarray(smp.tangent_u)[None], np.asarray(smp.tangent_v)[None]
    A = np.stack([np.stack([(s0 * tu).sum(-1), (s0 * tv).sum(-1)], -1),
                  np.stack([(s1 * tu).sum(-1), (s1 * tv).sum(-1)], -1)], -2)
    cos_inc = -(np.asarray(smp.normals)[None] * d).sum(-1) / np.linalg.norm(d, axis=-1)
    cl, cf = math.cos(st.incidence_limit), math.cos(st.incidence_limit - st.incidence_ramp)
    m = st.image_margin_px
    W, H = np.asarray(cam.width)[:, None], np.asarray(cam.height)[:, None]
    w = (_smooth((cos_inc - cl) / (cf - cl)) * _smooth((u + 0.5) / m) * _smooth((W - 0.5 - u) / m)
         * _smooth((v + 0.5) / m) * _smooth((H - 0.5 - v) / m))
    w = np.where(front, w, 0.0) * np.asarray(pho.occlusion)
    # T by an explicit eigen-decomposition (an independent route to the same tensor)
    M = A @ np.swapaxes(A, -1, -2)
    lam, V = np.linalg.eigh(M)  # ascending
    lam = np.maximum(lam, 1e-12 * lam[..., 1:])
    l = st.kappa / np.sqrt(lam)
    phi_small = _lookup(table, l[..., 0], l[..., 1]) / lam[..., 0]
    phi_big = _lookup(table, l[..., 1], l[..., 0]) / lam[..., 1]
    T = (phi_small[..., None, None] * V[..., :, 0, None] * V[..., None, :, 0]
         + phi_big[..., None, None] * V[..., :, 1, None] * V[..., None, :, 1])
    s = np.stack([s0, s1], -2)  # (C, N, 2, 3)
    k = st.patch_area * w * np.abs(np.linalg.det(A)) * (np.asarray(pho.contrast) / np.asarray(pho.noise)) ** 2
    C = np.einsum("cn,cnra,cnrq,cnqb->nab", k, s, T, s)
    C = C + np.eye(3) / st.prior_sigma ** 2
    ev = np.linalg.eigvalsh(C)
    sig_ev = 1.0 / ev
    sigma = np.sqrt((sig_ev ** st.eigen_power).sum(-1) ** (1 / st.eigen_power)) / st.sigma_unit
    omega = np.asarray(smp.area) * np.asarray(smp.importance)[np.asarray(smp.region)]
    omega = omega / omega.sum()
    q = st.score_power
    agg = sigma.max() * (omega * (sigma / sigma.max()) ** q).sum() ** (1 / q)
    short = np.maximum(np.asarray(smp.min_cameras)[np.asarray(smp.region)] - w.sum(0), 0.0)
    return agg + st.coverage_weight * (omega * short ** 2).sum()


def timed(fn, repeat):
    """(median, min) wall time of `repeat` calls, s: the median is the figure, the min what the
    machine gives when nothing else runs on its host (shared CI hosts vary by 1.5x)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times)


def kernel_time_and_faults(fn, repeat):
    """Per call: system (kernel) CPU time in s and minor page faults, over `repeat` calls."""
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    for _ in range(repeat):
        jax.block_until_ready(fn())
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return (r1.ru_stime - r0.ru_stime) / repeat, (r1.ru_minflt - r0.ru_minflt) / repeat


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--cameras", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--default-malloc", action="store_true",
                    help="do not keep freed memory in the heap (vdo.core.memory)")
    args = ap.parse_args()
    retained = False if args.default_malloc else retain_freed_memory()
    configure(retain_memory=False, compilation_cache=False)  # x64; compile times measured cold
    cam, smp, dense, table = build(args.samples, args.cameras)
    st = ob.Settings()
    print(f"vdo.objective benchmark: {args.cameras} cameras x {args.samples} samples, "
          f"{os.cpu_count()} CPUs, jax {jax.__version__} on {jax.devices()[0].platform}, "
          f"freed memory {'kept in the heap' if retained else 'returned (default malloc)'}")

    t0 = time.perf_counter()
    all_pairs = ob.ViewData.from_dense(dense.occlusion, dense.contrast, dense.noise, smp)
    t_all = time.perf_counter() - t0
    t0 = time.perf_counter()
    culled = ob.ViewData.from_dense(dense.occlusion, dense.contrast, dense.noise, smp, cam, st)
    t_cull = time.perf_counter() - t0
    n_dense = dense.occlusion.size
    print(f"pairs: {n_dense} dense (C x N); {all_pairs.n_pairs} with occlusion > 0 "
          f"(padded to {all_pairs.camera.size}, built in {1e3 * t_all:.0f} ms); "
          f"{culled.n_pairs} kept by the geometric selection (padded to {culled.camera.size}, "
          f"built in {1e3 * t_cull:.0f} ms)")

    st32 = ob.Settings(pair_dtype="float32")
    lens = dataclasses.replace(cam, distortion=jnp.tile(jnp.asarray(LENS), (args.cameras, 1)))
    culled_lens = ob.ViewData.from_dense(dense.occlusion, dense.contrast, dense.noise, smp, lens, st)
    rows = []
    for label, c, vd, sv in (("all occlusion>0 pairs", cam, all_pairs, st),
                             ("selected pairs", cam, culled, st),
                             ("selected pairs, f32", cam, culled, st32),
                             ("distorted, selected pairs", lens, culled_lens, st),
                             ("distorted, selected pairs, f32", lens, culled_lens, st32)):
        t0 = time.perf_counter()
        jax.block_until_ready(ob.score(c, smp, vd, table, sv))
        compile_v = time.perf_counter() - t0
        t0 = time.perf_counter()
        value, grad = jax.block_until_ready(ob.score_and_grad(c, smp, vd, table, sv))
        compile_g = time.perf_counter() - t0
        tv = timed(lambda: ob.score(c, smp, vd, table, sv), args.repeat)
        tg = timed(lambda: ob.score_and_grad(c, smp, vd, table, sv), args.repeat)
        rows.append((label, compile_v, compile_g, tv, tg, float(value), grad))

    sys_s, faults = kernel_time_and_faults(lambda: ob.score_and_grad(cam, smp, culled, table, st32),
                                           args.repeat)
    t_np, t_np_min = timed(lambda: numpy_score(cam, smp, dense, table, st), max(3, args.repeat // 3))
    v_np = numpy_score(cam, smp, dense, table, st)
    v_np_lens = numpy_score(lens, smp, dense, table, st)

    print(f"{'path':<46}{'compile s':>10}{'median ms':>11}{'min ms':>8}{'vs numpy':>10}{'score':>16}")
    print(f"{'numpy value (dense, float64)':<46}{'-':>10}{1e3 * t_np:>11.1f}{1e3 * t_np_min:>8.1f}"
          f"{1.0:>9.2f}x{v_np:>16.10g}")
    print(f"{'numpy value (dense, float64), distorted':<46}{'-':>10}{'-':>11}{'-':>8}{'-':>10}"
          f"{v_np_lens:>16.10g}")
    for label, cv, cg, (tv, tv_min), (tg, tg_min), value, _ in rows:
        print(f"{'jax value, ' + label:<46}{cv:>10.2f}{1e3 * tv:>11.1f}{1e3 * tv_min:>8.1f}"
              f"{t_np / tv:>9.2f}x{value:>16.10g}")
        print(f"{'jax value+grad, ' + label:<46}{cg:>10.2f}{1e3 * tg:>11.1f}{1e3 * tg_min:>8.1f}"
              f"{t_np / tg:>9.2f}x{'':>16}")
    for label, *_, value, _ in rows:
        ref = v_np_lens if label.startswith("distorted") else v_np
        print(f"relative difference of the values, jax ({label}) vs numpy: {abs(value / ref - 1):.2e}")
    g_all, g_cull, g_32, *_ = (jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(r[6])])
                               for r in rows)
    rel = lambda a, b: float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))
    print(f"gradient, selected vs all pairs: max |diff| / max |g| = {rel(g_cull, g_all):.2e}")
    print(f"gradient, f32 vs f64 pairs (selected): max |diff| / max |g| = {rel(g_32, g_cull):.2e}")
    print(f"value+grad, selected pairs, f32: {1e3 * sys_s:.1f} ms kernel time and {faults:.0f} "
          f"page faults per call")
    g_lens, g_lens32 = (jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(r[6])]) for r in rows[3:])
    print(f"gradient, distorted, f32 vs f64 pairs (selected): max |diff| / max |g| = {rel(g_lens32, g_lens):.2e}")
    # pinhole vs distorted value + gradient (f32, selected pairs), interleaved call by call so
    # that the load of a shared host falls on both alike
    pin, dis = [], []
    for _ in range(2 * args.repeat):
        for out, c, vd in ((pin, cam, culled), (dis, lens, culled_lens)):
            t = time.perf_counter()
            jax.block_until_ready(ob.score_and_grad(c, smp, vd, table, st32))
            out.append(time.perf_counter() - t)
    print(f"interleaved value+grad, selected pairs, f32: pinhole median {1e3 * statistics.median(pin):.1f} "
          f"min {1e3 * min(pin):.1f} ms; distorted median {1e3 * statistics.median(dis):.1f} "
          f"min {1e3 * min(dis):.1f} ms; distorted / pinhole (min) {min(dis) / min(pin):.2f}")
    print("target: value+grad <= 50 ms on 2 CPU cores")


if __name__ == "__main__":
    main()
