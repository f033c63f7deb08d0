"""The virtual test: a specimen under a closed-form displacement field, rendered as an image
series (`vdo render --series`), then measured by vdo's own correlation on the exported images and
compared with the imposed field and the predicted uncertainty; the folder's OpenCV calibration
files re-projected against its layout.json. By default the built-in beam-column; `--experiment`
takes any experiment file.

    python docs/examples/virtual_test.py --out runs/virtual_test [--scale 1] [--spp 16]
    python docs/examples/virtual_test.py --out /tmp/vt --quick     # 2 cropped cameras (the test)
    python docs/examples/virtual_test.py --out /tmp/vt --quick --dot-mm 0.25 --texel-mm 0.05
    python docs/examples/virtual_test.py --out /tmp/vt --quick \
        --experiment experiments/pressure_vessel/all_round.toml [--pair t030 t080]
    python docs/examples/virtual_test.py --out runs/vt_full --steps 4 --mode dic --realisations 1

`--steps N`: the field grows linearly over N load steps; each step is correlated against the
reference from the correlation's own start guesses, and a point that does not converge is
correlated again from the previous step's result (a lab re-seeds a lost point so).
`--mode dic`: the DIC render mode (full-size images in minutes).

Another experiment's field is general (`general_field`): about the centre c of the specimen's
bounding box and its size S (the box's diagonal), a translation S x GENERAL_TRANSLATION, a turn
by GENERAL_TURN about the vertical axis through c and a uniform stretch GENERAL_STRAIN along the
box's longest horizontal axis e:

    u = S t + phi e_z x (X - c) + eps ((X - c) . e) e

an affine field, which the mesh's vertices carry exactly. Its pair: `--pair`, else the two cameras
that share the most usable samples; `--quick` crops them around the sample nearest the centroid
of those samples.

The field (metres; joint centre c = (0, 0, 1.2), beam along +y from its root y0 = 0.06 to its
end y0 + L, L = 1 m, s = clip((y - y0) / L, 0, 1)): a rigid motion of the whole specimen, a
translation T plus a turn by phi about the vertical axis through c, and the Euler-Bernoulli
bending of a cantilever beam under an end load, with end deflection delta (down) and so an end
rotation of 3 delta / (2 L) about x:

    u = T + phi e_z x (X - c) + (0, -(z - c_z) w'(y), w(y)),  w = -delta (3 s^2 - s^3) / 2

The specimen mesh is refined to edges of at most `EDGE_MM` (so that the rendered surface follows
the cubic bending; vdo moves the mesh's vertices) and the field is written at its vertices as a
VTK file (`[load_path] displacements`, `vdo.geometry.keyframes`). Points: samples of every stereo pair's
regions that both cameras use with their whole patch, grown by EDGE_MARGIN_PX pixels (no pixel
the correlation reads on another face); predicted sigma from the layout state of
the pair alone at the rendered scale, times sqrt(2) (reference and deformed images are both
noisy); only points whose patch corners, at rest and moved, lie inside both (cropped) images.
The whole error must be within 3 such sigmas on every axis; it is split into the bias (the same
correlation on the noise-free images, the series' .exr radiance through the sensor's mean) and the
noise part (TIFF minus noise-free). Beside it, sigma_measured of the same pair (the [analysis]
processing: the interpolation bias over sub-pixel positions, its scatter and the noise through
the interpolant, `LayoutState.measured`) and the count within 3 sigma_measured. With fine sharp
dots (`--dot-mm 0.25 --texel-mm 0.05`: 2 px dots at the cameras' own pixels) the bias dominates:
the bound alone fails and sigma_measured holds (docs/exports.md). These cameras have no
f_number: sigma_measured and the renders both take them as f/8 lenses in focus (docs/render.md).

The series is rendered at the cameras' own pixels (`--scale 1`, the default here, as a lab's DIC
software would get them). At a reduced scale the bias is the correlation's interpolation floor:
at the built-in's [render] scale 0.25 (0.47 mm/px on the joint) the 2 mm dots are 4.3 px with
edges a quarter of a pixel wide, their content above the pixel's Nyquist frequency aliases, the
interpolation error is ~9x the sensor noise and the bias (0.008-0.02 px) is several sqrt(2) sigma
(measured change by change in docs/exports.md: not the renderer, the solver or the spline
order). The run prints `vdo.physics.checks`' interpolation floor of its cameras at the rendered scale;
at scale 1 (0.116 mm/px) it is ~1x the noise and the bias 0.0006-0.002 px. Needs opencv-python
(the test extra) for the calibration check.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

import vdo

HERE = Path(__file__).resolve().parent
EXPERIMENT = HERE.parent.parent / "experiments" / "beam_column" / "ten_cameras.toml"
CENTRE = np.array([0.0, 0.0, 1.2])          # m, the joint
BEAM_ROOT, BEAM_LENGTH = 0.06, 1.0          # m
TRANSLATION = np.array([0.6, -0.4, 0.8]) * 1e-3   # m
TURN = math.radians(0.15)                   # about z through the joint
END_DEFLECTION = 3e-3                       # m, down, at the beam end
EDGE_MM = 25.0                              # refined specimen mesh
N_SIGMA = 3.0
SCALE = 1.0                                 # the cameras' own pixels (module docstring)
BIAS_FLOOR_PX = 0.005                       # interpolation bias at scale 1 (docs/exports.md)
QUICK_PAIR = ("cam1", "cam2")               # the 100 mm lenses on the joint, from the front, above
QUICK_CROP_PX = (320, 240)                  # full-size pixels around the joint top's centre
FOCUS_POINT = np.array([0.0, 0.0, 1.26])    # m, the joint top's centre (the crops' centre)
EDGE_MARGIN_PX = 4.0                        # a point's patch grown by this many pixels of its
                                            # coarser camera must still lie on its region: the
                                            # pixels the correlation reads (the patch, the
                                            # cubic spline's reach, the lens's blur, a pixel
                                            # that straddles an edge) all on one face
WHOLE_PATCH_TOL = 1e-9                      # a patch fraction this close to 1 is whole (a sum of
                                            # cell areas: 0.9999999999999999 on a curved surface)
GENERAL_TRANSLATION = np.array([0.5, -0.3, 0.4]) * 1e-3   # per metre of the specimen's size
GENERAL_TURN = math.radians(0.1)            # about the vertical axis through the box's centre
GENERAL_STRAIN = 1e-3                       # along the box's longest horizontal axis


def imposed(X: np.ndarray) -> np.ndarray:
    """The closed-form displacement (N, 3) m at rest points X (N, 3) m (module docstring)."""
    X = np.atleast_2d(X)
    rel = X - CENTRE
    s = np.clip((X[:, 1] - BEAM_ROOT) / BEAM_LENGTH, 0.0, 1.0)
    w = -END_DEFLECTION * (3 * s ** 2 - s ** 3) / 2
    dw = -END_DEFLECTION * (6 * s - 3 * s ** 2) / (2 * BEAM_LENGTH)
    u = TRANSLATION + TURN * np.column_stack([-rel[:, 1], rel[:, 0], np.zeros(len(X))])
    return u + np.column_stack([np.zeros(len(X)), -rel[:, 2] * dw, w])


def general_field(points: np.ndarray):
    """The affine field of the module docstring for a specimen whose mesh points (N, 3) m are
    given: a function of rest points X (N, 3) m returning displacements (N, 3) m."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    axis = np.eye(3)[int(np.argmax((hi - lo)[:2]))]                 # longest horizontal axis

    def field(X: np.ndarray) -> np.ndarray:
        rel = np.atleast_2d(X) - centre
        turn = GENERAL_TURN * np.column_stack([-rel[:, 1], rel[:, 0], np.zeros(len(rel))])
        return size * GENERAL_TRANSLATION + turn + GENERAL_STRAIN * np.outer(rel @ axis, axis)
    return field


