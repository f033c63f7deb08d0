"""θ <-> camera specs: the optimizer's unconstrained variables and the camera poses they map to.

Per moving camera, each only when listed in ``[optimize] free``: its position ("u": on a rail
z_u with u = sigmoid(z_u), on a closed rail (a ring) u = z_u mod 1, so a camera can go round
past the seam, in a zone one sigmoid per axis of its box, or softmax weights over the
corners of a convex floor polygon, so the camera cannot leave its mount; over any other floor the
sigmoids of its bounding box, and the floor penalty, `vdo.constraints.floor_penalty`, keeps it on
the floor), pan, tilt (offsets from the
direction to its aim point when it holds one), roll, and with "lens" free the focal length (a
discrete choice made outside θ, `vdo.search.solver.choose_lenses`). `perturbation` draws the
extra starts around the hand layout."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import expit

from vdo.model.camera import Camera
from vdo.model.pose import aim_point, holds_aim
from vdo.model.rail import Rail
from vdo.config.experiment import Experiment

ANGLE_SCALE = math.radians(3.0)   # rad: the solver's largest unit for an angle (`Parameterization`)
PERIODIC_U_SCALE = 0.125          # the solver's unit for u on a closed rail: what the logit's 0.5
                                  # is in u at mid-rail (du/dz = 1/4 there)
PERIODIC_U_SPREAD = 0.1           # the extra starts' spread of u on a closed rail: the logit's 0.4
                                  # at mid-rail (`perturbation`)


# --------------------------------------------------------------------------------------------
# Parameterisation
# --------------------------------------------------------------------------------------------
class Parameterization:
    """θ <-> camera poses. `index[c]` maps 'u' (rail), 'x', 'y', 'z' (zone), 'pan', 'tilt',
    'roll' to positions in θ for the free parameters of camera c.

    Position ("u" in `[optimize] free`): on a rail, u = sigmoid(z_u) in (0, 1), on a closed
    rail u = z_u mod 1 in [0, 1) (C(0) = C(1): the position is continuous across the seam,
    `periodic`); in a zone mount
    (a box [lo, hi]), each axis with an extent, p_k = lo_k + (hi_k - lo_k) sigmoid(z_k), so the
    camera can never leave its zone and the map is smooth; an axis with no extent, and a
    camera on a fixed mount, keeps its configured position.

    A camera whose rail position u is free is aimed relative to its *aim point* a_c, the point of
    its hand-layout optical axis at the depth of `centre` (the regions' centroid): its free pan
    and tilt are offsets from the direction a_c - P(u), so that sliding along the rail keeps the
    same point in the middle of the image (without this, u and the angles are strongly coupled
    and BFGS creeps along a narrow valley). Otherwise (u held, or a vertical axis, whose heading
    is undefined) pan, tilt and roll are absolute. θ = 0 offsets reproduce the hand layout; a
    held angle keeps its configured value. Each parameter's natural scale (`scale`, the solver's
    unit) is 0.5 in logit u (or per zone axis), and for an angle `ANGLE_SCALE` or an eighth of the camera's
    horizontal field of view, whichever is smaller; PERIODIC_U_SCALE for u on a closed rail."""

    RELATIVE = ("pan", "tilt")  # the angles an aimed camera holds as offsets
    AXES = ("x", "y", "z")      # a zone camera's position parameters
    MOVES = ("u",) + AXES       # the parameters that move an optical centre

    def __init__(self, exp: Experiment, cameras: list[Camera], centre):
        self.exp, self.cameras = exp, cameras
        moving = set(exp.optimize.cameras or [c.name for c in cameras])
        free = exp.optimize.free
        self.index, theta, scale, aims = [], [], [], []
        self.zones = [exp.mount(s.mount) if s.mount and exp.mount(s.mount).kind == "zone" else None
                      for s in exp.camera_specs]
        logit = lambda u: math.log(u / (1 - u))
        rails = {r.name: Rail(name=r.name, control_points=r.control_points, degree=r.degree,
                              weights=r.weights, knots_given=r.knots) for r in exp.rails}      # in JAX: d(position)/du
        self.rails = [rails[s.rail] if s.rail else None for s in exp.camera_specs]
        self.periodic = []
        for cam, spec, zone, rail in zip(cameras, exp.camera_specs, self.zones, self.rails):
            idx = {}
            if cam.name in moving:
                for name in ("u", "pan", "tilt", "roll"):
                    if name not in free:
                        continue
                    if name == "u" and spec.rail is not None and rail.closed:
                        idx[name] = len(theta)
                        theta.append(float(spec.u))
                        scale.append(PERIODIC_U_SCALE)
                    elif name == "u" and spec.rail is not None:
                        idx[name] = len(theta)
                        theta.append(logit(float(np.clip(spec.u, 1e-4, 1 - 1e-4))))
                        scale.append(0.5)
                    elif name == "u" and zone is not None and zone.floor is not None and zone.convex:
                        weights = mean_value_coordinates(zone.floor, cam.position[:2])
                        for k in range(1, len(zone.floor)):   # softmax logits against corner 0
                            idx[f"w{k}"] = len(theta)
                            theta.append(math.log(weights[k] / weights[0]))
                            scale.append(0.5)
                        if zone.high[2] > zone.low[2]:
                            idx["z"] = len(theta)
                            frac = (cam.position[2] - zone.low[2]) / (zone.high[2] - zone.low[2])
                            theta.append(logit(float(np.clip(frac, 1e-4, 1 - 1e-4))))
                            scale.append(0.5)
                    elif name == "u" and zone is not None:
                        for k, axis in enumerate(self.AXES):
                            extent = zone.high[k] - zone.low[k]
                            if extent > 0:
                                idx[axis] = len(theta)
                                frac = (cam.position[k] - zone.low[k]) / extent
                                theta.append(logit(float(np.clip(frac, 1e-4, 1 - 1e-4))))
                                scale.append(0.5)
                    elif name != "u":
                        idx[name] = len(theta)
                        aimed = self._aimed(idx, cam) and name in self.RELATIVE
                        theta.append(0.0 if aimed else getattr(cam, name))
                        # a few degrees, less for a long lens: an eighth of its horizontal field
                        scale.append(min(ANGLE_SCALE, math.atan(cam.width / 2 / cam.focal_px) / 4))
            self.index.append(idx)
            self.periodic.append("u" in idx and rail.closed)
            aims.append(aim_point(cam.position, cam.pan, cam.tilt, centre))
        self.theta0 = np.array(theta, dtype=float)
        self.scale = np.array(scale, dtype=float)   # the solver works in units of these
        self.aims = np.array(aims)

    @staticmethod
    def _aimed(idx: dict, cam: Camera) -> bool:
        """Aim-relative angles: the position free and the axis not vertical (where the heading is
        undefined)."""
        return Parameterization.moves(idx) and holds_aim(cam.tilt)

    @classmethod
    def moves(cls, idx: dict) -> bool:
        """Whether these parameters move the optical centre."""
        return any(cls.is_position(k) for k in idx)

    @classmethod
    def is_position(cls, name: str) -> bool:
        """u (rail), x, y, z (zone box axes, or the height over a floor polygon), w1... (the
        softmax logits of a floor polygon's corners)."""
        return name in cls.MOVES or name[0] == "w"

    @property
    def held(self) -> dict:
        """The layout the parameters are offsets from, as arrays (what `poses` reads besides θ):
        optical centres (C, 3), pan, tilt, roll (C,) of the hand layout and the aim points (C, 3)."""
        return dict(position=jnp.asarray(np.array([c.position for c in self.cameras], dtype=float)),
                    **{k: jnp.asarray([float(getattr(c, k)) for c in self.cameras])
                       for k in ("pan", "tilt", "roll")},
                    aims=jnp.asarray(self.aims))

    @property
    def signature(self) -> tuple:
        """What the traced `poses` depends on besides its array inputs (`held`): two
        parameterisations with the same signature share compiled programs."""
        return (tuple(tuple(sorted(idx.items())) for idx in self.index), tuple(self.periodic),
                tuple(self._aimed(idx, c) for idx, c in zip(self.index, self.cameras)),
                tuple((s.rail, tuple(np.asarray(s.offset, float))) for s in self.exp.camera_specs),
                tuple(None if z is None else (tuple(z.low), tuple(z.high),
                                              None if z.floor is None else tuple(z.floor.ravel()))
                      for z in self.zones))

    def poses(self, theta, held: dict | None = None):
        """Optical centres (C, 3), pan, tilt, roll (C,) as JAX arrays; `held` (default
        `self.held`) gives the held values and aim points."""
        held = self.held if held is None else held
        pos, angles = [], {k: [] for k in ("pan", "tilt", "roll")}
        for c, (cam, spec, rail, idx) in enumerate(zip(self.cameras, self.exp.camera_specs, self.rails,
                                                       self.index)):
            if "u" in idx:
                z = theta[idx["u"]]
                p = rail.position(jnp.mod(z, 1.0) if self.periodic[c] else jax.nn.sigmoid(z)) + spec.offset
            elif self.moves(idx):
                p = self.zone_position(self.zones[c], theta, idx, held["position"][c])
            else:
                p = held["position"][c]
            if self._aimed(idx, cam):
                d = held["aims"][c] - p
                base = dict(pan=jnp.arctan2(d[1], d[0]), tilt=jnp.arctan2(d[2], jnp.hypot(d[0], d[1])))
                relative = self.RELATIVE
            else:
                base, relative = {}, ()
            pos.append(p)
            for k in angles:
                if k in idx:
                    angles[k].append(base[k] + theta[idx[k]] if k in relative else theta[idx[k]])
                else:
                    angles[k].append(held[k][c])
        return jnp.stack(pos), *(jnp.stack(angles[k]) for k in ("pan", "tilt", "roll"))

    @classmethod
    def zone_position(cls, zone, theta, idx: dict, held):
        """p_k = lo_k + (hi_k - lo_k) sigmoid(θ[idx[axis k]]) for the zone's free axes, else
        held[k] (m): inside the box [lo, hi] for every θ (written as the convex combination
        (1 - s) lo + s hi and clipped, so that rounding never puts it a hair outside). Over a
        convex floor polygon with corners v_k: (x, y) = Σ_k softmax(0, θ_w1, ...)_k v_k, inside
        the polygon for every θ, and z as above. A floor that is not convex (a ring, an L) moves
        its cameras over its bounding box, the box above, and the optimizer's floor penalty keeps
        them on it (`vdo.constraints.floor_penalty`)."""
        def axis(k, a):
            lo, hi = zone.low[k], zone.high[k]
            s = jax.nn.sigmoid(theta[idx[a]])
            return jnp.clip((1 - s) * lo + s * hi, lo, hi)
        if "w1" in idx:   # a convex floor: a convex combination of its corners, inside it
            logits = jnp.stack([jnp.zeros(())] + [theta[idx[f"w{k}"]] for k in range(1, len(zone.floor))])
            xy = jax.nn.softmax(logits) @ jnp.asarray(zone.floor)
            return jnp.stack([xy[0], xy[1], axis(2, "z") if "z" in idx else held[2]])
        return jnp.stack([axis(k, a) if a in idx else held[k] for k, a in enumerate(cls.AXES)])

    def u(self, theta) -> list:
        """Each camera's rail parameter u at θ (sigmoid, or mod 1 on a closed rail; the spec's
        own where u is held or there is no rail)."""
        theta = np.asarray(theta)
        return [(float(np.mod(theta[idx["u"]], 1.0)) if periodic else float(expit(theta[idx["u"]])))
                if "u" in idx else spec.u
                for spec, idx, periodic in zip(self.exp.camera_specs, self.index, self.periodic)]

    def cameras_at(self, theta) -> list[Camera]:
        if not hasattr(self, "_poses_jit"):   # one compiled program, not one per eager operation
            self._poses_jit = jax.jit(self.poses)
        pos, pan, tilt, roll = (np.asarray(a) for a in self._poses_jit(jnp.asarray(theta, dtype=float),
                                                                       self.held))
        return [c.with_pose(pos[i], pan[i], tilt[i], roll[i]) for i, c in enumerate(self.cameras)]

    def specs_at(self, theta) -> list:
        """Camera specs with the optimized rail parameter or zone position and aim (pan/tilt
        replace a target)."""
        cams, us = self.cameras_at(theta), self.u(theta)
        return [dataclasses.replace(spec, u=us[i] if spec.rail else None, target=None,
                                    position=np.asarray(cams[i].position) if spec.mount else spec.position,
                                    pan=cams[i].pan, tilt=cams[i].tilt, roll=cams[i].roll)
                for i, spec in enumerate(self.exp.camera_specs)]


def mean_value_coordinates(polygon: np.ndarray, point) -> np.ndarray:
    """Positive weights w (n,), Σ w = 1, with Σ w_k v_k = point for a point inside the convex
    polygon v (n, 2) (Floater's mean value coordinates: w_k ∝ (tan(α_(k-1)/2) + tan(α_k/2)) /
    |v_k - p|, α_k the angle at p between v_k and v_(k+1)). A point on the outline is first moved
    1e-6 of the way to the centroid (where the formula degenerates)."""
    v = np.asarray(polygon, float)
    p = np.asarray(point, float)
    p = p + 1e-6 * (v.mean(axis=0) - p)
    d = v - p
    r = np.linalg.norm(d, axis=1)
    nxt = np.roll(d, -1, axis=0)
    alpha = np.arctan2(d[:, 0] * nxt[:, 1] - d[:, 1] * nxt[:, 0], np.sum(d * nxt, axis=1))
    t = np.tan(alpha / 2)
    w = (np.roll(t, 1) + t) / r
    return w / w.sum()


def perturbation(param: Parameterization, rng) -> np.ndarray:
    """A random offset of θ for an extra start: positions by 0.4 in their logits (PERIODIC_U_SPREAD
    in u on a closed rail), angles by 3 degrees."""
    d = np.zeros_like(param.theta0)
    for idx, periodic in zip(param.index, param.periodic):
        for name, k in idx.items():
            if name == "u" and periodic:
                d[k] = rng.normal(0, PERIODIC_U_SPREAD)
            else:
                d[k] = rng.normal(0, 0.4) if Parameterization.is_position(name) else rng.normal(0, math.radians(3))
    return d
