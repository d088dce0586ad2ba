# fitmedia: the two set-up commands of the README are `make demo` and `make test`.
PY ?= python3

.PHONY: install demo test test-fast test-calibration bench synthetic

install:
	bash .ci/install.sh

demo: install
	fitmedia demo --out out/demo

# two pytest workers: CI has 2 cores, and most tests use one; the statistical calibration
# runs (the round-trip grid, ~10 min) are left to test-calibration (docs/testing.md)
test: install
	$(PY) -m pytest -q -n 2 --dist worksteal -m "not calibration" --durations=15

test-calibration: install
	$(PY) -m pytest -q -n 2 --dist worksteal -m calibration

test-fast:
	$(PY) -m pytest -q -n 2 --dist worksteal -m "not slow and not mitsuba"

bench:
	$(PY) bench/forward_single.py
	$(PY) bench/forward_mitsuba.py

synthetic:
	fitmedia synth capture_specs/bulb_120x90.yaml --medium "Lowfat Milk" --ml 16 --seed 2006 --out synthetic/default

.PHONY: package-data mutation mutation-before

# the package's copies of the bundled geometry and demo capture (tests/test_package_data.py)
package-data:
	cp capture_specs/*.yaml fitmedia/data/capture_specs/
	cp synthetic/default/capture.yaml synthetic/default/truth.json fitmedia/data/synthetic/default/
	cp synthetic/default/images/*.tiff fitmedia/data/synthetic/default/images/

# hand-made physics mutants against the fast physics tests, on a copy in /tmp (docs/testing.md)
mutation:
	$(PY) tools/mutation.py

mutation-before:
	$(PY) tools/mutation.py --before