def inputs(folder: Path, exp, field, refine_mm: float | None, steps: int = 1):
    """The specimen STL (refined to edges of at most `refine_mm`, or as it is) and the field at
    its vertices (.vtp, mm) in `folder`; the experiment using them (its [load_path] only these
    displacements). With `steps` > 1 the field grows linearly, k / steps of it at step k
    (field_<k>.vtp, gathered by field.pvd)."""
    import trimesh

    from vdo.config import experiment as config
    from vdo.core import vtp

    folder.mkdir(parents=True, exist_ok=True)
    spec = specimen_mesh(exp)
    mesh = trimesh.load(spec.path, force="mesh")
    vertices, faces = mesh.vertices, mesh.faces
    if refine_mm is not None:
        vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=refine_mm)
    trimesh.Trimesh(vertices, faces, process=False).export(folder / "specimen_refined.stl")
    nodes = np.unique(vertices * spec.scale, axis=0)
    if steps == 1:
        vtp.write_points(folder / "field.vtp", nodes / 1e-3, {"displacement": field(nodes) / 1e-3})
        displacements = folder / "field.vtp"
    else:
        sets = []
        for k in range(1, steps + 1):
            vtp.write_points(folder / f"field_{k}.vtp", nodes / 1e-3,
                             {"displacement": field(nodes) * (k / steps) / 1e-3})
            sets.append(f'    <DataSet timestep="{k}" file="field_{k}.vtp"/>')
        displacements = folder / "field.pvd"
        displacements.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n'
                                 "  <Collection>\n" + "\n".join(sets) + "\n  </Collection>\n</VTKFile>\n")
    meshes = tuple(dataclasses.replace(m, path=folder / "specimen_refined.stl") if m is spec else m
                   for m in exp.meshes)
    load_path = config.LoadPathSpec(displacements=displacements, deformed_mesh=spec.name,
                                    unit="mm")
    return dataclasses.replace(exp, meshes=meshes, load_path=load_path)


