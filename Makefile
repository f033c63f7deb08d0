# The two commands the README opens with. Each one prepares the machine first (scripts/setup.sh).
.PHONY: setup demo test bench

setup:
	@scripts/setup.sh

demo: setup
	.venv/bin/vdo demo

# one worker per core (at most 4), a test file per worker: its tests share compiled programs
test: setup
	.venv/bin/python -m pytest -q -n auto --maxprocesses=4 --dist loadfile

bench: setup
	.venv/bin/python benchmarks/visibility.py
