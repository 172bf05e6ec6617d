# Convenience targets; every one sets up the venv first (scripts/setup.sh is a no-op when current).
PY := .venv/bin/python

.PHONY: setup test demo bench bench-quick bench-components

setup:
	bash scripts/setup.sh

test:
	bash scripts/test.sh

demo:
	bash scripts/demo.sh

# issue 6: accuracy (paper Fig. 5 + section 2.2, variants, ablations) and realtime speed; ~30 min
bench: setup
	$(PY) bench/accuracy.py --jobs 2
	$(PY) bench/speed.py

# the same, smaller: ~5 min
bench-quick: setup
	$(PY) bench/accuracy.py --quick --jobs 2
	$(PY) bench/speed.py --quick

# component benchmarks: render workers, detection + pose, fusion update cost
bench-components: setup
	$(PY) bench/render.py
	$(PY) bench/detect.py
	$(PY) bench/fusion.py