def specimen_mesh(exp):
    """The mesh the regions lie on (the built-in's "specimen"): the mesh of the first region."""
    names = {m.name: m for m in exp.meshes}
    return names.get("specimen") or names[exp.regions[0].mesh]


def pair_and_focus(exp, pair=None):
    """(pair, focus point (3,) m): the two cameras named, else the two that share the most usable
    samples (the whole experiment judged at its own pixels); the sample nearest the centroid of
    the samples both use."""
    from vdo.state import layout_state, prepare

    names = [c.name for c in exp.camera_specs]
    unknown = [n for n in pair or () if n not in names]
    if unknown:
        raise SystemExit(f"--pair: no camera {unknown[0]!r} in {exp.path}; cameras: {', '.join(names)}")
    state = layout_state(prepare(exp))
    usable = state.prediction.usable
    if pair is None:
        shared = usable.astype(np.int64) @ usable.T.astype(np.int64)
        np.fill_diagonal(shared, -1)
        first, second = np.unravel_index(int(np.argmax(shared)), shared.shape)
        pair = (names[first], names[second])
    both = usable[names.index(pair[0])] & usable[names.index(pair[1])]
    if not both.any():
        raise SystemExit(f"--pair {pair[0]} {pair[1]}: the two cameras share no usable sample in "
                         f"{exp.path}; choose a pair that sees the same surface")
    points = state.samples.points[both]
    return tuple(pair), points[int(np.argmin(np.linalg.norm(points - points.mean(axis=0), axis=1)))]


def cropped(exp, names, crop_px, focus=FOCUS_POINT):
    """The experiment with only the cameras `names`, each cropped to `crop_px` full-size pixels
    centred on the projection of `focus` (the built-in: the joint top's centre; same pixels,
    shifted principal point)."""
    cameras = {c.name: c for c in vdo.cameras_of(exp.camera_specs, exp.rails)}
    specs = []
    for spec in exp.camera_specs:
        if spec.name not in names:
            continue
        cam = cameras[spec.name]
        centre = cam.project(np.asarray(focus, dtype=float)[None])[0]
        width, height = crop_px
        x0, y0 = np.rint(centre - np.array([width, height]) / 2)
        cx, cy = cam.principal_point
        offset = (float(cx - x0 - (width - 1) / 2), float(cy - y0 - (height - 1) / 2))
        specs.append(dataclasses.replace(spec, pixels=(width, height),
                                         sensor_width=cam.pixel_size * width,
                                         principal_offset_px=offset))
    return exp.with_cameras(specs)


