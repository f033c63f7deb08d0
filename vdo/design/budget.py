"""What a design will take, estimated before the work (`estimate`), and its refusal when that
does not fit (`refuse`). Candidates evenly spread over the list are judged
(`vdo.design.candidates.judge_block`): PROBE_WARM first, then one block of the size the judging
uses (`vdo.design.candidates.block_size`; at least PROBE in all), so that the process's peak
memory after it holds what judging a block takes (ray casts, Dr.Jit's and JAX's arrays, the
programs compiled), measured, not assumed. The score (`vdo.design.score.Scorer.add`) is timed
on their stored pairs; both scale to all K candidates:

    entries E = (pairs stored per probed candidate) x K,
    memory = peak after the probe's block + K CAMERA_BYTES
             + E (STORE_COPIES ENTRY_BYTES + SELECT_BYTES)  (bytes),
    judging = (probe s per candidate) x K,  search = (score s per stored pair) x E x score passes,

the score passes being greedy's n_max steps plus SEARCH_PASSES exchange passes and
POLISH_PASSES polish passes (`vdo.design.polish.polish`, which scores every feasible candidate
per slot to pick its shortlist) of every count's cameras (`score_passes`). With `[design]
score = "measured"` the probe is judged with its κ (`vdo.design.candidates.inflation`: one correlation model per new footprint), so the judging
time includes it; scaled to K it is an upper bound, the candidates sharing models on the lattice
(the built-in beam-column at 20 mm samples: 356 s estimated, 80 s taken, 9 s on the bound; at
80 mm: 117 s, 49 s, 7 s). The stored pairs and both times grow as candidates x samples, samples
as 1 / spacing^2, so a refusal names the [design] sample_spacing_mm and the candidate count that
fit.
"""

from __future__ import annotations

import math
import os
import resource
import time
from dataclasses import dataclass, replace

import numpy as np

from vdo.design.candidates import ENTRY_CHUNK, Block, Judging, block_size, collect, inventory, judge_block
from vdo.design.hull import SAMPLE_MAJOR_BYTES
from vdo.design.score import Scorer
from vdo.config.experiment import Experiment
from vdo.core.errors import ConfigError

PROBE = 64                   # candidates judged at least, evenly spread, to estimate the whole judgement
PROBE_WARM = 8               # of them judged first, untimed: their block compiles the programs
ENTRY_BYTES = 6 * 8 + 4 + 4  # one stored pair: 6 float64 information entries, float32 weight, int32 index
STORE_COPIES = 1             # the stored pairs are held once: each block's own copy (a memory map,
#                              `vdo.design.candidates.collect`) is unmapped as the whole takes it in
SELECT_BYTES = 56 + SAMPLE_MAJOR_BYTES   # bytes per stored pair that the selection adds after judging:
#                              the feasibility rule's sight lines and seen matrix (8 + 8 per usable pair),
#                              the entries' owners (4) and usable flags (1), chunked passes and the heap
#                              they leave (56; measured: scale benchmark, 7,176 candidates x 9,000 samples,
#                              0.98 GB over the 0.68 GB probe peak for 8.8 M stored pairs, 112 bytes per
#                              pair with their 56; the steel beam at 48,600 candidates x 420 samples, 67 per
#                              pair in all), and the bound's sample-major copy (`vdo.design.hull.linear_maps`)
CAMERA_BYTES = 1024          # a candidate's Camera, metadata and per-region rows (+ 9 bytes per region)
SEARCH_PASSES = 2            # exchange passes assumed per count: one that swaps, one that confirms
POLISH_PASSES = 1            # polish passes assumed per count: the one that confirms
GB = 1e9


@dataclass(frozen=True)
class Estimate:
    """What judging and selecting will take, estimated before the work (`estimate`): candidates
    K, samples N, candidates probed P, stored pairs E (the probe's mean per candidate x K), peak
    memory (bytes: the process's peak after judging the probe's full-size block, the stored pairs
    STORE_COPIES times and the selection's SELECT_BYTES per pair, the candidates' cameras),
    judging time (the probe's time per candidate x K) and search
    time (the score's time per stored pair, timed on the probe's pairs, x E x the score passes:
    greedy's n_max plus SEARCH_PASSES exchange and POLISH_PASSES polish passes of every count's
    cameras: an upper bound at full size, where those passes dominate; a small design pays more
    in each count's compilation and final judgement, which it leaves out), seconds; and the bound's and the restarts' wall-time budget, [design] bound_s +
    restart_s per count (caps; the bound spends its own in full unless it converges first; the refusal's spacing advice leaves it out, as it
    does not grow with the samples)."""

    candidates: int
    samples: int
    probed: int
    entries: int
    memory_bytes: float
    fixed_bytes: float
    judge_s: float
    search_s: float
    bound_s: float = 0.0       # the bound's and the restarts' wall-time budget: [design] (bound_s
                               # + restart_s) x the counts

    def line(self) -> str:
        bound = f" + up to {self.bound_s:.0f} s bound and restarts" if self.bound_s > 0 else ""
        return (f"design estimate: {self.candidates:,} candidates x {self.samples:,} samples, about "
                f"{self.entries:,} stored pairs (from {self.probed} probed candidates): "
                f"{self.memory_bytes / GB:.1f} GB peak, {self.judge_s:.0f} s judging + "
                f"about {self.search_s:.0f} s search{bound}")


