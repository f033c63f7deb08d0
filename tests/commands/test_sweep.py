"""`vdo sweep`: grids, zips and draws; bad input; kill and resume; Dask against the local pool;
coverage columns against the closed-form footprints of two cameras looking straight down."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from vdo.core.errors import ConfigError
from vdo.commands.sweep import _run_local, pareto_front, run_point, sweep
from vdo.config.sweep import combinations, expand, load_sweep, split_path

ROOT = Path(__file__).resolve().parents[2]
from conftest import CAMERAS, HEIGHT, SENSOR  # noqa: E402  (the two rail cameras over the plate)

SWEEP = """
[sweep]
experiment = "plate.toml"
{extra}

[[axis]]
path = "camera.*.focal_mm"
values = [16, 24]

[[axis]]
path = "speckle.dot_diameter_mm"
values = [2, 3]

[[axis]]
path = "speckle.tile_texels"
values = [256]

[[axis]]
path = "render.ambient_radiance"
values = [20.0]
"""


@pytest.fixture
def plate_sweep(plate_experiment, tmp_path):
    def make(extra="", text=SWEEP, name="sweep.toml"):
        plate_experiment(spacing=25, height=HEIGHT, cameras=CAMERAS)
        path = tmp_path / name
        path.write_text(textwrap.dedent(text.format(extra=extra)))
        return path

    return make


def read_table(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def without_times(rows):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def footprint_fractions(focal_mm: float) -> tuple[float, float]:
    """Plate area fractions inside >= 1 and both usable square footprints (closed form). A view
    is usable where its image-edge weight S((u + 1/2) / m) >= 1/2 (`vdo.physics.usable`), i.e. m/2 pixels
    inside each image edge: the footprint loses m of its 300 pixels per side."""
    from vdo.objective import Settings

    margin_px = Settings().image_margin_px
    half = SENSOR / focal_mm * HEIGHT / 2 * (1 - margin_px / 300)

    def clip(lo, hi):
        return max(0.0, min(hi, 0.5) - max(lo, -0.5))

    y = clip(-half, half)
    union = clip(min(-0.3 - half, 0.3 - half), max(-0.3 + half, 0.3 + half))
    both = clip(0.3 - half, -0.3 + half)
    return union * y, both * y


# --------------------------------------------------------------------------------------------
# The sweep file
# --------------------------------------------------------------------------------------------
def test_paths_grids_zips_and_draws(plate_sweep, tmp_path):
    assert split_path('camera."cam.1".focal_mm') == ("camera", "cam.1", "focal_mm")
    assert split_path("evaluation..patch_mm") is None
    spec = load_sweep(plate_sweep(text="""
[sweep]
experiment = "plate.toml"
[[axis]]
path = "evaluation.patch_mm"
range = [10, 30, 10]
[[axis]]
path = "camera.left.focal_mm"
values = [16, 24]
zip = "lens"
[[axis]]
path = "camera.right.focal_mm"
values = [17, 25]
zip = "lens"
[[axis]]
path = "speckle.dot_diameter_mm"
linspace = [1.0, 2.0, 3]
"""))
    combos = combinations(spec)
    assert len(combos) == 3 * 2 * 3
    assert combos[0] == {"evaluation.patch_mm": 10, "camera.left.focal_mm": 16,
                         "camera.right.focal_mm": 17, "speckle.dot_diameter_mm": 1.0}
    assert {(c["camera.left.focal_mm"], c["camera.right.focal_mm"]) for c in combos} == {(16, 17), (24, 25)}
    assert sorted({c["speckle.dot_diameter_mm"] for c in combos}) == [1.0, 1.5, 2.0]
    points = expand(spec)
    assert len({p.key for p in points}) == len(points)
    left = next(c for c in points[0].config["camera"] if c["name"] == "left")
    assert left["focal_mm"] == 16 and points[0].config["evaluation"]["patch_mm"] == 10
    assert Path(points[0].config["mesh"][0]["file"]).is_absolute()

    random = plate_sweep(text="""