def points_of_pair(state, first: int, second: int, per_region: int, motion=None,
                   margin_px: float = 3.0):
    """Sample indices the two cameras both use with their whole patch, up to `per_region` per
    region, spread over it (farthest-point order from the sample nearest the region's centre).
    The patch grown by EDGE_MARGIN_PX pixels of the coarser camera must lie on the region too:
    next to a specimen's edge the correlation's pixels straddle another face (another light, a
    silhouette), which the planar patch that sigma describes does not have (measured at full
    size on the built-in: errors of 5-13 sigma_measured at 5 mm from the joint's lower edges,
    docs/exports.md).
    The patch's four corners, at rest and moved by `motion` (N, 3) m (the sample's displacement),
    must lie `margin_px` inside both images: the usable test looks at the sample only, and a patch
    that leaves a (cropped) image is correlated on a part of itself against mirrored pixels."""
    pred, samples = state.prediction, state.samples
    ok = pred.usable[first] & pred.usable[second] & pred.measured \
        & (pred.patch_fraction >= 1.0 - WHOLE_PATCH_TOL)
    patch = state.geometry.experiment.evaluation.patch_size
    half = patch / 2
    if ok.any():
        from vdo.physics.usable import patch_overlap

        pixel = np.max([np.linalg.norm(samples.points - cam.position, axis=1) / cam.focal_px
                        for cam in (state.cameras[first], state.cameras[second])], axis=0)
        grown = patch + 2 * EDGE_MARGIN_PX * float(pixel[ok].max())
        on_region = np.asarray(patch_overlap(samples, grown).sum(axis=1)).ravel()
        ok &= on_region >= 1.0 - WHOLE_PATCH_TOL
    motion = np.zeros_like(samples.points) if motion is None else motion
    for cam in (state.cameras[first], state.cameras[second]):
        for su in (-half, half):
            for sv in (-half, half):
                corner = samples.points + su * samples.tangent_u + sv * samples.tangent_v
                for x in (cam.project(corner), cam.project(corner + motion)):
                    ok &= ((x[:, 0] >= margin_px) & (x[:, 0] <= cam.width - 1 - margin_px)
                           & (x[:, 1] >= margin_px) & (x[:, 1] <= cam.height - 1 - margin_px))
    chosen = []
    for region in np.unique(samples.region[ok]):
        idx = np.flatnonzero(ok & (samples.region == region))
        pts = samples.points[idx]
        pick = [int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
        while len(pick) < min(per_region, len(idx)):
            d = np.min(np.linalg.norm(pts[:, None] - pts[pick][None], axis=2), axis=1)
            pick.append(int(np.argmax(d)))
        chosen += [int(idx[p]) for p in pick]
    return chosen


def calibration_error(folder: Path) -> float:
    """Largest difference (px) between cv2.projectPoints with the values cv2.FileStorage reads
    from calibration/opencv/<camera>.yml and the projection by layout.json's K, R, t and
    distortion (OpenCV's model written out here), over points in front of each camera."""
    import cv2

    rng = np.random.default_rng(0)
    worst = 0.0
    for entry in json.loads((folder / "layout.json").read_text())["cameras"]:
        K, R, t = (np.asarray(entry[k], float) for k in ("K", "R", "t"))
        k1, k2, p1, p2, k3 = entry.get("distortion", [0.0] * 5)
        pc = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.2, 0.2, 50),
                              rng.uniform(1.0, 3.0, 50)])
        X = (pc - t) @ R                                    # world points (m)
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xd, yd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        mine = np.column_stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]])
        fs = cv2.FileStorage(str(folder / "calibration" / "opencv" / f"{entry['name']}.yml"),
                             cv2.FILE_STORAGE_READ)
        rvec = cv2.Rodrigues(fs.getNode("R").mat())[0]
        theirs = cv2.projectPoints(X * 1e3, rvec, fs.getNode("t").mat(), fs.getNode("camera_matrix").mat(),
                                   fs.getNode("distortion_coefficients").mat())[0].reshape(-1, 2)
        fs.release()
        worst = max(worst, float(np.abs(theirs - mine).max()))
    return worst


