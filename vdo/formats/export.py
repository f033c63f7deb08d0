"""`vdo export SOURCE --format F --out DIR`: the cameras of an experiment or of a run folder as
calibration files for DIC software.

SOURCE is an experiment TOML (its cameras resolved as `vdo evaluate` does) or a run folder with
layout.json (cameras at that run's pose and image scale). The stereo pairs are the cameras
assigned a common region with optical axes at most the pair rule's maximum apart
(`default_pairs`); a region the pairs leave partly uncovered is named in a warning
(`uncovered_regions`); for a run folder the scene comes from its config.toml. Which camera sees
which sample comes from the ray cast (`vdo.physics.visibility`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vdo.model.camera import Camera
from vdo.core.errors import ConfigError
from vdo.core.tolerances import TINY
from vdo.formats import dice
from vdo.formats import matchid
from vdo.formats import opencv
from vdo.formats import vic3d
from vdo.formats.calibration import stereo_pairs

log = logging.getLogger(__name__)
FORMATS = {"opencv": opencv.write, "matchid": matchid.write, "dice": dice.write, "vic3d": vic3d.write}


@dataclass(frozen=True)
class PairSyntax:
    """How a user names stereo pairs, in the messages that tell how: `form` the general form,
    `example` the same for two cameras (a format string of {first} and {second})."""

    form: str
    example: str

    def of(self, first: str, second: str) -> str:
        """The form naming cameras `first` and `second`."""
        return self.example.format(first=first, second=second)


# the command line's option (vdo export, vdo render)
PAIRS_OPTION = PairSyntax("--pairs FIRST:SECOND", "--pairs {first}:{second}")


def default_pairs(exp, cameras, vis, samples, requested=None, source=None,
                  syntax: PairSyntax = PAIRS_OPTION) -> list:
    """The stereo pairs of a layout: cameras assigned a common region whose optical axes are at
    most [analysis] max_pair_angle_deg apart (default `vdo.physics.measured`'s 60°: beyond it
    stereo matching fails on foreshortening; the pairs left out are logged, with the `syntax`
    that overrides the rule; a kept pair whose axes are closer than the minimum the optimizer
    holds it to, `vdo.constraints.angle_limits`, is named in a warning), or the `requested`
    (first, second) names, the lab's override, each
    checked to share a field of view (`stereo_pairs`; errors name `source`, default the
    experiment file)."""
    from vdo.constraints import angle_limits, assignments

    if requested is not None:
        return stereo_pairs(cameras, vis.visible, None, requested, source or exp.path)
    assigned = assignments(vis, samples, exp.optimize.assign_fraction)
    pairs = stereo_pairs(cameras, vis.visible, assigned, None, exp.path)
    index = {c.name: i for i, c in enumerate(cameras)}
    # the declared pairs of these cameras (`--cameras` may have left one of a pair out)
    declared = tuple(p for p in exp.stereo_pairs if all(n in index for n in p.cameras))
    keys, lows, _ = angle_limits(exp.regions, exp.optimize, declared, cameras, assigned)
    low_of = {(int(i), int(j)): float(low) for (i, j), low in zip(keys, lows)}
    limit = max_pair_angle(exp)
    kept, dropped, narrow = [], [], []
    for pair in pairs:
        angle = axes_angle(pair.first, pair.second)
        name = f"{pair.first.name}:{pair.second.name} {math.degrees(angle):.1f}"
        if angle > limit:
            dropped.append(name)
            continue
        kept.append(pair)
        low = low_of.get(tuple(sorted((index[pair.first.name], index[pair.second.name]))))
        if low is not None and angle < low:
            narrow.append(f"{name} (min {math.degrees(low):.0f})")
    if dropped:       # one line, however many pairs (45 of them on a 10-camera rig)
        log.info("%d camera pair(s) assigned a common region left out of the stereo pairs: "
                 "optical axes more than %.0f deg apart ([analysis] max_pair_angle_deg; naming "
                 "pairs with %s overrides): %s", len(dropped), math.degrees(limit), syntax.form,
                 ", ".join(dropped))
    if narrow:
        log.warning("%d exported stereo pair(s) with optical axes closer than their lenses' stereo "
                    "angle (depth uncertainty grows as 1/sin of the angle; the minimum is [optimize] "
                    "min_axis_angle_deg, a [[stereo_pair]]'s min_angle_deg, or the rule of thumb of "
                    "the shorter lens): %s deg; move a camera apart or name better pairs with %s",
                    len(narrow), ", ".join(narrow), syntax.form)
    return kept


def max_pair_angle(exp) -> float:
    """The largest angle between a default pair's optical axes (rad): [analysis]
    max_pair_angle_deg, else `vdo.physics.measured`'s DEFAULT_MAX_PAIR_ANGLE_DEG."""
    from vdo.physics.measured import DEFAULT_MAX_PAIR_ANGLE_DEG

    return exp.analysis.max_pair_angle if exp.analysis.max_pair_angle is not None \
        else math.radians(DEFAULT_MAX_PAIR_ANGLE_DEG)


