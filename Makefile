# The two commands the README opens with. Each one prepares the machine first (scripts/setup.sh).
.PHONY: setup demo test bench

setup:
	@scripts/setup.sh

demo: setup
	.venv/bin/vdo demo

test: setup
	.venv/bin/python -m pytest -q

bench: setup
	.venv/bin/python benchmarks/visibility.py