def run(out: Path, quick: bool = False, scale: float = SCALE, spp: int | None = None,
        per_region: int = 2, realisations: int = 4, overwrite: bool = False,
        crop_px: tuple[int, int] = QUICK_CROP_PX, dot_mm: float | None = None,
        texel_mm: float | None = None, experiment: Path = EXPERIMENT, pair=None, steps: int = 1,
        mode: str | None = None) -> dict:
    """Render the series and measure it (module docstring). Per point: the error of the series'
    own TIFFs, split into the bias (the same correlation on the noise-free images, the .exr
    radiance through the sensor's mean) and the noise part (TIFF minus noise-free), which
    √2 sigma predicts; and the mean noise part over `realisations` sensor-noise draws on the
    same radiance (the TIFF's and realisations - 1 more, `SensorModel.expose`). `steps` load
    steps (the field grows linearly to its whole at the last), each correlated against the
    reference; `mode`: the [render] mode (default the experiment's). Returns {"rows": [...]
    (one per point and step), "calibration_px": float, "series": series.json}."""
    from vdo.config import experiment as config
    from vdo.geometry.keyframes import at_step, load_path_of
    from vdo.render import scaled_camera
    from vdo.commands.series import render_series
    from vdo.dic.series import series_cameras, series_image
    from vdo.state import layout_state, prepare

    out = Path(out)
    builtin = Path(experiment).resolve() == EXPERIMENT
    exp = config.load(experiment)
    if dot_mm is not None or texel_mm is not None:     # another speckle: e.g. fine sharp dots
        sp = exp.speckle
        exp = dataclasses.replace(exp, speckle=dataclasses.replace(
            sp, dot_diameter=sp.dot_diameter if dot_mm is None else dot_mm * 1e-3,
            texel=sp.texel if texel_mm is None else texel_mm * 1e-3))
        sp = exp.speckle
        if not 0 < 3 * sp.texel <= sp.dot_diameter:   # the [speckle] rule: round dots need 3 texels
            raise SystemExit(f"--dot-mm {sp.dot_diameter * 1e3:g} / --texel-mm {sp.texel * 1e3:g}: "
                             "both > 0 and the texel at most a third of the dot")
    if builtin:
        field, refine_mm, pair, focus = imposed, EDGE_MM, tuple(pair or QUICK_PAIR), FOCUS_POINT
        if pair != QUICK_PAIR:
            pair, focus = pair_and_focus(exp, pair)
    else:
        import trimesh

        spec = specimen_mesh(exp)
        field, refine_mm = general_field(trimesh.load(spec.path, force="mesh").vertices * spec.scale), None
        pair, focus = pair_and_focus(exp, pair)
    if quick:
        exp = cropped(exp, pair, crop_px, focus)
    exp = inputs(out.with_name(out.name + "_inputs"), exp, field, refine_mm, steps)
    exp = dataclasses.replace(exp, render=dataclasses.replace(exp.render, exr=True,
                                                              mode=mode or exp.render.mode))
    summary = render_series(exp, out, scale=scale, spp=spp, overwrite=overwrite,
                            pairs=[pair] if quick or not builtin else None)
    geometry = prepare(exp)
    load_path = load_path_of(geometry.meshes, load_path_spec=exp.load_path, mesh_specs=exp.meshes,
                             groups=exp.groups)
    moved = {k: at_step(geometry, load_path, k, regions=exp.regions).samples.points
             for k in range(1, steps + 1)}
    cameras = {c.name: scaled_camera(c, summary["scale"])
               for c in vdo.cameras_of(exp.camera_specs, exp.rails)}
    sensor, s, patch = exp.sensor, geometry.samples, exp.evaluation.patch_size
    rows, floor = [], []
    for first, second in summary["stereo_pairs"]:
        names = [first, second]
        state = layout_state(geometry, [cameras[first], cameras[second]])
        chosen = points_of_pair(state, 0, 1, per_region, moved[steps] - s.points)
        if not chosen:
            continue
        regions = {s.region_names[s.region[i]] for i in chosen}
        floor += [f for f in summary["interpolation"]   # series.json: the check at the rendered scale
                  if f["camera"] in names and f["region"] in regions and f not in floor]
        at = (s.points[chosen], s.tangent_u[chosen], s.tangent_v[chosen], patch)
        pair = series_cameras(out, names)
        sigma = math.sqrt(2) * state.prediction.sigma_xyz[chosen]
        sigma_measured = state.measured.sigma_xyz[chosen]      # [analysis]: bias, scatter, noise
        reference = [series_image(out, n, 0, linear=True) for n in names]
        previous = None                # a lost point is re-seeded from the last step's result
        for step in range(1, steps + 1):
            new, previous = _rows_of_step(out, summary, pair, names, reference, step, steps, at, chosen,
                                          moved[step], s, sensor, realisations, field, sigma,
                                          sigma_measured, first, second, previous)
            rows += new
    return {"rows": rows, "interpolation": floor, "calibration_px": calibration_error(out),
            "series": summary}


def _with_retry(correlate, at, previous):
    """`correlate(points, tangent_u, tangent_v, patch, start=...)` from the correlation's own
    start guesses; the points that do not converge are correlated again from `previous` (the
    last step's result, where it is finite), as a lab re-seeds a lost point from the step before."""
    U, converged = correlate(*at)
    retry = ~converged & (np.isfinite(previous).all(axis=1) if previous is not None else False)
    if np.any(retry):
        points, tangent_u, tangent_v, patch = at
        again, ok = correlate(points[retry], tangent_u[retry], tangent_v[retry], patch,
                              start=previous[retry])
        U[retry], converged[retry] = again, ok
    return U, converged


