# fitmedia: the two set-up commands of the README are `make demo` and `make test`.
PY ?= python3

.PHONY: install demo test test-fast bench synthetic

install:
	bash .ci/install.sh

demo: install
	fitmedia demo --out out/demo

# two pytest workers: CI has 2 cores, and most tests use one
test: install
	$(PY) -m pytest -q -n 2 --dist worksteal

test-fast:
	$(PY) -m pytest -q -n 2 --dist worksteal -m "not slow and not mitsuba"

bench:
	$(PY) bench/forward_single.py
	$(PY) bench/forward_mitsuba.py

synthetic:
	fitmedia synth capture_specs/bulb_120x90.yaml --medium "Lowfat Milk" --ml 16 --seed 2006 --out synthetic/default
