"""`vdo design` resumes: the judged candidate blocks are kept beside the output folder
(`vdo.commands.design.block_store`, `vdo.design.candidates.BlockStore`) until the run folder is
written. A run interrupted after 2 of its blocks leaves no run folder and those 2 blocks; started
again with the same output folder it judges only the other blocks and writes the layout of an
uninterrupted run."""

from __future__ import annotations

import json

import pytest

from vdo.commands.design import block_store, design
from vdo.config import experiment as config
from vdo.design import candidates
from vdo.state import prepare

DESIGN = """
[design]
max_cameras = 2
rail_positions = 9
offset_m = [0, 0, 0]
sample_spacing_mm = 50
bound_s = 60
branch_s = 0
restart_s = 300
"""
# Nothing below may depend on the clock, so that the two runs compared make the same curve (twice
# in a loaded suite they did not): the bound's hull phase converges long before bound_s, no branch
# and bound (how many nodes it opens in its time follows the clock), and RESTART_PATIENCE
# fruitless starts end the restarts long before restart_s
JUDGE_BLOCK = candidates.judge_block    # the real one, before any test wraps it
PER_BLOCK = 2          # candidates per block: 5 blocks of the plate rail's 9 candidates


class Interrupt(KeyboardInterrupt):
    """What Ctrl-C raises (`vdo.core.interrupts.Interrupted` is a KeyboardInterrupt)."""


def counting(monkeypatch, stop_after: int | None = None) -> list:
    """Count `judge_block` calls (a list of the starts judged); raise `Interrupt` at call
    `stop_after` + 1."""
    judged = []

    def judge_block(j, start, stop):
        if stop_after is not None and len(judged) == stop_after:
            raise Interrupt()
        judged.append(start)
        return JUDGE_BLOCK(j, start, stop)

    monkeypatch.setattr(candidates, "judge_block", judge_block)
    return judged


def test_an_interrupted_design_resumes_from_its_judged_blocks(plate_experiment, tmp_path, monkeypatch):
    path = plate_experiment(spacing=50)
    path.write_text(path.read_text() + DESIGN)
    exp = config.load(path)
    monkeypatch.setattr(candidates, "PAIRS_PER_BLOCK", PER_BLOCK * len(prepare(exp).samples))

    whole = counting(monkeypatch)
    design(exp, tmp_path / "whole")
    blocks = len(whole)
    assert blocks >= 4 and not block_store(tmp_path / "whole").exists()

    out = tmp_path / "resumed"
    first = counting(monkeypatch, stop_after=2)
    with pytest.raises(Interrupt):
        design(exp, out)
    assert not out.exists() and first == whole[:2]
    kept = sorted(block_store(out).glob("*/*.npz"))
    assert [int(p.stem) for p in kept] == sorted(whole[:2])

    again = counting(monkeypatch)
    design(exp, out)
    assert sorted(again) == sorted(whole[2:])          # the 2 kept blocks were not judged again
    assert (out / "layout.json").read_text() == (tmp_path / "whole" / "layout.json").read_text()
    resumed, uninterrupted = (json.loads((d / "design.json").read_text()) for d in (out, tmp_path / "whole"))
    assert resumed["candidates"] == uninterrupted["candidates"] and resumed["curve"] == uninterrupted["curve"]
    for key in ("candidates", "blind_pruned", "entries"):     # (times and memory differ)
        assert resumed["measured"][key] == uninterrupted["measured"][key], key
    assert not block_store(out).exists()


def test_another_experiment_does_not_reuse_the_blocks(plate_experiment, tmp_path, monkeypatch):
    """The store's key covers what the judgement reads: another rail count or block size is
    another key (another folder, nothing read from the first); the same file read again is the
    same key."""
    path = plate_experiment(spacing=50)
    path.write_text(path.read_text() + DESIGN)
    exp = config.load(path)
    size = candidates.block_size(len(prepare(exp).samples))
    other = exp.with_settings(design={"rail_positions": 5})
    one = candidates.BlockStore.of(tmp_path, exp, size, 10)
    assert one.key != candidates.BlockStore.of(tmp_path, other, size, 10).key
    assert one.key != candidates.BlockStore.of(tmp_path, exp, size + 1, 10).key
    assert one.key == candidates.BlockStore.of(tmp_path, config.load(path), size, 10).key