[sweep]
experiment = "plate.toml"
samples = 50
seed = 3
[[axis]]
path = "evaluation.patch_mm"
uniform = [5, 20]
[[axis]]
path = "speckle.strokes"
integers = [0, 4]
""")
    first, again = combinations(load_sweep(random)), combinations(load_sweep(random))
    assert first == again and len(first) == 50
    assert all(5 <= c["evaluation.patch_mm"] <= 20 for c in first)
    assert {c["speckle.strokes"] for c in first} == {0, 1, 2, 3, 4}


def test_pareto_front():
    x = [1, 1, 2, 3, 3, 4]
    y = [5, 4, 4, 1, 2, 0.5]
    assert pareto_front(*map(__import__("numpy").asarray, (x, y))).tolist() == [1, 3, 5]


@pytest.mark.parametrize("path, expected", [
    ("evaluation.patch_size", "names no field of plate.toml (evaluation.patch_size: unknown field; "
                              "did you mean 'patch_mm'?)"),
    ("camera.cam9.focal_mm", "no [[camera]] named 'cam9' (there are: left, right)"),
    ("camera.left.focus_distance", "names no field of plate.toml"),
    ("evaluation", "is not a field path"),
    ("lens.focal_mm", "names no field of plate.toml (lens: unknown field"),
])
def test_bad_axis_path_is_one_line_before_any_work(plate_sweep, tmp_path, path, expected):
    file = plate_sweep(text=f'[sweep]\nexperiment = "plate.toml"\n[[axis]]\npath = "{path}"\nvalues = [1]\n')
    with pytest.raises(ConfigError) as err:
        sweep(load_sweep(file), tmp_path / "out")
    assert expected in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()


def test_every_point_invalid_fails_the_sweep(plate_sweep, tmp_path):
    file = plate_sweep(text='[sweep]\nexperiment = "plate.toml"\n[[axis]]\n'
                            'path = "evaluation.patch_mm"\nvalues = [-1, 0]\n')
    with pytest.raises(ConfigError, match=r"point 0 .*patch_mm: must be positive \(got -1\)"):
        sweep(load_sweep(file), tmp_path / "out")


def test_max_points_below_one_is_one_line(plate_sweep, tmp_path):
    with pytest.raises(ConfigError, match=r"--max-points: must be at least 1 \(got 0\)"):
        sweep(load_sweep(plate_sweep()), tmp_path / "bad", max_points=0)
    assert not (tmp_path / "bad").exists()


def test_refuses_a_folder_that_is_not_a_sweep(plate_sweep, tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "thesis.tex").write_text("keep me")
    with pytest.raises(ConfigError, match="not a vdo sweep"):
        sweep(load_sweep(plate_sweep()), tmp_path / "out")


def test_unreachable_dask_address_is_one_quick_line(plate_sweep, tmp_path):
    started = time.perf_counter()
    with pytest.raises(ConfigError, match="cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'"):
        sweep(load_sweep(plate_sweep()), tmp_path / "out", dask="tcp://127.0.0.1:9",
              connect_timeout=2)
    assert time.perf_counter() - started < 20
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# Running: kill and resume, Dask against the pool, numbers against the closed form
# --------------------------------------------------------------------------------------------
def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def done_files(folder: Path) -> dict:
    """key -> (mtime_ns, finished) of the points stored as done."""
    out = {}
    for f in (folder / "points").glob("*.json"):
        record = json.loads(f.read_text())
        if record["status"] == "done":
            out[f.stem] = (f.stat().st_mtime_ns, record["finished"])
    return out


def test_kill_resume_trial_dask_and_closed_form(plate_sweep, tmp_path):
    """A trial of two points (--max-points 2) on the local pool, then the rest on a Dask
    LocalCluster; one run on the local pool killed midway (SIGKILL) and resumed: the same table,
    no finished point recomputed. The resumed run also writes the run folders of the points it
    computes (`vdo evaluate`'s summary), the others came from the summary without a run folder:
    the same numbers."""
    spec = load_sweep(plate_sweep())
    n_valid = 4

    # 1. a trial of two points: the first two in the table's order run, the other two stay
    # pending; the second run, on Dask, computes those two alone
    trial = sweep(spec, tmp_path / "trial", workers=1, max_points=2)
    assert (trial["points"], trial["done"], trial["pending"], trial["computed"]) == (4, 2, 2, 2)
    assert [r["status"] for r in read_table(tmp_path / "trial" / "results.csv")] == \
        ["done", "done", "pending", "pending"]
    rest = sweep(spec, tmp_path / "trial", workers=1, dask="local")
    assert (rest["done"], rest["pending"], rest["computed"], rest["reused"]) == (4, 0, 2, 2)
    table = read_table(tmp_path / "trial" / "results.csv")
    assert [r["status"] for r in table] == ["done"] * 4
    assert sorted(f.name for f in (tmp_path / "trial" / "figures").iterdir()) == [
        "axis1_camera.all.focal_mm.png", "axis2_speckle.dot_diameter_mm.png"]
    assert not (tmp_path / "trial" / "dask-scratch").exists()

    # 2. coverage columns against the footprints (sample spacing 25 mm)
    for r in table[:4]:
        one, two = footprint_fractions(float(r["camera.*.focal_mm"]))
        assert float(r["top.seen_1"]) == pytest.approx(one, abs=0.03)
        assert float(r["top.seen_2"]) == pytest.approx(two, abs=0.03)
        assert float(r["top.sigma_p95_um"]) > float(r["top.sigma_p50_um"]) > 0

    # 3. the local pool, SIGKILLed once two points are stored
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "vdo", "sweep", str(spec.path), "--out",
                             str(tmp_path / "killed"), "--workers", "1", "--quiet"],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while len(done_files(tmp_path / "killed")) < 2:
        assert proc.poll() is None and time.time() < deadline, proc.stderr.read().decode()[-2000:]
        time.sleep(0.02)
    workers = children(proc.pid)
    proc.kill()
    proc.wait()
    proc.stderr.close()
    before = done_files(tmp_path / "killed")
    assert 2 <= len(before) < n_valid, "the sweep finished before it could be killed"
    for pid in workers:                    # the pool's workers leave with the sweep process
        for _ in range(100):
            if not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text():
                break
            time.sleep(0.1)
        else:
            os.kill(pid, signal.SIGKILL)
            pytest.fail(f"worker {pid} outlived the killed sweep")
    partial = read_table(tmp_path / "killed" / "results.csv")   # whole, never half-written
    assert len(partial) == 4 and sum(r["status"] == "done" for r in partial) >= len(before) - 1

    # 4. resumed (with run folders: not part of a point's key): only the missing points run,
    # and the table is the trial's
    with_folders = load_sweep(plate_sweep(extra="run_folders = true", name="folders.toml"))
    resumed = sweep(with_folders, tmp_path / "killed", workers=1)
    assert resumed["reused"] == len(before) and resumed["computed"] == n_valid - len(before)
    after = done_files(tmp_path / "killed")
    assert all(after[k] == v for k, v in before.items()), "a finished point was recomputed"
    assert len(after) == n_valid
    folders = {f.name for f in (tmp_path / "killed" / "runs").iterdir()}
    assert folders == set(after) - set(before)
    assert all((tmp_path / "killed" / "runs" / k / "summary.json").is_file() for k in folders)
    assert without_times(read_table(tmp_path / "killed" / "results.csv")) == without_times(table)


OPTIMIZE_SWEEP = """
[sweep]
experiment = "plate.toml"
action = "optimize"

[[axis]]
path = "evaluation.sample_spacing_mm"
values = [50]

[[axis]]
path = "optimize.starts"
values = [1]

[[axis]]
path = "optimize.rounds"
values = [1]

[[axis]]
path = "optimize.max_steps"
values = [2]

[[axis]]
path = "render.ambient_radiance"
values = [20.0]
"""


def test_an_optimize_point_reports_the_layout_its_run_folder_holds(plate_sweep, tmp_path):
    """action = "optimize": the point's row and stored summary come from the result `optimize`
    returns, in memory; they are what its run folder's summary_after.json and optimizer.json hold
    (the summary byte for byte), as when they were read back from there."""
    points = expand(load_sweep(plate_sweep(text=OPTIMIZE_SWEEP)), tmp_path / "store")
    record = run_point(points[0])
    assert record["status"] == "done", record["error"]
    folder = Path(points[0].run_dir)
    text = (folder / "summary_after.json").read_text()
    assert json.dumps(record["summary"], indent=2) + "\n" == text
    after, m = json.loads(text), record["metrics"]
    assert (m["n_cameras"], m["n_samples"]) == (2, after["settings"]["n_samples"])
    assert m["top.sigma_p95_um"] > 0        # measured somewhere: the numbers compared are numbers
    for stat in ("p50", "p95", "max"):
        assert m[f"top.sigma_{stat}_um"] == after["regions"]["top"]["sigma_max_um"][stat]
    assert [m[f"top.seen_{k}"] for k in (1, 2, 3)] == [after["regions"]["top"][f"seen_by_{k}_or_more"]
                                                      for k in (1, 2, 3)]
    assert "top.eps_uu_p95_ue" not in m       # optimize's summaries hold no strain σ
    optimizer = json.loads((folder / "optimizer.json").read_text())
    assert m["score_before"] == optimizer["score_before"]["score_um"]
    assert m["violations"] == json.loads((folder / "constraints.json").read_text())["violations"]


def test_a_dead_worker_is_replaced(plate_sweep):
    """Kill the pool's worker while it starts: its points run again in a fresh pool."""
    points = expand(load_sweep(plate_sweep(text='[sweep]\nexperiment = "plate.toml"\n[[axis]]\n'
                                                 'path = "evaluation.patch_mm"\nvalues = [-1, -2]\n')))
    killed, earlier = [], set(children(os.getpid()))

    def kill_first_worker():
        deadline = time.time() + 60
        while not killed and time.time() < deadline:
            for pid in set(children(os.getpid())) - earlier:
                if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text():
                    time.sleep(0.3)
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    break
            time.sleep(0.02)

    thread = threading.Thread(target=kill_first_worker)
    thread.start()
    results = list(_run_local(points, workers=1, threads=1))
    thread.join()
    assert killed and len(results) == 2
    for point, record in results:
        assert record["pid"] != killed[0]
        assert f"patch_mm: must be positive (got {point.axes['evaluation.patch_mm']})" in record["error"]


def test_vdo_set_is_part_of_each_point(plate_sweep, monkeypatch):
    """A coarse run (VDO_SET) is other points than the full run: its values are in each point's
    config and key, over the axis values, so a store never mixes them."""
    spec = load_sweep(plate_sweep())
    full = expand(spec)
    monkeypatch.setenv("VDO_SET", "evaluation.sample_spacing_mm = 80; camera.*.focal_mm = 35")
    coarse = expand(spec)
    assert len(coarse) == len(full) == 4
    assert not {p.key for p in coarse} & {p.key for p in full}
    for p in coarse:
        assert p.config["evaluation"]["sample_spacing_mm"] == 80
        assert [c["focal_mm"] for c in p.config["camera"]] == [35, 35]
