"""The house rules, read from the code itself (ast): imports run one way, down the floors below.

A module may import a module of its own package, or of a package (or top-level module) on a
lower floor; never one above. Inner (function-level) imports count as much as top-level ones.
No private name (leading underscore) is imported from another module, nor read through one
(`module._name`). Below `vdo.state` (every unit from meshes/ to constraints.py) functions take
the tables they read, not the whole `Experiment`. docs/architecture.md draws the same floors.
"""
from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "vdo"

# floor of each package or top-level module, bottom (0) to top
FLOORS = {
    "core": 0,
    "model": 1,
    "config": 2,
    "meshes": 3,
    "scene": 4,
    "geometry": 5,
    "information": 6,
    "objective": 7,
    "physics": 8,
    "constraints": 9,
    "state": 10,
    "formats": 11,
    "outputs": 12,
    "rendering": 13,
    "render": 14,
    "dic": 15,
    "search": 16,
    "optimize": 17,
    "calib": 17,
    "design": 18,
    "commands": 19,
    "__init__": 20,
    "__main__": 20,
}


def _unit(module: str) -> str:
    """vdo.physics.predict -> physics; vdo.scene -> scene."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _modules():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        name = ".".join(rel.parts)
        package = name.rsplit(".", 1)[0] if path.name != "__init__.py" else name[: -len(".__init__")]
        yield path, name, package


def _imports(path: Path, package: str):
    """(line, imported module, imported names) for every vdo import in the file, resolved."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("vdo"):
                    yield node.lineno, a.name, ()
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.startswith("vdo"):
                yield node.lineno, module, tuple(a.name for a in node.names)


def test_every_module_has_a_floor():
    units = {_unit(name) for _, name, _ in _modules() if name != "vdo.__init__"}
    assert units <= set(FLOORS), f"give these a floor in FLOORS and docs/architecture.md: {units - set(FLOORS)}"


