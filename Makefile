# The two newcomer commands (README.md): `make demo` and `make test`. Each sets itself up.
PY := .venv/bin/python
SCENE ?= glossy_plane_sphere
OUT ?= out/demo
EXTRAS ?= dev,sfm

.PHONY: setup demo test bench

setup:
	@EXTRAS=$(EXTRAS) bash scripts/setup_env.sh

# Base and Full trained, meshed and evaluated on the bundled scene; report in $(OUT)/report.md.
demo: setup
	$(PY) -m polargs_plugin.cli demo --scene $(SCENE) --out $(OUT)

# Two pytest workers on two cores; each worker single-threaded so they do not fight.
test: setup
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -n 2 -q -p no:cacheprovider

bench: setup
	$(PY) bench/rasterizer.py
	$(PY) bench/patchmatch.py
	$(PY) bench/preprocess.py
	$(PY) bench/plugin_overhead.py
