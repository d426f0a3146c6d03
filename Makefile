# The two newcomer commands (README.md): `make demo` and `make test`. Each sets itself up.
PY := .venv/bin/python
SCENE ?= glossy_plane_sphere
OUT ?= out/demo
EXTRAS ?= dev,sfm,docs

.PHONY: setup demo test docs bench

setup:
	@EXTRAS=$(EXTRAS) bash scripts/setup_env.sh

# Base and Full trained, meshed and evaluated on the bundled scene; report in $(OUT)/report.md.
demo: setup
	$(PY) -m polargs_plugin.cli demo --scene $(SCENE) --out $(OUT)

# Two pytest workers on two cores; each worker single-threaded so they do not fight.
test: setup
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -n 2 -q -p no:cacheprovider

# The user guide and the API reference (mkdocs.yml) into site/; --strict fails on any warning
# (a broken link or anchor, a docstring that does not parse).
docs: setup
	$(PY) -m mkdocs build --strict

bench: setup
	$(PY) bench/rasterizer.py
	$(PY) bench/patchmatch.py
	$(PY) bench/preprocess.py
	$(PY) bench/plugin_overhead.py
