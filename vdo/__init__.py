"""vdo: virtual design of multi-camera digital-image-correlation experiments.

The public API (names are imported on first use, so `import vdo` stays light)::

    import vdo
    vdo.configure()                           # x64, caches, memory, logging: once per process
    exp = vdo.load("experiment.toml")         # Experiment (validated; ConfigError on mistakes)
    geometry = vdo.prepare(exp)               # meshes, surface samples, speckle model
    state = vdo.layout_state(geometry)        # visibility, lighting, predicted fields
    summary = vdo.summary(state)              # the per-region table of `vdo evaluate`
    vdo.write_evaluation(state, "runs/eval")  # the run folder of `vdo evaluate`

`vdo.evaluate_experiment`, `vdo.render_experiment`, `vdo.optimize_experiment` and
`vdo.validate_cases` are the commands as functions (each writes a run folder; `vdo.commands.evaluate`,
`vdo.render`, ... are the modules); `vdo.render_images` and `vdo.run_validation` compute without
writing, `vdo.write_render` and `vdo.write_validation` write what they return. See docs/api.md.
"""

from __future__ import annotations

import importlib
import logging

from vdo.core.configure import configure   # a name, not the submodule: imported here on purpose

logging.getLogger(__name__).addHandler(logging.NullHandler())

_EXPORTS = {
    "load": ("vdo.config.experiment", "load"),
    "parse": ("vdo.config.experiment", "parse"),
    "Experiment": ("vdo.config.experiment", "Experiment"),
    "ConfigError": ("vdo.core.errors", "ConfigError"),
    "Camera": ("vdo.model.camera", "Camera"),
    "cameras_of": ("vdo.scene", "cameras_of"),
    "prepare": ("vdo.state", "prepare"),
    "layout_state": ("vdo.state", "layout_state"),
    "Geometry": ("vdo.state", "Geometry"),
    "LayoutState": ("vdo.state", "LayoutState"),
    "Prediction": ("vdo.physics.predict", "Prediction"),
    "Visibility": ("vdo.physics.visibility", "Visibility"),
    "summary": ("vdo.outputs.report", "state_summary"),
    "evaluate_experiment": ("vdo.commands.evaluate", "evaluate"),
    "write_evaluation": ("vdo.commands.evaluate", "write_evaluation"),
    "render_images": ("vdo.render", "render_images"),
    "RenderResult": ("vdo.render", "RenderResult"),
    "render_experiment": ("vdo.commands.render", "render_experiment"),
    "write_render": ("vdo.commands.render", "write_render"),
    "optimize_experiment": ("vdo.commands.optimize", "optimize"),
    "EvaluationResult": ("vdo.outputs.report", "EvaluationResult"),
    "OptimizeResult": ("vdo.optimize", "OptimizeResult"),
    "DesignResult": ("vdo.design.select", "DesignResult"),
    "load_validation": ("vdo.dic.validate", "load"),
    "run_validation": ("vdo.dic.validate", "run_cases"),
    "ValidationResult": ("vdo.dic.validate", "ValidationResult"),
    "validate_cases": ("vdo.commands.validate", "validate_cases"),
    "write_validation": ("vdo.commands.validate", "write_validation"),
    # scripting (docs/api.md): edits, regions, your own objective, sweeps from Python
    "RegionStats": ("vdo.state", "RegionStats"),
    "write_csv": ("vdo.core.table", "write_csv"),
    "MountModel": ("vdo.search.mountmodel", "MountModel"),
    "SampleFields": ("vdo.objective", "SampleFields"),
    "sweep_variants": ("vdo.commands.sweep", "sweep_variants"),
    "warm_up": ("vdo.state", "warm_up"),
}
# The command functions carry a suffix: `vdo.commands.evaluate`, `vdo.render`, ... are the modules.

__all__ = sorted(_EXPORTS) + ["configure"]


def __getattr__(name: str):
    try:
        module, attribute = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'vdo' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attribute)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
