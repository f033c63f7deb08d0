"""`vdo.configure()`: the persistent compilation cache under vdo's cache folder serves a second
process; settings are idempotent; the cache folder follows VDO_CACHE_DIR / XDG_CACHE_HOME."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax

from vdo.core.configure import cache_dir, configure

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import json, jax
from jax import monitoring
events = {}
monitoring.register_event_listener(lambda name, **kw: events.__setitem__(name, events.get(name, 0) + 1))
import vdo
vdo.configure()
vdo.configure()  # idempotent
import numpy as np
from vdo import objective
A = np.array([[[800.0, 30.0], [-20.0, 900.0]]])
from vdo.model.speckle import generate_pattern, gradient_energy_table, normalise
table = gradient_energy_table(normalise(generate_pattern(64, 1e-4, 4e-4, seed=1)), 1e-4, n=12)
T = objective.gradient_tensor(A, objective.TableEnergy(table))
print(json.dumps({"dir": jax.config.jax_compilation_cache_dir, "x64": jax.config.jax_enable_x64,
                  "dtype": str(T.dtype), "hits": events.get("/jax/compilation_cache/cache_hits", 0),
                  "misses": events.get("/jax/compilation_cache/cache_misses", 0)}))
"""


def run(env):
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_process_loads_compiled_programs_from_the_cache(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["VDO_CACHE_DIR"] = str(tmp_path / "cache")
    first = run(env)
    assert first["dir"] == str(tmp_path / "cache" / "jax")
    assert first["x64"] and first["dtype"] == "float64"
    assert first["hits"] == 0 and first["misses"] >= 1
    stored = list((tmp_path / "cache" / "jax").iterdir())
    assert stored
    second = run(env)
    assert second["hits"] >= 1 and second["misses"] == 0
    assert sorted(p.name for p in (tmp_path / "cache" / "jax").iterdir()) == sorted(p.name for p in stored)


def test_a_cache_folder_already_chosen_is_kept(monkeypatch, tmp_path):
    """This session's (conftest's configure(), or JAX_COMPILATION_CACHE_DIR) stays."""
    chosen = jax.config.jax_compilation_cache_dir
    assert chosen is not None
    monkeypatch.setenv("VDO_CACHE_DIR", str(tmp_path / "vdo"))
    configure()
    assert jax.config.jax_compilation_cache_dir == chosen and jax.config.jax_enable_x64
    assert not (tmp_path / "vdo").exists()


def test_cache_folder(monkeypatch, tmp_path):
    monkeypatch.delenv("VDO_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "vdo"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_dir() == Path.home() / ".cache" / "vdo"
    monkeypatch.setenv("VDO_CACHE_DIR", "~/elsewhere")
    assert cache_dir() == Path.home() / "elsewhere"