def peak_rss() -> float:
    """The process's peak resident memory so far (bytes; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def available_memory() -> float:
    """Bytes this process may still use: MemAvailable of /proc/meminfo plus what it holds now
    (its peak so far); the physical memory where /proc is missing."""
    try:
        with open("/proc/meminfo") as fh:
            free = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("MemAvailable:"))
    except (OSError, StopIteration):
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    return free + peak_rss()


def score_passes(exp: Experiment) -> int:
    """How many times the search scores every candidate: greedy's n_max steps plus SEARCH_PASSES
    exchange and POLISH_PASSES polish passes over each count's cameras (count = min_cameras ..
    n_max)."""
    return inventory(exp) + (SEARCH_PASSES + POLISH_PASSES) * sum(counts(exp))


def counts(exp: Experiment) -> range:
    """The camera counts the design's curve runs over: min_cameras .. n_max (the inventory)."""
    n = inventory(exp)
    return range(min(exp.design.min_cameras, n), n + 1)


def estimate(exp: Experiment, j: Judging, scorer: Scorer) -> Estimate:
    """Judge PROBE_WARM candidates, then one block of `block_size` (at least PROBE in all), evenly
    spread over `j`'s list, and time the score on their pairs; scale to all candidates (the
    `Estimate` fields). The probe costs at most one block's judging more than the design."""
    K, N = len(j.cams), len(j.geometry.samples)
    probed = min(K, max(PROBE, PROBE_WARM + block_size(N)))
    pick = np.unique(np.linspace(0, K - 1, probed).astype(int)) if K else np.zeros(0, int)
    probe = replace(j, cams=tuple(j.cams[i] for i in pick), mount=tuple(j.mount[i] for i in pick),
                    kind=tuple(j.kind[i] for i in pick), u=j.u[pick], heads=j.heads[pick],
                    body=j.body[pick], target=j.target[pick])
    warm = min(len(pick), PROBE_WARM)      # the first few compile the programs: not timed
    first = judge_block(probe, 0, warm) if warm else None
    t0 = time.perf_counter()
    rest = judge_block(probe, warm, len(pick)) if len(pick) > warm else None
    judge_s = (time.perf_counter() - t0) / max(len(pick) - warm, 1) * K if rest is not None else 0.0
    block = first if rest is None else Block.join([first, rest])
    per = float(block.counts.sum()) / len(pick) if len(pick) else 0.0
    entries = int(round(per * K))
    search_s = 0.0
    sample = collect(probe, [block]) if block is not None else None
    if sample is not None and sample.index.size:
        rows = np.arange(len(sample.cameras))
        zero = (np.zeros((N, 6)), np.zeros(N))
        scorer.add(*zero, sample, rows[:1])                                  # compiles
        t0 = time.perf_counter()
        scorer.add(*zero, sample, rows)
        chunks = math.ceil(sample.index.size / ENTRY_CHUNK)    # a chunk costs the same, full or padded
        search_s = (time.perf_counter() - t0) / (chunks * ENTRY_CHUNK) * entries * score_passes(exp)
    fixed = peak_rss() + K * CAMERA_BYTES      # the peak holds the probe's full-size block
    memory = fixed + entries * (STORE_COPIES * ENTRY_BYTES + SELECT_BYTES)
    return Estimate(K, N, len(pick), entries, memory, fixed, judge_s, search_s,
                    (exp.design.bound_seconds + exp.design.restart_seconds) * len(counts(exp))
                    + (exp.design.branch_seconds if exp.design.bound_seconds > 0 else 0.0))


def refuse(exp: Experiment, est: Estimate, memory_limit: float, time_limit: float | None) -> None:
    """ConfigError naming the [design] sample_spacing_mm and the candidate count that would fit
    when `est` needs more than `memory_limit` bytes or its judging (with one) more than
    `time_limit` seconds: the judging has to finish, while the selection stops at the limit with
    the counts it has searched (`vdo.design.select.design_layout`). The stored pairs and both
    times grow as candidates x samples, samples as 1 / spacing^2."""
    over = []
    if est.memory_bytes > memory_limit:
        room = memory_limit - est.fixed_bytes
        if room <= 0:
            raise ConfigError(exp.path, "design", (
                f"{est.line()}; but only {memory_limit / GB:.1f} GB is available and this process, one "
                f"block of candidates and the {est.candidates:,} candidates' cameras already take "
                f"{est.fixed_bytes / GB:.1f} GB: free memory, or far fewer candidates (zone_points, "
                "zone_heights, rail_positions, lenses_mm, aim_offsets_deg)"))
        over.append(((est.memory_bytes - est.fixed_bytes) / room, f"{memory_limit / GB:.1f} GB of memory"))
    if time_limit is not None and est.judge_s > time_limit:
        over.append((est.judge_s / time_limit, f"the time limit of {time_limit:g} s for judging the candidates"))
    if not over:
        return
    ratio, what = max(over)
    spacing = math.ceil(exp.design.sample_spacing * 1e3 * math.sqrt(ratio))
    raise ConfigError(exp.path, "design.sample_spacing_mm", (
        f"{est.line()}: more than {' and '.join(w for _, w in over)}; a sample_spacing_mm of {spacing} "
        f"or more, or at most {int(est.candidates / ratio):,} candidates (fewer zone_points, "
        "zone_heights, rail_positions, lenses_mm or aim_offsets_deg), fits"))
