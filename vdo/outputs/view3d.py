"""The run in 3D: meshes, the region samples coloured by a field, camera frustums and light panels,
read back from a run folder; and static perspective figures of it (PNG, like the paper's
Figs. 12-15).

Cameras come from layout.json (x ~ K (R X + t), OpenCV: camera x right, y down, z forward): the
optical centre is C = -Rᵀ t and an image corner (u, v) at depth d along the optical axis is
X = C + d Rᵀ K⁻¹ (u, v, 1)ᵀ. Each sample is drawn as its surface cell (`maps.cell_corners`),
lifted off the face by a tenth of its side so it is not hidden in the mesh.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from vdo.outputs import maps
from vdo.core import vtp
from vdo.core.errors import ConfigError
from vdo.model.surface import face_frame
from vdo.scene import SurfaceSamples, cameras_of

log = logging.getLogger(__name__)

MAX_OBSTACLE_FACES = 20_000     # obstacle meshes above this are simplified by vertex clustering


@dataclass(frozen=True)
class Field:
    """One per-sample field: its values, what it is, and how it is coloured."""

    key: str
    label: str
    values: np.ndarray
    cmap: str
    discrete: bool = False

    def colours(self) -> tuple[np.ndarray, float, float, str]:
        """RGBA per sample (N, 4) in [0, 1], the scale's limits and how they were chosen
        (`maps.color_range`); samples without a value get maps.NO_VALUE."""
        v = self.values.astype(float)
        if self.discrete:
            top = int(max(np.nanmax(v) if np.isfinite(v).any() else 0, 1))
            cmap = plt.get_cmap(self.cmap, top + 1)
            lo, hi, how = -0.5, top + 0.5, f"0 – {top}"
        else:
            cmap = plt.get_cmap(self.cmap)
            lo, hi, how = maps.color_range(v)
        rgba = cmap.with_extremes(bad=maps.NO_VALUE)(np.ma.masked_invalid((v - lo) / (hi - lo)))
        return rgba, lo, hi, how


@dataclass
class Scene3D:
    """What a run folder holds for a 3D view; `unreadable` says which files could not be read,
    and why (absent files are the caller's to report: what a folder should hold depends on the
    command that wrote it)."""

    name: str = ""                                 # the experiment's name, from its config
    meshes: list = field(default_factory=list)     # (name, role, vertices (V, 3), faces (F, 3))
    cameras: list = field(default_factory=list)    # (name, centre (3,), corners (4, 3))
    lights: list = field(default_factory=list)     # (name, corners (4, 3))
    samples: SurfaceSamples | None = None
    fields: list[Field] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)

    def extent(self) -> float:
        """The size of the scene (m): the diagonal of the specimen's (or else everything's) box."""
        pts = [v for _, role, v, _ in self.meshes if role == "specimen"] or \
              [v for _, _, v, _ in self.meshes]
        if self.samples is not None:
            pts.append(self.samples.points)
        if not pts:
            pts = [c for _, c, _ in self.cameras] or [np.zeros((1, 3))]
        pts = np.vstack([np.atleast_2d(p) for p in pts])
        return float(np.linalg.norm(np.ptp(pts, axis=0))) or 1.0


def frustum(K, R, t, width: int, height: int, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Optical centre (3,) and the image's four corners at `depth` (m) along the axis (4, 3),
    from x ~ K (R X + t). Corners are the outer pixel edges: (-0.5, -0.5) ... (w - 0.5, h - 0.5)."""
    K, R, t = (np.asarray(a, dtype=float) for a in (K, R, t))
    centre = -R.T @ t
    uv1 = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1],
                    [-0.5, height - 0.5, 1]], dtype=float)
    rays = np.linalg.solve(K, uv1.T).T                 # camera frame, z = 1
    return centre, centre + depth * rays @ R            # (R^T ray) for each row


def decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Simplify a mesh to at most `max_faces` by vertex clustering: vertices are snapped to a grid
    (cell doubled until few enough faces remain), merged per cell, degenerate faces dropped."""
    if len(faces) <= max_faces:
        return vertices, faces
    cell = float(np.linalg.norm(np.ptp(vertices, axis=0))) / 512
    while True:
        keys = np.floor(vertices / cell).astype(np.int64)
        _, index, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        f = inverse.reshape(-1)[faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        f = np.unique(np.sort(f, axis=1), axis=0) if len(f) > max_faces else f
        if len(f) <= max_faces:
            return vertices[index], f
        cell *= 2


def _fields(arrays: dict) -> list[Field]:
    """The fields of samples.vtp worth colouring by, in a fixed order: coverage, σ_max, σ per axis,
    sensitivity per axis, any strain σ (names with 'strain' or 'eps'), then what each camera sees
    (visible_<camera>)."""
    out = []
    if "coverage" in arrays:
        out.append(Field("coverage", "cameras that see the point", arrays["coverage"], "viridis", True))
    names = list(arrays)
    sigma = [n for n in names if n.startswith("sigma") and "strain" not in n and "eps" not in n]
    sens = [n for n in names if n.startswith("sensitivity")]
    strain = [n for n in names if ("strain" in n or "eps" in n) and arrays[n].ndim == 1]
    for n in sigma:
        out.append(Field(n, f"{n.replace('sigma', 'σ')} (µm)", arrays[n], "magma_r"))
    for n in sens:
        out.append(Field(n, f"{n} (mpixel/µm)", arrays[n], "viridis"))
    for n in strain:
        out.append(Field(n, f"{n} (µε)", arrays[n], "magma_r"))
    for n in names:
        if n.startswith("visible_"):
            out.append(Field(n, f"seen by {n[len('visible_'):]} (1: yes)",
                             arrays[n].astype(np.int32), "cividis", True))
    return [f for f in out if f.values.ndim == 1]


def _samples_from_vtp(points: np.ndarray, arrays: dict) -> SurfaceSamples:
    """Samples from samples.vtp: its tangent frames when written, else `face_frame` of each
    normal (the frame the sampler uses)."""
    normals = np.asarray(arrays["normal"], dtype=float)
    n = len(points)
    if "tangent_u" in arrays and "tangent_v" in arrays:
        t_u, t_v = np.asarray(arrays["tangent_u"], float), np.asarray(arrays["tangent_v"], float)
    else:
        uniq, inverse = np.unique(np.round(normals, 9), axis=0, return_inverse=True)
        frames = np.array([face_frame(u / np.linalg.norm(u)) for u in uniq])    # (U, 2, 3)
        t_u, t_v = frames[inverse.reshape(-1), 0], frames[inverse.reshape(-1), 1]
    return SurfaceSamples(points=np.asarray(points, float), normals=normals, tangent_u=t_u,
                          tangent_v=t_v, uv=np.zeros((n, 2)), area=np.asarray(arrays["area"], float),
                          region=np.asarray(arrays.get("region", np.zeros(n, int))),
                          region_names=(), region_importance=np.ones(1))


def load(run_dir) -> Scene3D:
    """Read config.toml, optimized.toml or designed.toml (meshes, lights), layout.json (cameras)
    and samples.vtp (fields) from a run folder, each when present. An unreadable file is noted in `unreadable`,
    never raised."""
    from vdo.config.experiment import load as load_config
    from vdo.physics.lighting import panel_frame
    from vdo.scene import load_meshes, tripods

    run_dir = Path(run_dir)
    sc = Scene3D()
    cfg = next((p for p in (run_dir / "config.toml", run_dir / "optimized.toml",
                            run_dir / "designed.toml") if p.is_file()), None)
    if cfg is not None:
        try:
            exp = load_config(cfg)
            sc.name = exp.name
            for m in load_meshes(mesh_specs=exp.meshes, regions=exp.regions, camera_specs=exp.camera_specs,
                                 rails=exp.rails, mounts=exp.mounts, path=exp.path):
                v, f = m.vertices, m.faces
                if m.role != "specimen" and len(f) > MAX_OBSTACLE_FACES:
                    v, f = decimate(v, f, MAX_OBSTACLE_FACES)
                    log.info("mesh %s simplified from %d to %d faces", m.name, len(m.faces), len(f))
                sc.meshes.append((m.name, m.role, v, f))
            on_tripods = any(m.tripod is not None for m in exp.mounts)
            for cam in cameras_of(exp.camera_specs, exp.rails) if on_tripods else ():   # each camera's tripod, one mesh
                parts = tripods([cam], camera_specs=exp.camera_specs, mounts=exp.mounts)
                if parts:
                    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
                    sc.meshes.append((f"tripod:{cam.name}", "camera",
                                      np.vstack([p.vertices for p in parts]),
                                      np.vstack([p.faces + o for p, o in zip(parts, offsets)])))
            for lt in exp.lights:
                _, e1, e2 = panel_frame(lt)
                w, h = lt.size
                c = np.asarray(lt.position, float)
                sc.lights.append((lt.name, np.array([c + sa * w / 2 * e1 + sb * h / 2 * e2 for sa, sb
                                                     in ((-1, -1), (1, -1), (1, 1), (-1, 1))])))
        except (ConfigError, OSError, ValueError) as exc:
            sc.unreadable.append(f"{cfg.name} unreadable or its meshes missing ({exc})")
    points = arrays = None
    vtp_path = run_dir / "samples.vtp"
    if vtp_path.is_file():
        try:
            points, arrays = vtp.read_points(vtp_path)
            sc.samples = _samples_from_vtp(points, arrays)
            sc.fields = _fields(arrays)
        except (ValueError, KeyError, OSError) as exc:
            sc.unreadable.append(f"samples.vtp unreadable ({exc})")
    lay = run_dir / "layout.json"
    if lay.is_file():
        try:
            cams = json.loads(lay.read_text())["cameras"]
            depth = 0.12 * sc.extent()
            for c in cams:
                centre, corners = frustum(c["K"], c["R"], c["t"], c["width"], c["height"], depth)
                sc.cameras.append((str(c["name"]), centre, corners))
        except (ValueError, KeyError, TypeError, np.linalg.LinAlgError) as exc:
            sc.unreadable.append(f"layout.json unreadable ({exc})")
    return sc


def cells(sc: Scene3D) -> np.ndarray:
    """(N, 4, 3) sample cells lifted off their face by 0.1 x their side along the normal."""
    s = sc.samples
    lift = 0.1 * np.sqrt(s.area)[:, None, None] * s.normals[:, None, :]
    return maps.cell_corners(s) + lift


def frustum_segments(centre: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(8, 2, 3) line segments of a frustum: centre to each corner, and the image rectangle."""
    return np.array([[centre, c] for c in corners] + [[corners[i], corners[(i + 1) % 4]]
                                                      for i in range(4)])


