#!/usr/bin/env bash
# Build the sdist and the wheel, install the wheel into a fresh virtual environment and check the
# installed package: every package of the source tree is in the wheel, `polargs --help` runs and
# every adapter module imports, all from the wheel's copy.
#
# Offline: the build runs without isolation in the project venv (setuptools, wheel and build come
# with the dev extra), and the fresh environment borrows the project venv's installed
# dependencies (torch, open3d, ...) through a .pth file naming its site-packages. The package
# itself comes only from the wheel: Python runs the .pth files of site-packages folders only, not
# those of a folder that a .pth file adds, so the editable install's finder stays inactive there.
#
#   bash scripts/check_wheel.sh          # VENV=.venv by default, as scripts/setup_env.sh
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
VENV=${VENV:-.venv}
PY="$root/$VENV/bin/python"
[ -x "$PY" ] || PY="$VENV/bin/python"  # VENV given as an absolute path
unset PYTHONPATH

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

echo "[wheel] python -m build --no-isolation (sdist, then the wheel from the sdist)"
if ! "$PY" -m build --no-isolation --outdir "$work/dist" . >"$work/build.log" 2>&1; then
  cat "$work/build.log" >&2
  exit 1
fi
sdist=$(ls "$work"/dist/*.tar.gz)
wheel=$(ls "$work"/dist/*.whl)
echo "[wheel] built $(basename "$sdist") and $(basename "$wheel")"

# Every package of the source tree (a folder with __init__.py) must be in the wheel.
"$PY" - "$wheel" <<'EOF'
import sys
import zipfile
from pathlib import Path

names = zipfile.ZipFile(sys.argv[1]).namelist()
in_wheel = {str(Path(n).parent).replace("/", ".") for n in names if n.endswith("/__init__.py")}
in_tree = {".".join(p.parent.relative_to("src").parts) for p in Path("src").rglob("__init__.py")}
in_tree |= {".".join(("polargs_adapters",) + p.parent.relative_to("adapters").parts)
            for p in Path("adapters").rglob("__init__.py")}
missing = sorted(in_tree - in_wheel)
if missing:
    sys.exit(f"[wheel] error: {sys.argv[1]}: packages missing from the wheel: {', '.join(missing)}")
modules = sum(n.endswith(".py") for n in names)
print(f"[wheel] {len(in_wheel)} packages, {modules} modules, {len(names)} files; every package of "
      f"src/ and adapters/ is there")
EOF

echo "[wheel] fresh venv: the wheel alone (--no-deps), the project venv's dependencies by a .pth file"
"$PY" -m venv --without-pip "$work/venv"
site=$("$work/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
"$PY" -c 'import sys; print("\n".join(p for p in sys.path if p.endswith("site-packages")))' \
  >"$site/project-dependencies.pth"
"$PY" -m pip --disable-pip-version-check -q --python "$work/venv/bin/python" install --no-deps "$wheel"

# From an empty folder, so that neither the source tree nor the editable install can answer.
cd "$work"
"$work/venv/bin/polargs" --help >"$work/help.txt"
head -n 1 "$work/help.txt"
"$work/venv/bin/python" - "$site" <<'EOF'
import importlib
import pkgutil
import sys
from pathlib import Path

site = Path(sys.argv[1]).resolve()
import polargs_adapters
import polargs_plugin

for package in (polargs_plugin, polargs_adapters):
    where = Path(package.__file__).resolve()
    if site not in where.parents:
        sys.exit(f"[wheel] error: {package.__name__} imported from {where}, not from the fresh venv {site}")
editable = [name for name in sys.modules if name.startswith("__editable__")]
if editable:
    sys.exit(f"[wheel] error: the editable install's finder is active: {editable}")
names = [info.name for info in pkgutil.walk_packages(polargs_adapters.__path__, "polargs_adapters.")]
for name in names:
    module = importlib.import_module(name)
    if site not in Path(module.__file__).resolve().parents:
        sys.exit(f"[wheel] error: {name} imported from {module.__file__}")
print(f"[wheel] polargs_plugin and polargs_adapters from {site}; imported {len(names)} adapter modules: "
      + ", ".join(n.removeprefix("polargs_adapters.") for n in names))
EOF
echo "[wheel] ok"
