"""A script's own objective: `MountModel`, the mount variables of an experiment and the
differentiable per-sample fields they give (`vdo.search.problem.Problem` underneath)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from vdo import objective
from vdo.config.experiment import Experiment
from vdo.model.camera import Camera
from vdo.search.problem import Problem


class MountModel:
    """The mount variables of an experiment and the per-sample fields they give, differentiable
    with JAX: what `vdo optimize` moves, built from its `Problem` (the same parameterisation,
    samples, speckle, lighting and ray cast).

    theta (P,), the optimizer's unconstrained variables (`Parameterization`), one per free
    parameter ([optimize] free) of each moving camera ([optimize] cameras), named in `names`:
    "cam.u": logit of the rail parameter (u = sigmoid(θ), 0..1 along the rail; on a closed rail
    u itself, taken mod 1); "cam.x", "cam.y",
    "cam.z": logit of the fraction of a zone's box along that axis (over a floor polygon
    "cam.w1", ...: softmax logits of its corners against the first, and "cam.z"); "cam.pan",
    "cam.tilt" (rad): offsets from the direction to the camera's aim point when its position is
    free (`vdo.model.pose.aim_point`: sliding keeps the same point in the middle of the image),
    else absolute; "cam.roll" (rad). `theta0` is the configured layout. focal_mm (C,) the focal
    length of every camera in mm, a continuous variable (default the configured lenses).

    `fields(theta, focal_mm, views)` is traceable: `jax.grad(lambda t: f(model.fields(t)))`
    works for any JAX function f of the `vdo.objective.SampleFields`. The ray-cast occlusion and
    the lighting are frozen at the layout `views` was cast at (default the configured one;
    `refresh(theta)` casts them at θ), as within one round of `vdo optimize`. `float64`: the
    per-pair work in float64 (for checks against finite differences; the optimizer's float32
    pairs carry ~1e-7 relative rounding)."""

    def __init__(self, exp: Experiment, float64: bool = False):
        self.problem = problem = Problem(exp)
        if float64:
            problem.settings = dataclasses.replace(problem.settings, pair_dtype="float64")
        self.theta0 = problem.param.theta0.copy()
        self.names = [""] * len(self.theta0)
        for cam, idx in zip(problem.cams0, problem.param.index):
            for name, k in idx.items():
                self.names[k] = f"{cam.name}.{name}"
        self.focal0_mm = np.array([c.focal_length * 1e3 for c in problem.cams0])
        self.pixel_size = jnp.asarray([c.pixel_size for c in problem.cams0])
        self.views = problem.start.views

    def camera_params(self, theta, focal_mm=None) -> objective.CameraParams:
        """The cameras at (θ, focal_mm) as `vdo.objective.CameraParams` (traceable)."""
        data = self.problem.data
        pos, pan, tilt, roll = self.problem.param.poses(jnp.asarray(theta), data["held"])
        f = data["focal_px"] if focal_mm is None else jnp.asarray(focal_mm) * 1e-3 / self.pixel_size
        size = data["size"]
        return objective.CameraParams(pos, pan, tilt, roll, f, data["cx"], data["cy"], size[:, 0],
                                      size[:, 1], data["distortion"])

    def fields(self, theta, focal_mm=None, views=None) -> objective.SampleFields:
        """The per-sample fields at (θ, focal_mm) (`vdo.objective.sample_fields`), traceable."""
        p = self.problem
        return objective.sample_fields(self.camera_params(theta, focal_mm), p.obj_samples,
                                       self.views if views is None else views, p.speckle.table,
                                       p.settings)

    def refresh(self, theta) -> objective.ViewData:
        """The ray cast and lighting at θ, as the frozen `views` of `fields`."""
        return self.problem.refresh(np.asarray(theta, dtype=float)).views

    def cameras_at(self, theta) -> list[Camera]:
        """The `vdo.model.camera.Camera`s at θ (configured lenses)."""
        return self.problem.param.cameras_at(np.asarray(theta, dtype=float))

    def experiment_at(self, theta) -> Experiment:
        """The experiment with its cameras at θ (rail parameter, zone position, pan/tilt/roll),
        e.g. for `vdo.layout_state` or writing with `vdo.write_evaluation`."""
        return self.problem.exp.with_cameras(self.problem.param.specs_at(np.asarray(theta, dtype=float)))
