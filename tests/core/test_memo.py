"""vdo.core.memo and the memos that use it, and the grid-cell index of vdo.model.surface: the
oldest entry leaves first, a key tells arrays apart by value, dtype and shape, a memoized speckle
tile or gradient-energy table is the one a fresh computation gives (the memo never answers for
other arguments), and the cell index answers as a dictionary would."""

from __future__ import annotations

import numpy as np
import pytest

from vdo.config.rig import SpeckleSpec
from vdo.core.memo import Memo, digest
from vdo.model import speckle
from vdo.model.speckle import generate_pattern, gradient_energy_table, normalise, pattern_for


def test_the_oldest_entry_leaves_first():
    memo = Memo(2)
    calls = []
    for key in ("a", "b", "a", "c", "a"):
        memo.get_or(key, lambda k=key: calls.append(k) or k.upper())
    # a, b computed; a kept; c pushes a (the oldest) out; a computed again
    assert calls == ["a", "b", "c", "a"]
    assert len(memo) == 2 and "a" in memo and "c" in memo and "b" not in memo
    with pytest.raises(ValueError, match="size"):
        Memo(0)


def test_digest_tells_values_dtype_and_shape_apart():
    a = np.arange(12, dtype=np.float64)
    assert digest(a) == digest(a.copy()) == digest(a[::1])
    assert digest(a) != digest(a.reshape(3, 4))
    assert digest(a) != digest(a.astype(np.float32))
    b = a.copy()
    b[5] += 1e-12
    assert digest(a) != digest(b)
    assert digest(a.reshape(3, 4).T) == digest(np.ascontiguousarray(a.reshape(3, 4).T))


def test_memoized_tiles_and_tables_are_the_fresh_ones():
    spec = SpeckleSpec(dot_diameter=1e-3, texel=2.5e-4, tile_texels=256, seed=7)
    other = SpeckleSpec(dot_diameter=1e-3, texel=2.5e-4, tile_texels=256, seed=8)
    tile = pattern_for(spec)
    assert pattern_for(spec) is tile and not tile.flags.writeable
    np.testing.assert_array_equal(tile, generate_pattern(256, 2.5e-4, 1e-3, 0.5, 10, 7))
    assert not np.array_equal(pattern_for(other), tile)

    f, g = normalise(tile), normalise(pattern_for(other))
    first = gradient_energy_table(f, 2.5e-4)
    for args, kwargs in [((g, 2.5e-4), {}), ((f, 3e-4), {}), ((f, 2.5e-4), {"l_max": 0.01}),
                         ((f, 2.5e-4), {"n": 32}), ((f[:200], 2.5e-4), {})]:
        speckle._TABLES.clear()
        fresh = gradient_energy_table(*args, **kwargs)
        speckle._TABLES.clear()
        gradient_energy_table(f, 2.5e-4)
        again = gradient_energy_table(*args, **kwargs)      # after another tile's table
        for name in ("log_l", "g_iso", "g_aniso"):
            np.testing.assert_array_equal(getattr(fresh, name), getattr(again, name))
        assert not np.array_equal(fresh.g_aniso, first.g_aniso) or fresh.g_aniso.shape != first.g_aniso.shape
    assert gradient_energy_table(f, 2.5e-4) is gradient_energy_table(f.copy(), 2.5e-4)


def test_cell_index_answers_as_a_dictionary_of_cells_would():
    """`vdo.model.surface.CellIndex` (the grid lookups of the patch overlaps and the seam) against
    a Python dict built with setdefault: the first value of a repeated cell, -1 where absent,
    negative and large indices."""
    from vdo.model.surface import CellIndex

    rng = np.random.default_rng(3)
    cells = rng.integers(-40, 40, size=(500, 2))
    cells[::50] = [[-2**30, 2**30 - 1]]                  # far cells, repeated
    values = rng.integers(0, 10**6, size=len(cells))
    expected: dict = {}
    for c, v in zip(map(tuple, cells), values):
        expected.setdefault(c, int(v))
    queries = np.concatenate([cells, rng.integers(-45, 45, size=(2000, 2)), [[2**30, -2**30]]])
    found = CellIndex(cells, values).find(queries)
    assert found.tolist() == [expected.get(tuple(q), -1) for q in queries]
    assert CellIndex(cells).find(cells[:3]).tolist() == [0, 1, 2]
    assert CellIndex(np.zeros((0, 2))).find(cells[:2]).tolist() == [-1, -1]