VIEWS = {"front": (22.0, -62.0), "back": (28.0, 118.0)}   # (elevation, azimuth) in degrees
VIEW_AXES = (0.0, 0.0, 0.86, 0.93)           # the 3D axes in figure fractions (left, bottom, w, h)
VIEW_COLORBAR = (0.87, 0.2, 0.022, 0.56)     # its colour bar


def plot_static(sc: Scene3D, fld: Field, path, title: str, elev: float = 22.0,
                azim: float = -62.0) -> None:
    """A perspective view of the coloured samples and the cameras (frustums and names) and light
    panels, saved as PNG. Meshes are left out: matplotlib sorts polygons by their mean depth only,
    so large mesh triangles would be drawn over the samples (the HTML report shows them)."""
    rgba, lo, hi, how = fld.colours()
    polys, colours = cells(sc), rgba
    fig = plt.figure(figsize=(10, 7.5))      # placed by hand: a constrained layout drew it twice
    ax = fig.add_axes(VIEW_AXES, projection="3d", computed_zorder=False)
    ax.set_proj_type("persp", focal_length=0.35)
    coll = Poly3DCollection(polys, facecolors=colours,
                            edgecolors="none", linewidths=0)
    ax.add_collection3d(coll)
    if sc.cameras:
        segs = np.concatenate([frustum_segments(c, k) for _, c, k in sc.cameras])
        ax.add_collection3d(Line3DCollection(segs, colors="tab:blue", linewidths=0.8))
        for name, c, _ in sc.cameras:
            ax.text(*c, f" {name}", fontsize=7, color="tab:blue")
    for name, corners in sc.lights:
        ax.add_collection3d(Poly3DCollection([corners], facecolors=(1.0, 0.85, 0.2, 0.7),
                                             edgecolors="0.4", linewidths=0.5))
    pts = np.vstack([polys.reshape(-1, 3)] + [c for _, c, _ in sc.cameras])
    lo3, hi3 = pts.min(axis=0), pts.max(axis=0)
    ax.set_xlim(lo3[0], hi3[0]), ax.set_ylim(lo3[1], hi3[1]), ax.set_zlim(lo3[2], hi3[2])
    ax.set_box_aspect(np.maximum(hi3 - lo3, 1e-3 * max(hi3 - lo3)))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)"), ax.set_zlabel("z (m)")
    ax.tick_params(labelsize=7)
    mappable = plt.cm.ScalarMappable(cmap=plt.get_cmap(fld.cmap, int(hi - lo) if fld.discrete
                                                       else None),
                                     norm=plt.Normalize(lo, hi))
    bar = fig.colorbar(mappable, cax=fig.add_axes(VIEW_COLORBAR))
    bar.set_label(f"{fld.label}; scale {lo:.4g} – {hi:.4g} ({how})" if not fld.discrete
                  else f"{fld.label}; {how}", fontsize=9)
    if fld.discrete:
        bar.set_ticks(range(0, int(hi + 0.5)))
    ax.set_title(title, fontsize=11, wrap=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def write_static(run_dir, sc: Scene3D | None = None, keys=("coverage", "sigma_max")) -> list[Path]:
    """maps/view3d_<field>.png for each of `keys` present in the run folder's samples.vtp
    (`sc`: the folder already read by `load`)."""
    run_dir = Path(run_dir)
    sc = load(run_dir) if sc is None else sc
    if sc.samples is None:
        return []
    (run_dir / "maps").mkdir(exist_ok=True)
    name = ""
    cfg = run_dir / "summary.json"
    if cfg.is_file():
        try:
            name = json.loads(cfg.read_text()).get("experiment", "")
        except ValueError:
            pass
    written = []
    for fld in sc.fields:
        if fld.key in keys and np.isfinite(fld.values.astype(float)).any():
            path = run_dir / "maps" / f"view3d_{fld.key}.png"
            plot_static(sc, fld, path, f"{name}: {fld.label}" if name else fld.label)
            written.append(path)
    return written
