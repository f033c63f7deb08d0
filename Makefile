# The two commands the README opens with. Each one prepares the machine first (scripts/setup.sh).
.PHONY: setup demo test bench

setup:
	@scripts/setup.sh

demo: setup
	.venv/bin/vdo demo

# one worker per core (at most 4), a test file per worker: its tests share compiled programs;
# the files in collection order, the slowest first (tests/conftest.py, HEAVY_FIRST), not xdist's
# own order by test count, which handed a 2-minute file of 3 tests out last (749 -> 647 s warm
# together with that file's cut);
# one OpenBLAS thread per worker (its threads spin while they wait: with a worker per core, a
# 220 x 220 product took 12.9 ms with two threads against 0.45 ms with one on this 2-core machine)
# XLA's LLVM backend at -O0: the suite compiles ~7,700 programs and runs most of them a few times;
# on a cold cache this took the suite from 14 min 12 s to 12 min 27 s, warm it costs ~1 min
# (benchmarks/README.md, "Test suite"); the numbers tested are the same at any optimisation level
test: setup
	XLA_FLAGS="$${XLA_FLAGS:-} --xla_backend_optimization_level=0" OPENBLAS_NUM_THREADS=1 .venv/bin/python -m pytest -q -n auto --maxprocesses=4 --dist loadfile --no-loadscope-reorder

bench: setup
	.venv/bin/python benchmarks/visibility.py
