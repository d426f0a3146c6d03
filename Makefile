# The two newcomer commands (README.md): `make demo` and `make test`. Each sets itself up.
PY := .venv/bin/python
SCENE ?= glossy_plane_sphere
OUT ?= out/demo
EXTRAS ?= dev,sfm,docs

.PHONY: setup demo test test-fast test-min docs check-wheel bench

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

# The inner loop: the suite without the tests marked slow (under a minute on 2 cores once the
# numba kernels are compiled and cached).
test-fast: setup
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -n 2 -q -p no:cacheprovider -m "not slow"

# The lowest declared versions of the dependencies (pyproject.toml's floors, pinned) in a second
# environment, cached under ~/.cache/polargs_plugin/min-env and reused; then the plug-in path's
# tests (hooks, losses, correction, densification, kit, adapters' stand-ins, patch scripts).
test-min:
	bash scripts/min_env.sh

# sdist + wheel, the wheel installed into a fresh venv: `polargs --help` and every adapter import.
check-wheel: setup
	bash scripts/check_wheel.sh

bench: setup
	$(PY) bench/rasterizer.py
	$(PY) bench/patchmatch.py
	$(PY) bench/preprocess.py
	$(PY) bench/plugin_overhead.py