def axes_angle(first: Camera, second: Camera) -> float:
    """The angle between two cameras' optical axes (rad), acos(a1 · a2)."""
    return math.acos(float(np.clip(first.optical_axis @ second.optical_axis, -1, 1)))


def best_pair(exp, cameras, visible, samples) -> tuple[str, str, str, float] | None:
    """The two cameras, optical axes within `max_pair_angle`, that see together the largest
    fraction of one region r,

        f_ijr = Σ_{n in r} v_in v_jn A_n / Σ_{n in r} A_n

    (v the ray cast's `visible` (C, N), rows in the order of `cameras`; A the samples' areas, the
    measure of `vdo.constraints.assignments`), as (first, second, region, f); None when no two
    such cameras see a point of a region together."""
    visible = np.asarray(visible, dtype=float)
    limit = max_pair_angle(exp)
    candidates = [(i, j) for i in range(len(cameras)) for j in range(i + 1, len(cameras))
                  if axes_angle(cameras[i], cameras[j]) <= limit]
    best, example = 0.0, None
    for r, region in enumerate(samples.region_names):
        mask = samples.region == r
        area = samples.area[mask]
        together = (visible[:, mask] * area) @ visible[:, mask].T / max(area.sum(), TINY)
        for i, j in candidates:
            if together[i, j] > best:
                best, example = together[i, j], (cameras[i].name, cameras[j].name, region)
    return None if example is None else (*example, float(best))


def pair_example(exp, cameras, visible, samples, syntax: PairSyntax = PAIRS_OPTION) -> str | None:
    """The example pair of the messages that ask for pairs, in `syntax`: "e.g. --pairs A:B
    (together they see 46% of region 'r', the most of any two)" (`best_pair`), or None."""
    found = best_pair(exp, cameras, visible, samples)
    if found is None:
        return None
    first, second, region, fraction = found
    return (f"e.g. {syntax.of(first, second)} (together they see {fraction:.0%} of region "
            f"{region!r}, the most of any two)")


def no_pair_message(exp, cameras, vis, samples, syntax: PairSyntax = PAIRS_OPTION) -> str:
    """Why a layout has no default stereo pair (`default_pairs` is empty) and the fix: name pairs
    in `syntax` (default --pairs FIRST:SECOND), with the example of `pair_example`; without two
    cameras that see a point of a region together, the fix is to move them."""
    why = (f"no two cameras are assigned a common region (each seeing at least [optimize] "
           f"assign_fraction = {exp.optimize.assign_fraction:g} of its area) with optical axes at most "
           f"{math.degrees(max_pair_angle(exp)):.0f} deg apart")
    example = pair_example(exp, cameras, vis.visible, samples, syntax)
    if example is None:
        return (f"{why}, and no two such cameras see a point of a region together: move the cameras "
                f"so that two share a view, then name them with {syntax.form}")
    return f"{why}: name the pairs with {syntax.form}, {example}"


# Fraction of a region's area that the exported stereo pairs may leave unseen by both cameras of
# every pair, where two cameras of the rig (optical axes within the pair angle) do see it together,
# before `uncovered_regions` warns: a pair's common view loses a few percent at its image edges,
# a ring measured by pairs on one side only loses most of it (three quarters in the trial).
PAIR_GAP = 0.05


