# Convenience targets; every one sets up the venv first (scripts/setup.sh is a no-op when current).
PY := .venv/bin/python

.PHONY: setup test demo bench bench-quick bench-components

setup:
	bash scripts/setup.sh

test:
	bash scripts/test.sh

demo:
	bash scripts/demo.sh

# issue 6: accuracy (paper Fig. 5 + section 2.2, variants, ablations) then realtime speed; the
# time each took goes to bench/results/all.json (budget: 30 min on the 2-core machine)
bench: setup
	$(PY) bench/all.py --jobs 2

# the same, smaller (budget: 5 min); bench/results/all_quick.json
bench-quick: setup
	$(PY) bench/all.py --quick --jobs 2

# component benchmarks: render workers, detection + pose, fusion update cost, the journal, lens range
bench-components: setup
	$(PY) bench/render.py
	$(PY) bench/detect.py
	$(PY) bench/fusion.py
	$(PY) bench/journal.py
	$(PY) bench/lens_range.py
