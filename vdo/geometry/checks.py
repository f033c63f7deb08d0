"""Every up-front check of an experiment that needs more than its TOML file, run together before
any heavy work (ray casting, rendering, JAX compilation): its meshes read and checked, no camera
inside one (`vdo.scene.load_meshes`), its load path's files read whole with every step of the
pose file in the displacement file (`vdo.geometry.keyframes.load_path_of`), and, with "lens" in
[optimize] free, every moving camera's lens in its catalogue
(`vdo.config.experiment.lens_catalogue_errors`). The checks do not stop at the first mistake:
every one found is raised together (`vdo.core.errors.ConfigErrors`, one line each), so that a
file with several mistakes is fixed in one go.
"""

from __future__ import annotations

from pathlib import Path

from vdo.config.experiment import Experiment, lens_catalogue_errors
from vdo.core.errors import Collect
from vdo.geometry.keyframes import LoadPath, load_path_of


def check_experiment(exp: Experiment, poses: Path | None = None) -> LoadPath | None:
    """Run every up-front check of `exp` (module docstring) and of `poses` (`vdo render
    --series`'s pose file, replacing the [load_path]'s); raise the one mistake found as a
    `ConfigError`, several as `ConfigErrors`. Returns the load path (None when there is none).
    A load path whose displacements need a mesh that could not be read is not read (the mesh's
    error is reported)."""
    from vdo.scene import load_meshes

    errors = Collect()
    meshes = load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                         rails=exp.rails, mounts=exp.mounts, path=exp.path, errors=errors)
    load_path = None
    needed = exp.load_path.deformed_mesh if exp.load_path.displacements is not None else None
    if (exp.load_path.active or poses is not None) and (
            needed is None or needed in {m.name for m in meshes}):
        with errors.check():
            load_path = load_path_of(exp, meshes, poses)
    errors.errors += lens_catalogue_errors(exp)
    errors.raise_all()
    return load_path
