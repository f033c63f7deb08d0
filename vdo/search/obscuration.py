"""Differentiable obscuration of a region of interest in one camera's image.

For a camera i and a region of interest (a set of triangles of the specimen), the optimizer needs a
smooth measure of how much of the region's image is masked by obstacles, with its gradient with
respect to the camera pose θ = (x, y, z, pan, tilt) (optical centre in metres, angles in radians,
as in `vdo.model.camera`; roll and the intrinsics are held fixed).

Method
------
Two small mask images are rendered with Mitsuba at a reduced scale of the camera (same field of
view, aspect and principal point; default 96 pixels wide): in both the region is an area emitter
of radiance 1 seen directly (``max_depth = 1``, so a pixel's value is the fraction of it covered by
the visible region); in the first the obstacles are present as black occluders, in the second they
are absent. With V and V0 the sums of the two images (pixels),

    o(θ) = 1 - V(θ) / V0(θ)        (dimensionless, in [0, 1]; o = 0 when V0 = 0)

is the fraction of the region's (unobstructed) image that the obstacles mask.

Mitsuba 3.7+ does not differentiate sensor parameters, so the sensor stays fixed at the origin of
its own frame looking down +z and the geometry moves by the inverse of the camera pose instead. A
world point X is mapped to Mitsuba's camera frame by

    p = D R(pan, tilt, roll) (X - C),     D = diag(-1, -1, 1),

where R (world -> OpenCV camera) is `vdo.model.camera.rotation` and D turns OpenCV's axes (x right,
y down) into Mitsuba's (x left, y up); this is the inverse of `Camera.mitsuba_to_world`. The
transform is written in Dr.Jit arithmetic on AD variables θ, so gradients flow from the images to
the vertex positions and on to θ. The integrator is ``prb_projective`` (projective sampling,
Zhang et al. 2023) with ``max_depth = 1`` and no indirect term (``sppi = 0``): its primarily
visible silhouette term accounts for the occluders' silhouettes and the region's own outline
moving in the image, which is the whole derivative here (the radiance is constant).

Each evaluation uses fixed seeds, so the same θ gives the same value (finite differences need
that; with the box filter of `vdo.render.sensor_dict` the primal is bit-identical). The value is a
Monte Carlo estimate at `spp` samples per pixel, i.e. piecewise constant in θ on a scale of
1/sqrt(spp) pixel; the gradient is that of its expectation (a smooth function).

`ObscurationRenderer.value_and_grad` returns (o, do/dθ) with numpy; `jax_function` wraps it as a
`jax.custom_jvp` whose primal and tangent call Dr.Jit through `jax.pure_callback` (a
custom_vjp bridge would break solvers that use forward mode, such as Levenberg-Marquardt).
"""

from __future__ import annotations

from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np

from vdo.core.backend import mitsuba
from vdo.model.camera import Camera
from vdo.render import sensor_dict
from vdo.scene import SceneMesh

THETA_NAMES = ("x", "y", "z", "pan", "tilt")
PARK = 100.0   # m behind the camera: where the unobstructed render keeps the obstacles


def camera_theta(camera: Camera) -> np.ndarray:
    """θ = (x, y, z, pan, tilt) of `camera` (m, m, m, rad, rad)."""
    return np.array([*np.asarray(camera.position, dtype=float), camera.pan, camera.tilt])


def lifted_region(region: SceneMesh, offset: float) -> SceneMesh:
    """The region moved `offset` (m) along its vertex normals (toward its front side)."""
    normals = np.asarray(region.trimesh.vertex_normals, dtype=float)
    return SceneMesh(region.name, region.role, region.vertices + offset * normals, region.faces)


def _mesh(mi, mesh: SceneMesh, emitter: bool):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}})
    if emitter:
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": 1.0}})
    out = mi.Mesh(mesh.name, len(mesh.vertices), len(mesh.faces), props=props)
    params = mi.traverse(out)
    params["vertex_positions"] = np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel()
    params["faces"] = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
    params.update()
    return out