def uncovered_regions(exp, cameras, vis, samples, pairs) -> str | None:
    """The warning when the stereo `pairs` leave part of a region uncovered, else None. A pair
    covers the samples both its cameras see (the ray cast's `visible`: the common area that
    `vdo.constraints.sharing`, the optimizer's pair rule, measures); a region is named when the
    pairs leave more than `PAIR_GAP` of its area uncovered that some two cameras with optical axes
    within `max_pair_angle` see together, with its share of all regions' area and the fraction
    of it the pairs cover against the fraction such two cameras can. The fix: pairs added greedily (each time the one covering the most of
    that missing area) until every named region is within `PAIR_GAP`, gathered into one --pairs
    FIRST:SECOND list with the pairs already exported (--pairs replaces them)."""
    visible = np.asarray(vis.visible, dtype=bool)
    index = {c.name: i for i, c in enumerate(cameras)}
    chosen = [(index[p.first.name], index[p.second.name]) for p in pairs]
    limit = max_pair_angle(exp)
    fitting = [(i, j) for i in range(len(cameras)) for j in range(i + 1, len(cameras))
               if axes_angle(cameras[i], cameras[j]) <= limit]
    both = lambda ij: visible[ij[0]] & visible[ij[1]]
    union = lambda ijs: np.any([both(ij) for ij in ijs], axis=0) if ijs else np.zeros(len(samples), bool)
    covered = union(chosen)
    coverable = union(fitting) | covered
    area, total = samples.area, float(samples.area.sum())
    fraction = lambda m, r: float(area[m & (samples.region == r)].sum() / area[samples.region == r].sum())
    short = [r for r in range(len(samples.region_names))
             if fraction(coverable & ~covered, r) > PAIR_GAP]
    if not short:
        return None
    named = [f"{samples.region_names[r]} ({area[samples.region == r].sum() / total:.0%} of all "
             f"regions' area): {fraction(covered, r):.0%} of it seen by both cameras of an exported pair, "
             f"{fraction(coverable, r):.0%} by two cameras within the pair angle" for r in short]
    missing = coverable & ~covered & np.isin(samples.region, short)
    added = []
    while any(fraction(missing, r) > PAIR_GAP for r in short):
        gain, ij = max(((float(area[missing & both(ij)].sum()), ij) for ij in fitting
                        if ij not in chosen + added), default=(0.0, None))
        if gain <= 0:
            break
        added.append(ij)
        missing &= ~both(ij)
    name = lambda ij: f"{cameras[ij[0]].name}:{cameras[ij[1]].name}"
    return (f"{len(short)} region(s) left partly uncovered by the exported stereo pairs: "
            + "; ".join(named) + ". To export pairs on them name every pair with --pairs "
            f"FIRST:SECOND, e.g. --pairs {' '.join(name(ij) for ij in chosen + added)}")


def write_all(cameras, pairs, folder: Path, source, *, no_pair: str) -> dict[str, list[Path]]:
    """Every format into folder/<format>/ (as `vdo render` writes them beside its images). A
    format that cannot hold these cameras (VIC-3D with tangential distortion, the pair formats
    without a pair) is skipped with a warning; without a pair, one line for both, ending with
    `no_pair` (why, and the fix: `no_pair_message`; read only then). Returns the written paths
    per format."""
    written = {}
    if not pairs:
        log.warning("matchid, vic3d: no stereo calibration written: %s", no_pair)
    for fmt, write in FORMATS.items():
        if fmt in ("matchid", "vic3d") and not pairs:
            continue
        (Path(folder) / fmt).mkdir(parents=True)
        try:
            written[fmt] = write(cameras, pairs, Path(folder) / fmt, source)
        except ConfigError as exc:
            if fmt != "vic3d":
                raise
            log.warning("vic3d calibration not written: %s", exc.message)
            (Path(folder) / fmt).rmdir()
    return written


def camera_from_layout(entry: dict, path) -> Camera:
    """A `Camera` from one layout.json entry (`vdo.outputs.report.layout`), rebuilt from its pose fields
    and checked against the K, R, t stored beside them (1e-9 relative), so that a hand-edited
    layout.json cannot export a calibration that differs from its own matrices."""
    name = str(entry.get("name", "?"))
    try:
        K = np.asarray(entry["K"], dtype=float)
        width, height = int(entry["width"]), int(entry["height"])
        cam = Camera(name=name, width=width, height=height, pixel_size=entry["pixel_um"] * 1e-6,
                     focal_length=entry["focal_mm"] * 1e-3,
                     position=np.asarray(entry["position_m"], dtype=float),
                     pan=math.radians(entry["pan_deg"]), tilt=math.radians(entry["tilt_deg"]),
                     roll=math.radians(entry["roll_deg"]),
                     principal_offset_px=(K[0, 2] - (width - 1) / 2, K[1, 2] - (height - 1) / 2),
                     distortion=tuple(float(k) for k in entry.get("distortion", [0.0] * 5)))
        stored = [np.asarray(entry[key], dtype=float) for key in ("K", "R", "t")]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ConfigError(path, f'camera "{name}"', f"is not a vdo layout entry ({exc!r})") from None
    if len(cam.distortion) != 5:
        raise ConfigError(path, f'camera "{name}".distortion', "must hold 5 numbers (k1, k2, p1, p2, k3)")
    for key, mine, theirs in zip("KRt", (cam.K, cam.R, cam.t), stored):
        if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=1e-9,
                                                         atol=1e-9 * np.abs(theirs).max()):
            raise ConfigError(path, f'camera "{name}".{key}', "does not match the camera's pose "
                                                              "fields (was layout.json edited?)")
    return cam