@pytest.mark.parametrize("path,name,package", list(_modules()), ids=lambda x: str(x))
def test_imports_run_down(path, name, package):
    me = "__init__" if name == "vdo.__init__" else _unit(name)
    wrong = []
    for line, module, names in _imports(path, package):
        targets = [module] if module != "vdo" else [f"vdo.{n}" for n in names]
        for target in targets:
            other = _unit(target) if target != "vdo" else "__init__"
            if other == me:
                continue
            if FLOORS[other] >= FLOORS[me]:
                wrong.append(f"{path.name}:{line} imports {target} (floor {FLOORS[other]} >= {FLOORS[me]})")
        if module != name:
            private = [n for n in names if n.startswith("_") and n != "__version__"]
            if private:
                wrong.append(f"{path.name}:{line} imports private {private} from {module}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("path,name,package", list(_modules()), ids=lambda x: str(x))
def test_no_private_name_is_read_through_another_module(path, name, package):
    """`module._name` on an imported vdo module is the private import by another door."""
    tree = ast.parse(path.read_text())
    aliases = {}                  # local name -> the vdo module it is bound to
    for _, module, names in _imports(path, package):
        for n in names:
            folder = ROOT.parent / module.replace(".", "/")
            if (folder / f"{n}.py").is_file() or (folder / n / "__init__.py").is_file():
                aliases[n] = f"{module}.{n}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("vdo.") and a.asname:
                    aliases[a.asname] = a.name
    wrong = [f"{path.name}:{node.lineno} reads {aliases[node.value.id]}.{node.attr}"
             for node in ast.walk(tree)
             if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
             and node.value.id in aliases and aliases[node.value.id] != name
             and node.attr.startswith("_") and not node.attr.startswith("__")]
    assert not wrong, "\n".join(wrong)


def test_the_config_stops_at_the_door():
    """Reading and validating an experiment (one with a rail) and every field of a validation
    file imports no JAX, Mitsuba, Dr.Jit or matplotlib: `vdo check` and every command's up-front
    validation stay light."""
    import subprocess
    import sys
    code = ("import sys; from vdo.config.experiment import load; "
            "load('experiments/beam_column/ten_cameras.toml'); "
            "from vdo.config import validation; validation.load('experiments/validation.toml'); "
            "print(sorted(m for m in ('jax', 'mitsuba', 'drjit', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT.parent)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_config_builds_no_camera_and_no_rail():
    """`vdo/config/` imports (at the top or inside a function) neither `vdo.model.camera` nor
    `vdo.model.rail`, the JAX modules: cameras are built by `vdo.scene.cameras_of`."""
    heavy = ("vdo.model.camera", "vdo.model.rail")
    wrong = [f"{path.name}:{line} imports {module if module in heavy else module + '.' + n}"
             for path, name, package in _modules() if _unit(name) == "config"
             for line, module, names in _imports(path, package)
             for n in names or ("",)
             if module in heavy or module == "vdo.model" and f"vdo.model.{n}" in heavy]
    assert not wrong, "\n".join(wrong)


def test_a_moved_camera_reaims_without_jax():
    """Editing cameras with `Experiment.with_camera` (a move along a rail, with the re-aim at the
    aim point, and a turn) stays in NumPy: no JAX, Mitsuba or Dr.Jit is imported, and the edits
    took (the re-aim's geometry is checked in tests/test_scripting.py)."""
    import json
    import subprocess
    import sys
    code = ("import json, sys; from vdo.config.experiment import load; "
            "e = load('experiments/beam_column/three_cameras.toml'); "
            "m = e.with_camera('cam1', u=0.3, centre=[0.0, 0.0, 0.5]).with_camera('cam2', pan_deg=10); "
            "print(json.dumps([sorted(k for k in ('jax', 'mitsuba', 'drjit') if k in sys.modules), "
            "[c.u for c in m.camera_specs[:1]] + [c.pan for c in m.camera_specs[:2]], "
            "[c.pan for c in e.camera_specs[:1]]]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT.parent)
    heavy, (u, pan_moved, pan_turned), (pan_before,) = json.loads(out.stdout)
    assert heavy == [], out.stderr
    assert u == 0.3 and pan_turned == pytest.approx(math.radians(10))
    assert pan_moved != pytest.approx(pan_before)   # re-aimed after the move


def test_only_commands_write_run_folders():
    """Only the command modules (vdo/commands/) import `vdo.core.runfolder.run_folder`: every
    layer below computes and returns a typed result, and its command writes it. (The module
    that defines it, vdo/core/runfolder.py, is the one other place it may be named.)"""
    wrong = []
    for path, name, package in _modules():
        if _unit(name) == "commands" or name == "vdo.core.runfolder":
            continue
        for line, module, names in _imports(path, package):
            if module == "vdo.core.runfolder" and "run_folder" in names or \
                    module == "vdo.core" and "runfolder" in names:
                wrong.append(f"{path.relative_to(ROOT.parent)}:{line} imports run_folder")
    assert not wrong, "write run folders in vdo/commands/ only:\n" + "\n".join(wrong)


def _takes_the_experiment(node: ast.AST) -> list[str]:
    """The parameters of a function (def or lambda) that hold the whole experiment: named `exp`
    or annotated `Experiment` (a name, an attribute or a string)."""
    a = node.args
    params = a.posonlyargs + a.args + a.kwonlyargs + [p for p in (a.vararg, a.kwarg) if p]
    return [p.arg for p in params if p.arg == "exp" or p.annotation is not None
            and re.search(r"\bExperiment\b", ast.unparse(p.annotation))]


# the units below the door (`vdo.state`) that take tables, not the experiment: the units under
# state in FLOORS above core, model and config (which define, read and check the experiment)
BELOW_THE_DOOR = ("meshes", "scene", "geometry", "information", "objective", "physics", "constraints")


def test_below_the_door_rule_covers_every_unit_under_state():
    """BELOW_THE_DOOR is every unit between config and state: a unit added there is covered."""
    assert set(BELOW_THE_DOOR) == {u for u, f in FLOORS.items() if FLOORS["config"] < f < FLOORS["state"]}


def test_every_unit_below_the_door_takes_tables_not_the_experiment():
    """Below `vdo.state` (vdo/meshes/, vdo/scene.py, vdo/geometry/, vdo/information/,
    vdo/objective.py, vdo/physics/ and vdo/constraints.py) a function takes the tables it reads
    (`evaluation`, `analysis`, `regions`, `mesh_specs`, `camera_specs`, ...), not the whole
    `Experiment`: no parameter named `exp` nor annotated `Experiment`, and no `.experiment` read
    off what it is handed (a `Geometry`'s or a `LayoutState`'s). The experiment stops at the
    door."""
    wrong = []
    for path, name, _ in _modules():
        if _unit(name) not in BELOW_THE_DOOR:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                for arg in _takes_the_experiment(node):
                    function = getattr(node, "name", "<lambda>")
                    wrong.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} {function}({arg})")
            elif _reads_the_experiment(node):
                wrong.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} reads {ast.unparse(node)}")
    assert not wrong, "take the tables, not the experiment:\n" + "\n".join(wrong)


def _reads_the_experiment(node: ast.AST) -> bool:
    """Whether `node` reads an `experiment` attribute (`geometry.experiment`)."""
    return isinstance(node, ast.Attribute) and node.attr == "experiment"


def test_the_experiment_rule_sees_an_attribute():
    """The rule above finds `.experiment` read off an object, and not a name that holds the word."""
    code = "x = geometry.experiment.regions\ny = experiment_path\nz = state.experiments\n"
    found = [ast.unparse(n) for n in ast.walk(ast.parse(code)) if _reads_the_experiment(n)]
    assert found == ["geometry.experiment"]


def test_the_experiment_rule_sees_a_parameter():
    """The rule above finds `exp` and an `Experiment` annotation wherever the parameter stands."""
    code = ("def a(exp): pass\n"
            "def b(x, *, e: Experiment): pass\n"
            "def c(x, e: 'vdo.config.experiment.Experiment' = None): pass\n"
            "f = lambda exp: exp\n"
            "def d(evaluation, exps, experiment_path): pass\n")
    found = [(getattr(n, "name", "<lambda>"), _takes_the_experiment(n))
             for n in ast.walk(ast.parse(code))
             if isinstance(n, (ast.FunctionDef, ast.Lambda))]
    assert sorted(found) == [("<lambda>", ["exp"]), ("a", ["exp"]), ("b", ["e"]), ("c", ["e"]),
                             ("d", [])]


def test_the_files_run_first_are_test_files():
    """conftest's HEAVY_FIRST (the schedule's first files) names files that exist."""
    from conftest import HEAVY_FIRST

    root = Path(__file__).resolve().parents[1]
    assert [name for name in HEAVY_FIRST if not (root / name).is_file()] == []