class ObscurationRenderer:
    """Obscuration o(θ) of `region` by `obstacles` in the image of `camera`, and its gradient.

    `camera` gives the intrinsics (focal length, principal point, aspect) and the roll, which stay
    fixed; θ = (x, y, z, pan, tilt) in metres and radians replaces its pose. The mask images are
    `width` pixels wide (height from the camera's aspect), rendered with `spp` samples per pixel
    (a square number; the stratified sampler rounds to one) and fixed `seed`. `mode` chooses
    reverse ("reverse": one dr.backward of o) or forward ("forward": five dr.forward passes) AD.
    `cache_size` value+gradient results are kept per θ (exact bytes of θ).

    The region is an open mesh whose boundary edges are silhouettes for the projective sampler.
    It is rendered lifted by `region_offset` (m, default 0.2 mm) along its vertex normals, so the
    specimen it belongs to can be passed whole among the obstacles (the specimen's other faces may
    hide the region): it then neither z-fights the region nor repeats the region's outline as an
    open boundary of its own (an obstacle sharing edges with the region would count that
    discontinuity twice). The region emits from its front side only (the side its face normals
    point to)."""

    def __init__(self, camera: Camera, region: SceneMesh, obstacles: list[SceneMesh],
                 width: int = 96, spp: int = 64, seed: int = 0, mode: str = "reverse",
                 region_offset: float = 2e-4, cache_size: int = 8):
        if mode not in ("reverse", "forward"):
            raise ValueError(f"mode must be 'reverse' or 'forward', not {mode!r}")
        self.mi = mi = mitsuba()
        self.camera = camera
        self.spp, self.seed, self.mode = int(spp), int(seed), mode
        self.scale = width / camera.width
        sensor = sensor_dict(camera, spp=self.spp, scale=self.scale, jitter=True)
        sensor["to_world"] = mi.ScalarTransform4f()       # fixed at the origin, looking down +z
        sensor["film"]["sample_border"] = True
        self.resolution = (sensor["film"]["width"], sensor["film"]["height"])
        self.integrator = mi.load_dict({"type": "prb_projective", "max_depth": 1, "sppi": 0,
                                        "guiding": "none"})
        # Scene 0 holds the region and the obstacles; scene 1 (the unobstructed image) holds the
        # same shapes in the same order, with the obstacles parked PARK m behind the camera. Both
        # renders use the same seeds, so the region's silhouette samples come from the same random
        # numbers (the shape is chosen with fixed per-shape weights): where no obstacle overlaps
        # the region, V = V0 and dV = dV0 exactly, and elsewhere their noise is correlated.
        meshes = [lifted_region(region, region_offset), *obstacles]
        self._world = [mi.Point3f(*[mi.Float(np.asarray(m.vertices, dtype=np.float64)[:, j])
                                    for j in range(3)]) for m in meshes]
        self._scenes, self._params = [], []
        for _ in range(2):
            scene = {"type": "scene", "sensor": sensor}
            for k, mesh in enumerate(meshes):
                scene[f"shape_{k:03d}"] = _mesh(mi, mesh, emitter=(k == 0))
            scene = mi.load_dict(scene)
            self._scenes.append(scene)
            self._params.append(mi.traverse(scene))
        self._cache: OrderedDict[bytes, tuple[float, np.ndarray]] = OrderedDict()
        self._cache_size = cache_size

    # -- geometry --------------------------------------------------------------------------
    def _transform(self, theta):
        """Set every mesh's vertices to D R (X - C) (Mitsuba camera frame) with θ Dr.Jit values."""
        dr, mi = _drjit(), self.mi
        x, y, z, pan, tilt = theta
        # Python floats: a numpy scalar times a Dr.Jit array would give a detached numpy array
        cr, sr = float(np.cos(self.camera.roll)), float(np.sin(self.camera.roll))
        cp, sp, ct, st = dr.cos(pan), dr.sin(pan), dr.cos(tilt), dr.sin(tilt)
        x0 = (sp, -cp, mi.Float(0.0))
        y0 = (st * cp, st * sp, -ct)
        zc = (ct * cp, ct * sp, st)
        xc = tuple(cr * a + sr * b for a, b in zip(x0, y0))
        yc = tuple(-sr * a + cr * b for a, b in zip(x0, y0))
        for k, X in enumerate(self._world):
            d = (X.x - x, X.y - y, X.z - z)
            px = xc[0] * d[0] + xc[1] * d[1] + xc[2] * d[2]
            py = yc[0] * d[0] + yc[1] * d[1] + yc[2] * d[2]
            pz = zc[0] * d[0] + zc[1] * d[1] + zc[2] * d[2]
            key = f"shape_{k:03d}.vertex_positions"
            self._params[0][key] = dr.ravel(mi.Point3f(-px, -py, pz))
            self._params[1][key] = dr.ravel(mi.Point3f(-px, -py, pz - (PARK if k else 0.0)))
        for params in self._params:
            params.update()

    def _images_sum(self):
        dr, mi = _drjit(), self.mi
        sums = []   # the same seeds for both images: their noise is correlated and cancels in V/V0
        for scene, params in zip(self._scenes, self._params):
            image = mi.render(scene, params, integrator=self.integrator, seed=self.seed,
                              seed_grad=self.seed + 1, spp=self.spp)
            sums.append(dr.sum(image.array))
        return sums

    # -- evaluation ------------------------------------------------------------------------
    def images(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """The two mask images (with, without obstacles) at θ, each (height, width), in [0, 1]."""
        dr, mi = _drjit(), self.mi
        theta = np.asarray(theta, dtype=float)
        with dr.suspend_grad():
            self._transform([dr.opaque(mi.Float, float(t)) for t in theta])
            return tuple(np.asarray(mi.render(s, integrator=self.integrator, seed=self.seed,
                                              spp=self.spp))[..., 0] for s in self._scenes)

    def value(self, theta) -> float:
        """o(θ) without the gradient (or from the cache)."""
        theta = np.asarray(theta, dtype=float)
        hit = self._cache.get(theta.tobytes())
        if hit is not None:
            return hit[0]
        masked, free = self.images(theta)
        return _ratio(float(masked.sum()), float(free.sum()))

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """(o, do/dθ) at θ = (x, y, z, pan, tilt); do/dθ in 1/m for the position, 1/rad for the
        angles."""
        theta = np.asarray(theta, dtype=float).reshape(5)
        key = theta.tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit[0], hit[1].copy()
        result = self._evaluate(theta)
        self._cache[key] = result
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return result[0], result[1].copy()

    def _evaluate(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        dr, mi = _drjit(), self.mi
        # Opaque: a literal would be baked into the kernels and force a recompile per θ
        t = [dr.opaque(mi.Float, float(value)) for value in theta]
        for var in t:
            dr.enable_grad(var)
        self._transform(t)
        V, V0 = self._images_sum()
        v, v0 = float(V[0]), float(V0[0])
        if v0 <= 0.0:               # the region is not in the image: nothing to obscure
            self._detach()
            return 0.0, np.zeros(5)
        o = 1.0 - V / V0
        grad = np.zeros(5)
        if self.mode == "reverse":
            dr.backward(o)
            grad[:] = [dr.grad(var)[0] for var in t]
        else:
            for k in range(5):
                for j, var in enumerate(t):
                    dr.set_grad(var, 1.0 if j == k else 0.0)
                dr.forward_from(t[k], flags=dr.ADFlag.ClearVertices)
                grad[k] = dr.grad(o)[0]
                dr.clear_grad(o)
        self._detach()
        return _ratio(v, v0), grad

    def _detach(self):
        """Drop the AD graph (vertex positions detached) before the next evaluation."""
        dr = _drjit()
        for params in self._params:
            for k in range(len(self._world)):
                key = f"shape_{k:03d}.vertex_positions"
                params[key] = dr.detach(params[key])
            params.update()

    # -- JAX -------------------------------------------------------------------------------
    def jax_function(self):
        """θ (jax array (5,)) -> o (scalar), a `jax.custom_jvp` calling Dr.Jit via pure_callback.

        The primal computes value and gradient together (cached per θ), so the JVP at the same θ
        does not render again; works under jit, jvp, grad, jacfwd and vmap (sequentially)."""

        def host_value_and_grad(theta):
            value, grad = self.value_and_grad(np.asarray(theta, dtype=float))
            return np.asarray(value, dtype=np.float64), np.asarray(grad, dtype=np.float64)

        shapes = (jax.ShapeDtypeStruct((), jnp.float64), jax.ShapeDtypeStruct((5,), jnp.float64))

        def call(theta):
            return jax.pure_callback(host_value_and_grad, shapes, theta, vmap_method="sequential")

        @jax.custom_jvp
        def obscuration(theta):
            return call(jnp.asarray(theta, dtype=jnp.float64))[0]

        @obscuration.defjvp
        def obscuration_jvp(primals, tangents):
            (theta,), (theta_dot,) = primals, tangents
            value, grad = call(jnp.asarray(theta, dtype=jnp.float64))
            return value, jnp.dot(grad, theta_dot)

        return obscuration


def _ratio(v: float, v0: float) -> float:
    return 0.0 if v0 <= 0.0 else float(np.clip(1.0 - v / v0, 0.0, 1.0))


def _drjit():
    mitsuba()
    import drjit as dr

    return dr


# --------------------------------------------------------------------------------------------
# Obscuration: one JAX function whose set of renderers changes between rounds
# --------------------------------------------------------------------------------------------
class ObscurationTerm:
    """P_obscuration(poses) = Σ_k (o_k / m)^2 over the tracked (camera, region) pairs, with its
    gradient w.r.t. each camera's (x, y, z, pan, tilt) from Mitsuba; poses is (C, 5)."""

    def __init__(self, n_cameras: int, limit: float):
        self.n, self.limit = n_cameras, max(limit, 1e-3)
        self.tracked: list[tuple[int, ObscurationRenderer]] = []
        self._cache = (None, None)

        def host(poses):
            poses = np.asarray(poses, dtype=float)
            key = poses.tobytes()
            if self._cache[0] != key:
                value, grad = 0.0, np.zeros((self.n, 5))
                for c, renderer in self.tracked:
                    o, do = renderer.value_and_grad(poses[c])
                    value += (o / self.limit) ** 2
                    grad[c] += 2 * o / self.limit ** 2 * do
                self._cache = (key, (np.float64(value), grad))
            return self._cache[1]

        shapes = (jax.ShapeDtypeStruct((), jnp.float64), jax.ShapeDtypeStruct((n_cameras, 5), jnp.float64))

        @jax.custom_jvp
        def penalty(poses):
            return jax.pure_callback(host, shapes, poses)[0]

        @penalty.defjvp
        def penalty_jvp(primals, tangents):
            value, grad = jax.pure_callback(host, shapes, primals[0])
            return value, jnp.sum(grad * tangents[0])

        self.penalty = penalty

    def track(self, renderers: list[tuple[int, ObscurationRenderer]]) -> None:
        """Differentiate these (camera, renderer) pairs from now on (the cache of the last
        evaluation is dropped with the old set)."""
        self.tracked = list(renderers)
        self._cache = (None, None)
