#!/usr/bin/env bash
# The declared minimum versions, tested: every ">=" floor of pyproject.toml's dependencies pinned
# "==" (plus the gsplat extra's pin) in a second virtual environment, then the tests of the
# plug-in path (hooks, losses, correction, densification, the adapter kit, the adapters against
# their stand-ins, the patch scripts) with the package taken from this source tree.
#
# The environment is cached outside the checkout, keyed by the pins, and reused while they do
# not change: ${POLARGS_MIN_ENV_CACHE:-~/.cache/polargs_plugin/min-env}/<key>. The first build
# downloads about 2.5 GB: PyPI's Linux wheels of torch 2.3 are CUDA builds that import only with
# their nvidia-* libraries (they run on the CPU all the same); CPU-only builds come from
# PyTorch's own index, which is not used here.
#
#   bash scripts/min_env.sh              # build or reuse the environment, run the tests
#   bash scripts/min_env.sh --build      # build or reuse the environment only (CI starts this
#                                        # in the background while the main suite runs)
#   bash scripts/min_env.sh --pins       # print the pins only
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
PY=${PYTHON:-python3}
unset PYTHONPATH

pins=$("$PY" - <<'PYEOF'
import re
import tomllib

project = tomllib.load(open("pyproject.toml", "rb"))["project"]
for requirement in project["dependencies"]:
    match = re.fullmatch(r"\s*([A-Za-z0-9_.-]+)\s*>=\s*([0-9][0-9A-Za-z.]*)\s*", requirement)
    if not match:
        raise SystemExit(f"error: pyproject.toml: dependency '{requirement}' has no plain '>=' floor to pin")
    print(f"{match[1]}=={match[2]}")
print(*project["optional-dependencies"]["gsplat"], sep="\n")
PYEOF
)
if [ "${1:-}" = "--pins" ]; then
  echo "$pins"
  exit 0
fi

cache=${POLARGS_MIN_ENV_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/polargs_plugin/min-env}
key=$(printf '%s\n%s\n' "$pins" "$("$PY" -c 'import sys; print(sys.version_info[:2])')" | sha256sum | cut -c1-16)
venv="$cache/$key"
if [ ! -f "$venv/.complete" ]; then
  echo "[test-min] building $venv with the pins:" $pins
  rm -rf "$venv"
  mkdir -p "$cache"
  "$PY" -m venv "$venv"
  # shellcheck disable=SC2086
  "$venv/bin/python" -m pip --disable-pip-version-check -q install $pins pytest pytest-xdist hypothesis
  touch "$venv/.complete"
else
  echo "[test-min] reusing $venv"
fi
if [ "${1:-}" = "--build" ]; then
  exit 0
fi
"$venv/bin/python" -c 'import torch, numpy, kornia, open3d, numba; print("[test-min] torch", torch.__version__, "numpy", numpy.__version__, "kornia", kornia.__version__, "open3d", open3d.__version__, "numba", numba.__version__)'

# The package from this tree: src/ for polargs_plugin, adapters/ under its import name.
links=$(mktemp -d)
trap 'rm -rf "$links"' EXIT
ln -s "$root/adapters" "$links/polargs_adapters"
export PYTHONPATH="$root/src:$links"
tests=(tests/test_hooks.py tests/test_losses.py tests/test_correction.py tests/test_correction_hdr.py
       tests/test_densifier.py tests/test_seeding.py tests/test_filters.py tests/test_kit.py
       tests/test_patch_scripts.py tests/test_adapter_*.py)
OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \
  "$venv/bin/python" -m pytest -n 2 -q -p no:cacheprovider -m "not slow" "${tests[@]}"
