"""Per (camera, sample) pair: the projection, the sensitivity, the footprint and the soft weight
(`vdo.objective`'s docstring gives the model; "Soft weights" and "Lens distortion" there):

sensitivity  s = dx/dX = (f / Z_c) D [[1, 0, -X_c/Z_c], [0, 1, -Y_c/Z_c]] R   (2x3, pixel/m;
             D the lens distortion's Jacobian, I for a pinhole)
footprint    A = s [t_u t_v]                                                 (2x2, pixel/m)
weight       w = [Z_c > near] S(t_inc) S(t_1) S(t_2) S(t_3) S(t_4)          (occlusion not applied)
             S the C^2 `smoothstep`, t_inc = (cos theta - cos theta_lim) / (cos(theta_lim - ramp)
             - cos theta_lim), t_1..t_4 the distances (pixels) of (u, v) to the image edges
             [-1/2, W - 1/2] x [-1/2, H - 1/2] over `image_margin_px`

The cameras enter as the columns of a camera table (`camera_table`, (C, 17): R row-major,
position, f, cx, cy, W, H; (C, 22) with the 5 distortion coefficients; the `CAM_*` slices), the
samples as the 12 columns of a sample table (`sample_table`: point, normal, t_u, t_v).
3-vectors are tuples of broadcastable arrays, so that XLA fuses everything: `pairs` broadcasts
every camera against every sample (dense (C, N), `vdo.objective.geometry`), `pairs_from` takes
any broadcastable columns (the camera-major blocks of `vdo.information.blocks`).

Above `vdo.information.inputs` (`Settings`); below `views` and `blocks`."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from vdo.information.inputs import CameraParams, Samples, Settings
from vdo.model.camera import distort, distortion_jacobian, image_point, rotation


def smoothstep(t):
    """C^2 step: 0 for t <= 0, 6t^5 - 15t^4 + 10t^3 on [0, 1], 1 for t >= 1."""
    t = jnp.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def smoothstep_grad(t):
    """d smoothstep / dt = 30 t^2 (1 - t)^2 on [0, 1], 0 outside."""
    t = jnp.clip(t, 0.0, 1.0)
    return 30.0 * (t * (1.0 - t)) ** 2


def weight_scales(st):
    """(cos theta_lim, 1 / (cos(theta_lim - ramp) - cos theta_lim), 1 / image_margin_px): the
    smoothstep arguments of the soft weights are t_inc = (cos theta - cos theta_lim) x the
    second and t_img = (distance to the image edge) x the third."""
    c_lim, c_full = math.cos(st.incidence_limit), math.cos(st.incidence_limit - st.incidence_ramp)
    return c_lim, 1.0 / (c_full - c_lim), 1.0 / st.image_margin_px


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


# Per-camera quantities, columns of the (C, 17) camera table: R (row-major), position, intrinsics;
# with lens distortion 5 more (C, 22): the coefficients in `vdo.model.camera.DISTORTION` order.
CAM_R, CAM_POS, CAM_F, CAM_CX, CAM_CY, CAM_W, CAM_H = slice(0, 9), slice(9, 12), 12, 13, 14, 15, 16
PINHOLE_COLUMNS, CAM_DIST = 17, slice(17, 22)


def camera_table(cam: CameraParams):
    """(C, 17): R = rotation (rows x_c, y_c, z_c) row-major, position, f, cx, cy, W, H (the
    pixel counts W, H not differentiated); (C, 22) with the distortion coefficients (constants)
    when `cam.distortion` is not None."""
    R = rotation(cam.pan, cam.tilt, cam.roll)
    c = R.shape[0]
    W, H = jax.lax.stop_gradient((cam.width, cam.height))
    columns = [R.reshape(c, 9), cam.position, jnp.stack([cam.focal_px, cam.cx, cam.cy, W, H], -1)]
    if cam.distortion is not None:
        columns.append(jax.lax.stop_gradient(jnp.asarray(cam.distortion, dtype=R.dtype)))
    return jnp.concatenate(columns, -1)


def sample_table(smp: Samples):
    """(N, 12): point, normal, t_u, t_v."""
    return jnp.concatenate([smp.points, smp.normals, smp.tangent_u, smp.tangent_v], -1)


def _split(table, shape_of):
    """Columns of a (K, m) table as m arrays reshaped by shape_of (broadcastable components)."""
    return [shape_of(table[:, k]) for k in range(table.shape[1])]


class _Geo(NamedTuple):
    """Per-pair geometry and its intermediates (broadcastable arrays; 3-vectors as tuples)."""

    d: tuple      # X - P, m
    p: tuple      # R d, camera frame, m
    front: jax.Array
    iz: jax.Array  # 1 / Z_c (1 where not in front), 1/m
    xn: jax.Array  # X_c / Z_c
    yn: jax.Array
    u: jax.Array   # pixel
    v: jax.Array
    g: jax.Array   # f / Z_c, pixel/m
    lens: tuple | None  # with distortion: (coefficients, x_d, y_d, D's entries (a, b, d)), else None
    s0: tuple      # sensitivity rows, pixel/m
    s1: tuple
    A: tuple       # footprint A00, A01, A10, A11, pixel/m
    rd: jax.Array  # 1 / |d|
    cos_inc: jax.Array
    t_inc: jax.Array  # smoothstep arguments: incidence, then the 4 image edges
    t_img: tuple
    w: jax.Array   # soft weight (occlusion not included)


def pairs_from(cq, sq, st: Settings) -> _Geo:
    """Per-pair geometry from broadcastable components: cq the 17 camera columns (22 with the
    lens distortion), sq the 12 sample columns (module docstring for the formulas)."""
    R = [cq[3 * a:3 * a + 3] for a in range(3)]
    P, f, cx, cy, W, H = cq[9:12], cq[CAM_F], cq[CAM_CX], cq[CAM_CY], cq[CAM_W], cq[CAM_H]
    X, nrm, tu, tv = sq[0:3], sq[3:6], sq[6:9], sq[9:12]
    d = tuple(X[k] - P[k] for k in range(3))  # camera centre -> point
    p = tuple(dot(R[a], d) for a in range(3))
    front = p[2] > st.near
    iz = 1.0 / jnp.where(front, p[2], 1.0)  # safe depth: the weight is 0 where not in front
    xn, yn = p[0] * iz, p[1] * iz
    g = f * iz
    if len(cq) == PINHOLE_COLUMNS:
        lens = None
        u, v = image_point((f, None, cx, f, cy), xn, yn)
        s0 = tuple(g * (R[0][b] - xn * R[2][b]) for b in range(3))
        s1 = tuple(g * (R[1][b] - yn * R[2][b]) for b in range(3))
    else:  # s = g D [[1, 0, -x], [0, 1, -y]] R with D = d(x_d, y_d)/d(x, y) = [[a, b], [b, d]]
        coefficients = tuple(cq[CAM_DIST])
        xd, yd = distort(xn, yn, coefficients)
        jxx, jxy, _, jyy = distortion_jacobian(xn, yn, coefficients)
        lens = (coefficients, xd, yd, (jxx, jxy, jyy))
        u, v = image_point((f, None, cx, f, cy), xd, yd)   # (x_d, y_d): distorted above
        e0 = tuple(R[0][b] - xn * R[2][b] for b in range(3))
        e1 = tuple(R[1][b] - yn * R[2][b] for b in range(3))
        s0 = tuple(g * (jxx * e0[b] + jxy * e1[b]) for b in range(3))
        s1 = tuple(g * (jxy * e0[b] + jyy * e1[b]) for b in range(3))
    A = (dot(s0, tu), dot(s0, tv), dot(s1, tu), dot(s1, tv))

    dd = dot(d, d)
    rd = jax.lax.rsqrt(jnp.maximum(dd, jnp.finfo(dd.dtype).tiny))
    cos_inc = -dot(nrm, d) * rd
    c_lim, inc_scale, m = weight_scales(st)
    t_inc = (cos_inc - c_lim) * inc_scale
    t_img = ((u + 0.5) * m, (W - 0.5 - u) * m, (v + 0.5) * m, (H - 0.5 - v) * m)
    w_img = smoothstep(t_img[0]) * smoothstep(t_img[1]) * smoothstep(t_img[2]) * smoothstep(t_img[3])
    w = jnp.where(front, smoothstep(t_inc) * w_img, 0.0)
    return _Geo(d, p, front, iz, xn, yn, u, v, g, lens, s0, s1, A, rd, cos_inc, t_inc, t_img, w)


def pairs(cam: CameraParams, smp: Samples, st: Settings) -> _Geo:
    """Dense (C, N) geometry (every camera with every sample)."""
    cq = _split(camera_table(cam), lambda x: x[:, None])
    sq = _split(sample_table(smp), lambda x: x[None, :])
    return pairs_from(cq, sq, st)
