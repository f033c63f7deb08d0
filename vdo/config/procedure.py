"""The tables of what is done with the rig, read by `vdo.config.experiment`: the lab's processing
([analysis], [[stereo_pair]]), region groups ([[group]]), the load path ([load_path]), and the
settings of `vdo optimize`, `vdo design` and `vdo calibrate` ([optimize], [design],
[calibration]); each table's own checks (`check_analysis`, ...). Angles are radians inside vdo."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vdo.config.reader import Table
from vdo.config.rig import UNITS
from vdo.config.schema import File, Flag, Numbers, Points, Real, Text, Vector, Whole, Words, row


@dataclass(frozen=True)
class Analysis:
    """The DIC analysis the strain uncertainty is predicted for (`vdo.physics.strain`): global DIC with Q4
    elements of side `element` (m), or subset DIC with square subsets of side `subset` (m) or
    `subset_px` pixels on a grid of `step` (m) or `step_px` pixels, shape function "zero" or
    "affine", strain from a plane fit over `strain_window` x `strain_window` subset centres.
    Pixels are those of the finest camera at each sample (`vdo.physics.strain.sizes`)."""

    method: str = row("method", Text(choices=("global", "subset")), "global",
                      doc="global (finite-element) or subset (local) DIC")
    element: float | None = row("element_mm", Real(positive=True), None, unit="mm",
                                shown="[evaluation] patch_mm", doc="Q4 element side (global DIC)")
    subset: float | None = row("subset_mm", Real(positive=True), None, unit="mm", shown="none",
                               doc="subset side in mm (or subset_px)")
    subset_px: float | None = row("subset_px", Real(positive=True), 29.0,
                                  doc="subset side in pixels (unless subset_mm)")
    step: float | None = row("step_mm", Real(positive=True), None, unit="mm", shown="none",
                             doc="subset grid step in mm (or step_px)")
    step_px: float | None = row("step_px", Real(positive=True), 7.0,
                                doc="subset grid step in pixels (unless step_mm)")
    shape_function: str = row("shape_function", Text(choices=("zero", "affine")), "affine",
                              doc="subset shape function")
    strain_window: int = row("strain_window", Whole(low=2), 15,
                             doc="subset centres per side of the strain plane fit (virtual gauge)")
    interpolant: str = row("interpolant", Text(choices=("cubic", "quintic", "keys")), "cubic",
                           doc="the correlation's interpolant: cubic or quintic B-spline, or keys "
                               "(Keys' bicubic convolution, a = -0.5) (σ_measured's bias and noise)")
    reference: str = row("reference", Text(choices=("noisy", "noise-free")), "noisy",
                         doc="noisy: a recorded reference image; noise-free: a synthetic one")
    processing: str = row("processing", Text(choices=("all-views", "pairs")), "all-views",
                          doc="all views in one correlation, or stereo pairs merged per point")
    pairs: str = row("pairs", Text(choices=("auto", "declared")), "auto",
                     doc="pairs: auto (any two usable views with the angle between their rays "
                         "in [lens minimum, max_pair_angle_deg]) or the [[stereo_pair]] tables")
    merge: str = row("merge", Text(choices=("best", "fusion")), "best",
                     doc="pairs at a point: the best one, or inverse-variance fusion")
    max_pair_angle: float | None = row("max_pair_angle_deg", Real(1.0, 180.0), None, unit="deg",
                                       shown="60", doc="largest angle between a pair's rays (auto)")


def check_analysis(t: Table, v: dict) -> None:
    if v["pairs"] == "declared" and v["processing"] != "pairs":
        raise t.error("pairs", 'declared pairs need processing = "pairs"')
    for mm, px in (("subset", "subset_px"), ("step", "step_px")):
        if t.has(f"{mm}_mm") and t.has(px):
            raise t.error(px, f"give the size once: {px} or {mm}_mm")
        if v[mm] is not None:
            v[px] = None


STEREO_SPAN_DEG = 20.0            # a declared pair's default max_angle_deg = its min + this


@dataclass(frozen=True)
class StereoPairSpec:
    """A declared stereo pair: two cameras whose optical axes must make an angle in
    [min_angle, max_angle] (rad). min_angle None: the stereo rule of thumb for the shorter lens
    (`vdo.constraints.stereo_min_angle`); max_angle None: that minimum + STEREO_SPAN_DEG."""

    cameras: tuple[str, ...] = row("cameras", Words(what="two camera names", nonempty=True),
                                   doc='the two cameras, e.g. ["left", "right"]')
    min_angle: float | None = row("min_angle_deg", Real(0.0, 180.0), None, unit="deg",
                                  shown="by lens", doc="smallest angle between the optical axes")
    max_angle: float | None = row("max_angle_deg", Real(0.0, 180.0), None, unit="deg",
                                  shown=f"min + {STEREO_SPAN_DEG:g}", doc="largest angle between the optical axes")


def check_stereo_pair(t: Table, v: dict) -> None:
    if len(v["cameras"]) != 2:
        raise t.error("cameras", f'must name two different cameras, e.g. ["left", "right"] '
                                 f"(got {list(v['cameras'])!r})")
    check_angles(t, v, "min_angle_deg", "max_angle_deg", "min_angle", "max_angle")


def check_angles(t: Table, v: dict, low_key, high_key, low, high) -> None:
    if v[low] is not None and v[high] is not None and v[high] < v[low]:
        raise t.error(high_key, f"= {math.degrees(v[high]):g} is below {low_key} = "
                                f"{math.degrees(v[low]):g}: the maximum must be at least the minimum")


@dataclass(frozen=True, eq=False)
class GroupSpec:
    """Meshes that move together along the load path (a hexapod's platform with its
    end-effector, a crosshead). Every mesh is also a group of its own name."""

    name: str = row("name", Text(name=True), doc="unique; not the name of a mesh")
    meshes: tuple[str, ...] = row("meshes", Words(what="mesh names", nonempty=True),
                                  doc="the [[mesh]] names that move together")
    pivot: np.ndarray = row("pivot_m", Vector(3, letters="xyz"), [0.0, 0.0, 0.0], unit="m",
                            doc="the point the group's rotations turn about")


@dataclass(frozen=True)
class LoadPathSpec:
    """The steps of a moving test (`vdo.geometry.keyframes`): rigid poses of groups per step, and
    optionally nodal displacements of one specimen mesh per step."""

    poses: Path | None = row("poses", File((".csv",), "pose", "a CSV"), None, shown="none",
                             doc="CSV: step, group, x_mm, y_mm, z_mm, rx_deg, ry_deg, rz_deg")
    displacements: Path | None = row("displacements", File((".csv", ".vtu", ".vtp", ".pvd"), "displacement",
                                                           "a CSV, .vtu, .vtp or .pvd"), None,
                                     shown="none", doc="CSV: step, x_m, y_m, z_m, ux_mm, uy_mm, uz_mm; or "
                                                       "VTK XML nodal displacements (.vtu/.vtp, one step; "
                                                       ".pvd, one file per step)")
    deformed_mesh: str | None = row("deformed_mesh", Text(name=True), None, shown="none",
                                    doc="the specimen mesh the displacements apply to")
    unit: str | None = row("unit", Text(choices=tuple(UNITS)), None, shown="none",
                           doc="length unit of a VTK file's points and displacements (required for VTK)")
    displacement_array: str | None = row("displacement_array", Text(), None, shown="auto",
                                         doc="the VTK point array of displacements (default: the one "
                                             "3-component array, or the one named displacement, U, ...)")
    every: int = row("every", Whole(low=1), 1,
                     doc="judge and render every every-th step of the files and the last one (a "
                         "quicker look at a long series; every row of every step is still checked)")
    step_time: float | None = row("step_s", Real(positive=True), None, unit="s", shown="none",
                                  doc="seconds the load takes from one step of the files to the "
                                      "next, the images taken on the move: with \"time\" in "
                                      "[exposure] free, each camera's exposure keeps its image "
                                      "motion within [exposure] blur_px")

    @property
    def active(self) -> bool:
        return self.poses is not None or self.displacements is not None


def check_load_path(t: Table, v: dict) -> None:
    if (v["displacements"] is None) != (v["deformed_mesh"] is None):
        raise t.error("deformed_mesh", "give displacements and deformed_mesh together (the file's "
                                       "nodes are that mesh's vertices)")
    vtk = v["displacements"] is not None and v["displacements"].suffix.lower() != ".csv"
    if vtk and v["unit"] is None:
        raise t.error("unit", "a VTK file carries no length unit: give unit = \"mm\" or \"m\" (its "
                              "points and displacements)")
    if v["step_time"] is not None and v["poses"] is None and v["displacements"] is None:
        raise t.error("step_s", "is the time between the load path's steps: give its poses or "
                                "displacements, or drop step_s")
    if not vtk and (v["unit"] is not None or v["displacement_array"] is not None):
        raise t.error("unit" if v["unit"] is not None else "displacement_array",
                      "is for a VTK displacement file (a CSV names its units in its header)")


EXPOSURE_FREE = ("aperture", "time", "lights", "light_positions")


@dataclass(frozen=True)
class ExposureSpec:
    """[exposure]: the light each camera gathers and what `vdo design` and `vdo optimize` may set
    of it after placing the cameras (`vdo.physics.exposure`, docs/exposure.md)."""

    max_time: float = row("max_ms", Real(positive=True), 50.0, unit="ms",
                          doc="the longest exposure the test allows (with [load_path] step_s, "
                              "each camera's is also held to blur_px of image motion)")
    blur_px: float = row("blur_px", Real(positive=True), 0.1,
                         doc="the image motion (pixels) a camera may record during one exposure "
                             "while the load runs ([load_path] step_s): its exposure time is at "
                             "most blur_px / its fastest image speed")
    f_numbers: tuple[float, float] = row("f_number_range", Vector(2, positive=True, as_tuple=True,
                                                                   letters=("min", "max")),
                                         [2.8, 16.0], doc="the stops the lenses allow")
    target_gray: float = row("target_gray", Real(0.3, 0.95), 0.85,
                             doc="99th percentile gray aimed at in each camera's brightest region, "
                                 "a fraction of the range")
    free: tuple[str, ...] = row("free", Words(choices=EXPOSURE_FREE), [], shown="none",
                                doc='what design and optimize set: "aperture" (each camera\'s '
                                    'f-number and focus), "time" (its exposure time), "lights" '
                                    "(each [[light]]'s radiance up to its max_radiance), "
                                    '"light_positions" (where each [[light]] with a mount stands)')


def check_exposure(t: Table, v: dict) -> None:
    low, high = v["f_numbers"]
    if not low < high:
        raise t.error("f_number_range", f"= [{low:g}, {high:g}]: give [smallest, largest] stop, "
                                        "e.g. [2.8, 16]")


@dataclass(frozen=True)
class OptimizeSpec:
    """What `vdo optimize` may move and the practical constraints it enforces."""

    free: tuple[str, ...] = row(
        "free", Words(choices=("u", "pan", "tilt", "roll", "lens"), nonempty=True), ["u", "pan", "tilt"],
        doc='parameters that move per camera (add "roll" to free it, otherwise cameras stay '
            'horizontal; add "lens" to choose each moving camera\'s lens from lenses_mm)')
    lenses: tuple[float, ...] = row(
        "lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [], unit="mm",
        doc='the lens catalogue for "lens" in free: a greedy outer loop tries each other lens on each '
            "moving camera and keeps it when the result is better (feasible first, then by score)")
    cameras: tuple[str, ...] | None = row("cameras", Words(what="camera names"), None, shown="all",
                                          doc="names of the cameras that move")
    regions: tuple[str, ...] | None = row(
        "regions", Words(what="region names", nonempty=True), None, shown="all",
        doc="regions whose uncertainty and coverage enter the score (constraints apply everywhere)")
    min_axis_angle: float | None = row(
        "min_axis_angle_deg", Real(0.0, 90.0), None, unit="deg", shown="by lens",
        doc="minimum angle between the optical axes of two cameras sharing a region; default 35° up "
            "to 12 mm, 25° at 17 mm, 15° from 35 mm (the shorter lens of the pair)")
    max_axis_angle: float | None = row(
        "max_axis_angle_deg", Real(0.0, 180.0), None, unit="deg", shown="none",
        doc="largest angle between the optical axes of two cameras sharing a region (off by default "
            "for multi-view; declared stereo pairs have their own)")
    clearance: float = row("clearance_m", Real(low=0.0), 0.05, unit="m",
                           doc="camera bodies keep this distance from every mesh and each other")
    max_obscuration: float = row("max_obscuration", Real(0.0, 1.0), 0.01,
                                 doc="largest fraction of an assigned region's image an obstacle may mask")
    assign_fraction: float = row("assign_fraction", Real(0.01, 1.0), 0.5,
                                 doc="a camera is assigned the regions it sees this much of in the "
                                     "starting layout")
    restart_seconds: float = row("restart_s", Real(low=0), 60.0,
                                 doc="wall seconds per camera count for random restarts (starts drawn "
                                     "from the bound's weights, each followed by exchange passes; "
                                     "docs/design.md; 0: none)")
    score: str = row(
        "score", Text(choices=("bound", "measured")), "bound",
        doc='what the score\'s σ is: "bound", the Cramér-Rao bound; "measured", what the lab\'s '
            "correlation measures ([analysis] interpolant and reference: each camera's information "
            "divided by its error over the bound, refreshed every round; docs/theory.md)")
    starts: int = row("starts", Whole(low=1), 3, doc="multi-start: the hand layout + perturbed copies")
    rounds: int = row("rounds", Whole(low=1), 3,
                      doc="penalty rounds, each ending with a visibility refresh")
    max_steps: int = row("max_steps", Whole(low=1), 40, doc="BFGS steps per round")
    seed: int = row("seed", Whole(low=0), 0, doc="perturbation of the extra starts")
    load_path: bool = row(
        "load_path", Flag(), True,
        doc="with a [load_path]: score the views that hold over the test (seen at rest and at "
            "load_path_fraction of the keyframes), not at rest alone (docs/theory.md)")
    load_path_fraction: float = row(
        "load_path_fraction", Real(high=1.0, positive=True), 1.0,
        doc="fraction q (0 < q <= 1) of the keyframes at which a view must be seen to count; 1 = "
            "every one (the worst case)")
    load_path_keyframes: int = row(
        "load_path_keyframes", Whole(low=1), 4,
        doc="keyframes each visibility refresh casts: the extremes of the path first, then evenly "
            "spaced (all steps when the path has no more); the result is judged over every step")


@dataclass(frozen=True, eq=False)
class DesignSpec:
    """What `vdo design` may choose: the camera bodies ([[body]], or [design]'s one sensor), the
    lens catalogue, where candidates stand on the mounts and how they aim (`vdo.design.candidates`)."""

    max_cameras: int | None = row("max_cameras", Whole(low=1), None,
                                  shown="the [[body]] counts, else the [[camera]] count",
                                  doc="the most cameras to place (the inventory)")
    min_cameras: int = row("min_cameras", Whole(low=1), 2, doc="fewest cameras on the Pareto curve")
    sensor_width: float | None = row("sensor_width_mm", Real(positive=True), None, unit="mm",
                                     shown="the first [[camera]]'s", doc="sensor width of the bodies")
    pixels: tuple[int, int] | None = row(
        "pixels", Vector(2, positive=True, whole=True, as_tuple=True, letters="WH"), None,
        shown="the first [[camera]]'s", doc="pixel counts of the bodies")
    lenses: tuple[float, ...] = row("lenses_mm", Numbers(as_set=True, what="focal lengths in mm"), [],
                                    unit="mm", shown="the [[camera]] lenses", doc="the lens catalogue")
    target_sigma_um: float | None = row("target_sigma_um", Real(positive=True), None, shown="none",
                                        doc="sigma_max p95 (µm) to reach on the scored regions (σ_measured's "
                                            "with score = \"measured\"): the smallest camera count "
                                            "that does is reported")
    coverage_weight: float = row(
        "coverage_weight", Real(positive=True), 1.0,
        doc="how much a view short of a region's min_cameras costs in the selection's score, "
            "as a multiple of the default (a sample's whole area one view short costs as much as "
            "its sigma going from 1 um to unmeasured): above 1 the design gives up sigma on the "
            "scored regions for area seen by min_cameras everywhere, below 1 the reverse "
            "(docs/design.md, \"Coverage against precision\")")
    rail_positions: int = row("rail_positions", Whole(low=1), 12,
                              doc="candidate positions per rail, evenly spread in u")
    offset: np.ndarray = row("offset_m", Vector(3, letters="xyz"), [0.0, 0.0, 0.15], unit="m",
                             doc="from the rail point to a candidate's optical centre (also tried mirrored below the bar)")
    aim_offsets: tuple[float, ...] = row("aim_offsets_deg", Numbers(as_set=True, what="angles in deg"),
                                         [], unit="deg", shown="none",
                                         doc="extra aims: each region target's pan and tilt +- these")
    sample_spacing: float = row("sample_spacing_mm", Real(positive=True), 20.0, unit="mm",
                                doc="sample spacing for the selection (the result is judged at [evaluation]'s)")
    zone_points: int = row("zone_points", Whole(low=1), 3,
                           doc="candidate positions per horizontal axis of a zone [[mount]] (a grid; "
                               "in a floor polygon, the grid points inside it)")
    zone_heights: int = row("zone_heights", Whole(low=1), 3,
                            doc="candidate heights per zone, evenly spread over its height range")
    keyframes: int = row("keyframes", Whole(low=0), 3,
                         doc="load-path steps at which the candidates' occlusion is also judged (the "
                             "steps farthest from rest and from each other); a candidate counts where "
                             "it sees a sample at rest and at each (0: at rest only)")
    bound_seconds: float = row("bound_s", Real(low=0), 60.0,
                               doc="wall seconds per camera count for the bound on the best score "
                                   "(`vdo.design.bound`; 0: no bound)")
    restart_seconds: float = row("restart_s", Real(low=0), 60.0,
                                 doc="wall seconds per camera count for random restarts (starts drawn "
                                     "from the bound's weights, each followed by exchange passes; "
                                     "docs/design.md; 0: none)")
    branch_seconds: float = row("branch_s", Real(low=0), 300.0,
                                doc="wall seconds at most of branch and bound on the bound of the "
                                    "inventory's count (the layout written), after its relaxation; it "
                                    "stops earlier when a minute lifts the bound by less than 0.05 % "
                                    "(`vdo.design.bound`; 0: none)")
    score: str = row(
        "score", Text(choices=("bound", "measured")), "bound",
        doc='what the selection\'s σ is: "bound", the Cramér-Rao bound; "measured", what the lab\'s '
            "correlation measures ([analysis] interpolant and reference: each candidate's information "
            "divided by its error over the bound in each region; docs/design.md)")

    @property
    def rail_us(self) -> np.ndarray:
        """The rail_positions values of u in [0, 1] that a rail offers (edges included; the
        middle alone for one)."""
        return np.linspace(0.0, 1.0, self.rail_positions) if self.rail_positions > 1 else np.array([0.5])


ON_REQUEST = ("calibration",)      # tables whose presence asks for work: written back only when given


TARGET_KINDS = ("checkerboard",)   # what `vdo calibrate` renders and detects (OpenCV)


@dataclass(frozen=True, eq=False)
class CalibrationSpec:
    """[calibration]: the lab's calibration session that `vdo calibrate` renders, calibrates and
    propagates (`vdo.calib`, docs/calibration.md): the target, its poses, the detection noise."""

    target: str = row("target", Text(choices=TARGET_KINDS), "checkerboard",
                      doc="checkerboard (inner corners: findChessboardCorners + cornerSubPix)")
    rows: int = row("rows", Whole(low=3, high=60), 7,
                    doc="inner corners per column; rows + columns odd (one odd, one even) so "
                        "that the board's orientation is unambiguous")
    columns: int = row("columns", Whole(low=3, high=60), 10, doc="inner corners per row")
    pitch: float | None = row("pitch_mm", Real(positive=True), None, unit="mm",
                              shown="the target spans field_fill of the narrowest field",
                              doc="square side")
    pitch_tolerance: float = row("pitch_tolerance_mm", Real(low=0.0), 0.0, unit="mm",
                                 doc="the maker's pitch tolerance (1 sigma): a scale error of the "
                                     "whole calibration, shared by every load step")
    flatness: float = row("flatness_mm", Real(low=0.0), 0.0, unit="mm",
                          doc="the maker's flatness tolerance: the rendered target bows by this "
                              "much at its centre (the calibration assumes it flat)")
    field_fill: float = row("field_fill", Real(0.1, 1.0), 0.5,
                            doc="fraction of a camera's field width the target spans at the "
                                "working distance (generated poses, automatic pitch)")
    poses_per_camera: int = row("poses_per_camera", Whole(low=3, high=500), 12,
                                doc="generated poses per camera (intrinsics), spread over its field")
    shared_poses: int = row("shared_poses", Whole(low=0, high=500), 6,
                            doc="generated poses per stereo pair seen by both cameras (extrinsics)")
    distances: tuple[float, ...] | None = row(
        "distances_m", Numbers(what="distances in metres"), None, unit="m",
        shown="each camera's working distance", doc="target distances from the camera, cycled")
    tilt: float = row("tilt_deg", Real(0.0, 60.0), 30.0, unit="deg",
                      doc="largest tilt of a generated pose away from facing the camera")
    pose_centres: np.ndarray | None = row("pose_centres_m", Points(minimum=1), None, unit="m",
                                          shown="none (generated)",
                                          doc="explicit poses: where the target's centre is")
    pose_normals: np.ndarray | None = row("pose_normals", Points(minimum=1), None, shown="none",
                                          when="pose_centres",
                                          doc="explicit poses: the target's front normal, one per centre")
    detection_sigma_px: float | None = row(
        "detection_sigma_px", Real(positive=True), None, shown="from the residuals",
        doc="corner/dot detection noise (px, 1 sigma) of the covariance sigma^2 (J^T J)^-1")
    strain: float = row("strain", Real(positive=True, high=0.5), 0.002,
                        doc="the test's strain level (calibration-induced error is also given per unit)")
    displacement: float = row("displacement_mm", Real(positive=True), 1.0, unit="mm",
                              doc="the test's displacement level")
    target_strain_error: float = row("target_strain_error", Real(positive=True), 1e-5,
                                     doc="`vdo calibrate --plan`: calibration-induced strain error "
                                         "(1 sigma, p95 over samples) to reach at the test's level")
    seed: int = row("seed", Whole(low=0), 0, doc="seed of the generated poses and the images' noise")


def check_calibration(t: Table, v: dict) -> None:
    if (v["rows"] + v["columns"]) % 2 == 0:
        raise t.error("columns", f"rows = {v['rows']} and columns = {v['columns']} have the same "
                                 "parity: make one odd and one even (a board that looks the same "
                                 "turned by 180 deg has no defined corner order)")
    centres, normals = v["pose_centres"], v["pose_normals"]
    if (centres is None) != (normals is None):
        raise t.error("pose_normals", "explicit poses need pose_centres_m and pose_normals together")
    if centres is not None:
        if len(normals) != len(centres):
            raise t.error("pose_normals", f"must hold one normal per centre ({len(centres)})")
        length = np.linalg.norm(normals, axis=1)
        if np.any(length < 1e-9):
            raise t.error("pose_normals", f"normal {int(np.argmin(length))} is zero")
        v["pose_normals"] = normals / length[:, None]
    if v["pitch"] is not None and v["pitch_tolerance"] >= 0.1 * v["pitch"]:
        raise t.error("pitch_tolerance_mm", "must be below a tenth of pitch_mm")


def check_optimize(t: Table, v: dict) -> None:
    check_angles(t, v, "min_axis_angle_deg", "max_axis_angle_deg", "min_axis_angle", "max_axis_angle")


def check_design(t: Table, v: dict) -> None:
    if (v["sensor_width"] is None) != (v["pixels"] is None):
        raise t.error("pixels", "give the bodies' sensor_width_mm and pixels together (or neither: "
                                "the first [[camera]]'s)")
    if v["max_cameras"] is not None and v["max_cameras"] < v["min_cameras"]:
        raise t.error("max_cameras", f"= {v['max_cameras']} is below min_cameras = {v['min_cameras']}")
