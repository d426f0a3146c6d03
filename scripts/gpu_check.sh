#!/usr/bin/env bash
# One GPU check, from the source tree (nothing installed): the CUDA-only tests, CUDA/CPU time
# ratios of the rasterizer, PatchMatch and SSIM (one JSON line), one ablation cell (base and full)
# on CUDA and, with --trainer NAME CHECKOUT, that trainer patched and trained 1000 iterations.
# Each step says what it could not do and why (no GPU, no open3d, no extension) instead of failing
# silently. About 5 minutes on an H200 with --iters 1500 (the cells take most of it). See
# docs/adapters/dryrun.md.
#
#   bash scripts/gpu_check.sh [--out DIR] [--scene SCENE_FOLDER] [--iters N] [--trainer NAME CHECKOUT]
#
# --scene: a scene folder made elsewhere with `polargs generate ... --export colmap` (generating
# one needs open3d, which GPU machines often lack; training it does not). --iters: the cells'
# iterations (default: the CPU schedule's 5000). Exit status: 0 when every step that ran passed,
# 1 when one failed.
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PYTHON=${PYTHON:-python3}
OUT=out/gpu_check
SCENE=""
ITERS=()
TRAINER=""
CHECKOUT=""
while [ $# -gt 0 ]; do
  case "$1" in
    --out) OUT=$2; shift 2 ;;
    --scene) SCENE=$2; shift 2 ;;
    --iters) ITERS=(--iters "$2"); shift 2 ;;
    --trainer) TRAINER=$2; CHECKOUT=$3; shift 3 ;;
    -h|--help) sed -n 2,14p "$0"; exit 0 ;;
    *) echo "error: unknown argument $1" >&2; exit 2 ;;
  esac
done
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
# polargs_adapters is the adapters/ folder: a link under that name makes it importable in place.
mkdir -p "$OUT/pythonpath"
ln -sfn "$ROOT/adapters" "$OUT/pythonpath/polargs_adapters"
export PYTHONPATH="$ROOT/src:$OUT/pythonpath${PYTHONPATH:+:$PYTHONPATH}"
FAILED=0
NOT_DONE=()
note() { echo "[gpu_check] $*"; }
skip() { note "not done: $*"; NOT_DONE+=("$*"); }
run_step() {  # name, then the command
  local name=$1; shift
  note "$name ..."
  if "$@"; then note "$name: ok"; else note "$name: FAILED"; FAILED=1; fi
}
has_module() { "$PYTHON" -c "import $1" >/dev/null 2>&1; }
missing_modules() {  # those of the modules named that $PYTHON cannot import, space-separated; one process
  "$PYTHON" - "$@" 2>/dev/null <<'PYEOF'
import importlib
import sys

missing = []
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
    except Exception:
        missing.append(name)
print(" ".join(missing), end="")
PYEOF
}

if ! "$PYTHON" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
  skip "every step: no CUDA device (torch.cuda.is_available() is False, or torch is missing)"
  note "summary: nothing run; ${#NOT_DONE[@]} step(s) not done"
  exit 0
fi
"$PYTHON" -c "import torch; print('[gpu_check] device:', torch.cuda.get_device_name(0), '| torch', torch.__version__)"
# The package's requirements for this interpreter: a plain `pip` may install for another one.
MISSING=$(missing_modules numpy scipy kornia cv2 imageio numba tqdm)
if [ -n "$MISSING" ]; then
  note "error: $PYTHON ($("$PYTHON" -c 'import sys; print(sys.executable)')) cannot import: ${MISSING% }; install them for it ($PYTHON -m pip install ...) and run again"
  exit 1
fi

# 1. The CUDA-only tests (they skip themselves without a GPU elsewhere), from the test files that
# hold them: the other files need packages (open3d) that a GPU machine may lack.
CUDA_TEST_FILES=$(grep -l "torch.cuda.is_available()" "$ROOT"/tests/test_*.py)
if ! has_module pytest || ! has_module polanalyser; then
  skip "CUDA-only tests: pytest or polanalyser (the tests' reference) is not installed for $PYTHON"
else
  run_step "CUDA-only tests" "$PYTHON" -m pytest -q -p no:cacheprovider -rs -k "cuda or gpu" $CUDA_TEST_FILES
fi

# 2. CUDA / CPU time ratios (one JSON line, also in $OUT/ratios.json).
run_step "CUDA/CPU ratios" "$PYTHON" "$ROOT/bench/gpu_ratios.py" --json "$OUT/ratios.json"

# 3. One ablation cell, base and full, on CUDA.
if [ -z "$SCENE" ]; then
  if has_module open3d; then
    SCENE="$OUT/scene"
    [ -f "$SCENE/cameras.json" ] || run_step "scene" "$PYTHON" -m polargs_plugin.cli generate --scene glossy_plane_sphere \
      --out "$SCENE" --views 24 --size 128x128 --export colmap --overwrite
  else
    skip "ablation cell and trainer run: no scene (generating one needs open3d; pass --scene FOLDER made elsewhere with --export colmap)"
  fi
fi
if [ -n "$SCENE" ]; then
  for variant in base full; do
    flags=(); [ "$variant" = base ] && flags=(--no-polar)
    run_step "ablation cell ($variant)" "$PYTHON" -m polargs_plugin.cli train "$SCENE" --out "$OUT/cell-$variant" \
      --device cuda --schedule cpu "${ITERS[@]}" "${flags[@]}"
  done
  has_module open3d || skip "meshing and Chamfer of the cells: open3d is not installed (run 'polargs mesh' and 'polargs eval' on $OUT/cell-* on a machine with it)"
fi

# 4. An upstream trainer, patched, 1000 iterations.
if [ -n "$TRAINER" ]; then
  if [ -z "$SCENE" ] || [ ! -d "$SCENE/colmap" ]; then
    skip "$TRAINER: no scene with a COLMAP export (--export colmap)"
  elif [ ! -f "$ROOT/adapters/$TRAINER/patch.py" ]; then
    skip "$TRAINER: no adapters/$TRAINER/patch.py"
  else
    run_step "patch $TRAINER" "$PYTHON" "$ROOT/adapters/$TRAINER/patch.py" "$CHECKOUT"
    (cd "$CHECKOUT" && POLARGS_DATA="$SCENE" POLARGS_PRESET=synthetic "$PYTHON" train.py -s "$SCENE/colmap" \
      -m "$OUT/trainer-$TRAINER" --iterations 1000 --densify_from_iter 100 --densification_interval 100 \
      --test_iterations 1001 --save_iterations 1000 --quiet) > "$OUT/trainer-$TRAINER.log" 2>&1
    status=$?
    if [ $status -eq 0 ]; then note "$TRAINER 1000 iterations: ok ($OUT/trainer-$TRAINER.log)"
    elif grep -q "No module named" "$OUT/trainer-$TRAINER.log"; then
      skip "$TRAINER: $(grep -m1 'No module named' "$OUT/trainer-$TRAINER.log") (build the trainer's extensions first)"
    else note "$TRAINER 1000 iterations: FAILED (see $OUT/trainer-$TRAINER.log)"; FAILED=1; fi
  fi
fi

note "summary: $([ $FAILED -eq 0 ] && echo 'every step that ran passed' || echo 'a step FAILED'); ${#NOT_DONE[@]} step(s) not done"
for item in "${NOT_DONE[@]}"; do note "  - $item"; done
exit $FAILED