def _rows_of_step(out, summary, pair, names, reference, step, steps, at, chosen, moved, s, sensor,
                  realisations, field, sigma, sigma_measured, first, second, previous=None):
    """The rows of one load step of one pair (`run`), and what the next step falls back on: this
    step's results (noise-free and measured) where they converged. `previous`: the last step's
    (None at step 1), the start of a point that does not converge from the correlation's own
    start guess (`_with_retry`)."""
    from vdo.render import noise_free_dn
    from vdo.dic.series import correlate_points, correlate_series, series_image

    rows = []
    linear = {0: reference, step: [series_image(out, n, step, linear=True) for n in names]}
    clean_start, start = previous if previous is not None else (None, None)
    clean_images = [[noise_free_dn(x, sensor) for x in linear[k]] for k in (0, step)]
    clean, clean_converged = _with_retry(lambda *a, **k: correlate_points(pair, *clean_images, *a, **k),
                                         at, clean_start)
    measured, converged = _with_retry(lambda *a, **k: correlate_series(out, step, names, *a, **k),
                                      at, start)
    noise = [measured - clean]
    for r in range(1, realisations):
        draw = {k: [sensor.expose(x, np.random.default_rng([summary["seed"], 1000 + r, i, k]))
                    for i, x in enumerate(linear[k])] for k in (0, step)}
        noise.append(_with_retry(lambda *a, **k: correlate_points(pair, draw[0], draw[step], *a, **k),
                                 at, start)[0] - clean)
    mean_noise = np.mean(noise, axis=0)
    for k, i in enumerate(chosen):
        rendered = moved[i] - s.points[i]
        bias = clean[k] - rendered
        bias_px = max(float(np.abs(c.project((s.points[i] + clean[k])[None])[0]
                                   - c.project((s.points[i] + rendered)[None])[0]).max())
                      for c in pair)
        rows.append({"pair": f"{first}:{second}", "step": step,
                     "region": s.region_names[s.region[i]],
                     "point_mm": (s.points[i] * 1e3).round(1).tolist(),
                     "closed_form_um": (field(s.points[i])[0] * (step / steps) * 1e6).tolist(),
                     "rendered_um": (rendered * 1e6).tolist(),
                     "measured_um": (measured[k] * 1e6).tolist(),
                     "error_um": ((measured[k] - rendered) * 1e6).tolist(),
                     "bias_um": (bias * 1e6).tolist(), "bias_px": bias_px,
                     "noise_um": (noise[0][k] * 1e6).tolist(),
                     "mean_noise_um": (mean_noise[k] * 1e6).tolist(),
                     "realisations": len(noise), "sigma_um": (sigma[k] * 1e6).tolist(),
                     "ratio": float(np.max(np.abs(measured[k] - rendered) / sigma[k])),
                     "sigma_measured_um": (sigma_measured[k] * 1e6).tolist(),
                     "ratio_measured": float(np.max(np.abs(measured[k] - rendered)
                                                    / sigma_measured[k])),
                     "noise_ratio": float(np.max(np.abs(noise[0][k]) / sigma[k])),
                     "mean_noise_ratio": float(np.max(np.abs(mean_noise[k]) / sigma[k])
                                               * math.sqrt(len(noise))),
                     "converged": bool(converged[k])})
    following = (np.where(clean_converged[:, None], clean, np.nan),
                 np.where(converged[:, None], measured, np.nan))
    return rows, following


DETAIL_ROWS = 60        # print every point's table up to this many rows, else per pair and step


def print_table(result: dict) -> None:
    from vdo.physics import checks

    steps = sorted({r["step"] for r in result["rows"]})
    if len(steps) > 1 or len(result["rows"]) > DETAIL_ROWS:
        print(f"{'pair':<12}{'step':>5}{'points':>8}{'within 3 sqrt2 sig':>20}{'within 3 sig_meas':>19}"
              f"{'largest err/sig_meas':>22}{'|u| mean um':>13}")
        for key in dict.fromkeys((r["pair"], r["step"]) for r in result["rows"]):
            group = [r for r in result["rows"] if (r["pair"], r["step"]) == key]
            print(f"{key[0]:<12}{key[1]:>5}{len(group):>8}{sum(r['ratio'] <= N_SIGMA for r in group):>20}"
                  f"{sum(r['ratio_measured'] <= N_SIGMA for r in group):>19}"
                  f"{max(r['ratio_measured'] for r in group):>22.2f}"
                  f"{np.mean([np.linalg.norm(r['rendered_um']) for r in group]):>13.0f}")
        for step in steps:
            group = [r for r in result["rows"] if r["step"] == step]
            print(f"step {step}: {sum(r['ratio_measured'] <= N_SIGMA for r in group)} of {len(group)} "
                  f"points within {N_SIGMA:g} sigma_measured "
                  f"({100 * np.mean([r['ratio_measured'] <= N_SIGMA for r in group]):.1f} %), "
                  f"{sum(r['ratio'] <= N_SIGMA for r in group)} within {N_SIGMA:g} sqrt(2) sigma")
    else:
        _print_points(result["rows"])
    _print_totals(result)


def _print_points(rows) -> None:
    print(f"{'pair':<12}{'region':<16}{'axis':>5}{'closed form':>12}{'rendered':>10}{'measured':>10}"
          f"{'error':>8}{'bias':>8}{'noise':>8}{'mean noise':>11}{'sqrt2 sig':>10}{'noise/sig':>10}")
    for r in rows:
        for a, axis in enumerate("xyz"):
            print(f"{r['pair'] if a == 0 else '':<12}{r['region'] if a == 0 else '':<16}{axis:>5}"
                  f"{r['closed_form_um'][a]:>12.1f}{r['rendered_um'][a]:>10.1f}{r['measured_um'][a]:>10.1f}"
                  f"{r['error_um'][a]:>8.2f}{r['bias_um'][a]:>8.2f}{r['noise_um'][a]:>8.2f}"
                  f"{r['mean_noise_um'][a]:>11.2f}{r['sigma_um'][a]:>10.2f}"
                  f"{abs(r['noise_um'][a]) / r['sigma_um'][a]:>10.2f}")


def _print_totals(result: dict) -> None:
    from vdo.physics import checks

    rows = result["rows"]
    n = rows[0]["realisations"]
    print(f"bias (noise-free images): {min(r['bias_px'] for r in rows):.4f}-"
          f"{max(r['bias_px'] for r in rows):.4f} px in the images (floor {BIAS_FLOOR_PX} px); "
          f"{sum(r['ratio'] <= N_SIGMA for r in rows)} of {len(rows)} points' whole error within "
          f"{N_SIGMA:g} sqrt(2) sigma (largest {max(r['ratio'] for r in rows):.2f})")
    print(f"noise part (TIFF minus noise-free): {sum(r['noise_ratio'] <= N_SIGMA for r in rows)} of "
          f"{len(rows)} points within {N_SIGMA:g} sqrt(2) sigma on every axis (largest "
          f"{max(r['noise_ratio'] for r in rows):.2f}); mean of {n} draws within {N_SIGMA:g} "
          f"sqrt(2) sigma / sqrt({n}): {sum(r['mean_noise_ratio'] <= N_SIGMA for r in rows)} of "
          f"{len(rows)} (largest {max(r['mean_noise_ratio'] for r in rows):.2f}); displacements in um")
    print(f"sigma_measured ([analysis]: the interpolation bias, its scatter and the noise through "
          f"the interpolant): {sum(r['ratio_measured'] <= N_SIGMA for r in rows)} of {len(rows)} "
          f"points' whole error within {N_SIGMA:g} sigma_measured on every axis (largest "
          f"{max(r['ratio_measured'] for r in rows):.2f}); sigma_measured / sqrt(2) sigma "
          f"{min(min(np.divide(r['sigma_measured_um'], r['sigma_um'])) for r in rows):.1f}-"
          f"{max(max(np.divide(r['sigma_measured_um'], r['sigma_um'])) for r in rows):.1f}")
    for f in result["interpolation"]:
        print(f"design check at the rendered scale, {f['camera']} {f['region']}: "
              f"{f['mm_per_px']:.3f} mm/px, interpolation error {f['error_dn']:.0f} DN against a "
              f"sensor noise of {f['noise_dn']:.0f} DN ({f['ratio']:.1f}x"
              + (", flagged: bias-dominated)" if f["ratio"] > checks.INTERPOLATION_NOISE else ")"))
    print(f"calibration/opencv vs layout.json: largest re-projection difference "
          f"{result['calibration_px']:.2e} px")


def plot(result: dict, path: Path) -> None:
    """Measured against rendered displacement per axis (every point and step), and each point's
    largest |error| / sigma_measured against the 3 sigma line, as a PNG."""
    import matplotlib.pyplot as plt

    rows = result["rows"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    for a, (axis, marker) in enumerate(zip("xyz", "osD")):
        ax.plot([r["rendered_um"][a] for r in rows], [r["measured_um"][a] for r in rows], marker,
                ms=3, alpha=0.6, label=axis)
    lim = max(abs(v) for r in rows for v in r["rendered_um"]) * 1.1
    ax.plot([-lim, lim], [-lim, lim], "k-", lw=0.8)
    ax.set_xlabel("imposed (rendered) displacement (µm)")
    ax.set_ylabel("measured by correlation (µm)")
    ax.legend(title="axis")
    ax.grid(alpha=0.3)
    steps = sorted({r["step"] for r in rows})
    for step in steps:
        ratios = np.sort([r["ratio_measured"] for r in rows if r["step"] == step])
        bx.plot(ratios, np.arange(1, len(ratios) + 1) / len(ratios), drawstyle="steps-post",
                label=f"step {step}")
    bx.axvline(N_SIGMA, color="k", lw=0.8)
    bx.axhline(0.95, color="0.5", lw=0.8, ls="--")
    bx.set_xlabel("largest |error| / σ_measured of a point")
    bx.set_ylabel("fraction of points")
    bx.legend()
    bx.grid(alpha=0.3)
    within = np.mean([r["ratio_measured"] <= N_SIGMA for r in rows])
    fig.suptitle(f"virtual test: {len(rows)} point-steps, {100 * within:.1f} % within "
                 f"{N_SIGMA:g} σ_measured",
                 fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="the series folder (new)")
    parser.add_argument("--quick", action="store_true", help="two cropped cameras (the test)")
    parser.add_argument("--crop", type=int, nargs=2, default=QUICK_CROP_PX, metavar=("W", "H"),
                        help="--quick: full-size pixels kept around the joint")
    parser.add_argument("--scale", type=float, default=SCALE, help="render scale (default 1)")
    parser.add_argument("--spp", type=int, default=None, help="default: [render] spp")
    parser.add_argument("--per-region", type=int, default=2, help="points per pair and region")
    parser.add_argument("--realisations", type=int, default=4, help="sensor-noise draws per point")
    parser.add_argument("--dot-mm", type=float, default=None,
                        help="speckle dot diameter, mm (default: the experiment's 2 mm)")
    parser.add_argument("--texel-mm", type=float, default=None,
                        help="speckle texel, mm (at most a third of the dot; default 0.25 mm)")
    parser.add_argument("--experiment", type=Path, default=EXPERIMENT,
                        help="experiment file (default: the built-in beam-column)")
    parser.add_argument("--pair", nargs=2, default=None, metavar=("A", "B"),
                        help="the two cameras (default: the built-in's cam1 cam2, else the two "
                             "sharing the most usable samples)")
    parser.add_argument("--steps", type=int, default=1,
                        help="load steps: the field grows linearly to its whole at the last")
    parser.add_argument("--mode", choices=("sampled", "dic"), default=None,
                        help="[render] mode (default: the experiment's)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps {args.steps}: give at least 1 load step")
    if not args.experiment.is_file():
        parser.error(f"--experiment: no file {args.experiment}; give an experiment's .toml")
    from vdo.core.runfolder import check_out

    try:                               # a used --out says so in one line before any work
        check_out(args.out, args.overwrite)
    except vdo.ConfigError as err:
        parser.error(str(err))
    vdo.configure()
    result = run(args.out, args.quick, args.scale, args.spp, args.per_region, args.realisations,
                 args.overwrite, tuple(args.crop), args.dot_mm, args.texel_mm,
                 args.experiment.resolve(), tuple(args.pair) if args.pair else None, args.steps,
                 args.mode)
    print_table(result)
    figure = args.out.with_name(args.out.name + "_result.png")
    plot(result, figure)
    args.out.with_name(args.out.name + "_result.json").write_text(json.dumps(result["rows"], indent=1))
    print(f"figure: {figure}; every point: {figure.with_suffix('.json')}")
    return result


if __name__ == "__main__":
    try:
        main()
    except vdo.ConfigError as err:       # a user mistake: one line, as vdo's commands print it
        sys.exit(f"error: {err}")
