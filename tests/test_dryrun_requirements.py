"""Dry runs, before anything runs: the modules a checkout's training script requires and this
environment lacks, named all at once with the command that installs them (on placeholder
checkouts), and the stand-in of ``pytorch3d.transforms`` (against scipy's rotations and analytic
ones), served where pytorch3d is not installed."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from scipy.spatial.transform import Rotation

from polargs_plugin.dryrun import trainers
from polargs_plugin.dryrun.finder import install_standins, is_installed
from polargs_plugin.dryrun.requirements import install_command, missing_modules, required_imports
from polargs_plugin.dryrun.standins import pytorch3d_transforms as p3d
from polargs_plugin.io import PolarInputError
from polargs_plugin.service.dryrun import DryRunRequest, dry_run
from test_dryrun import _placeholder_checkout

MISSING = ("polargs_placeholder_missing_a", "polargs_placeholder_missing_b", "polargs_placeholder_missing_c")


def _insert_after(path: Path, anchor: str, text: str) -> None:
    source = path.read_text()
    assert anchor in source, path
    path.write_text(source.replace(anchor, anchor + text, 1))


def _checkout_with_missing_imports(tmp_path: Path) -> Path:
    """The placeholder graphdeco checkout, its script and its modules importing made-up modules:
    three required (the script, the model module, a module the scene package imports relatively),
    the others optional (try, if, inside a function), and PGSR's pytorch3d.transforms."""
    checkout = _placeholder_checkout(tmp_path, "graphdeco_2024_train.py")
    _insert_after(checkout / "train.py", "import os\n", f"import {MISSING[0]}\n")
    (checkout / "scene" / "extra.py").write_text(f"import {MISSING[2]}.sub as sub\n")
    _insert_after(checkout / "scene" / "__init__.py", "import math\n", "from . import extra\n")
    _insert_after(checkout / "scene" / "gaussian_model.py", "import torch\n", (
        f"import sys\nfrom {MISSING[1]} import thing\n"
        "from pytorch3d.transforms import quaternion_to_matrix\n"
        "try:\n    import polargs_placeholder_optional\nexcept ImportError:\n    pass\n"
        "if sys.platform == 'never':\n    import polargs_placeholder_guarded\n"
        "def _later():\n    import polargs_placeholder_in_a_function\n"
    ))
    return checkout


def test_missing_modules_are_named_at_once_before_any_run(tmp_path: Path) -> None:
    checkout = _checkout_with_missing_imports(tmp_path)
    work = tmp_path / "work"
    with pytest.raises(PolarInputError) as caught:
        dry_run(DryRunRequest(checkout=checkout, trainer="graphdeco", workdir=work))
    message = str(caught.value)
    assert "\n" not in message
    assert f"train.py imports modules this environment lacks: {', '.join(MISSING)} — install them with: " in message
    assert message.endswith(f"{sys.executable} -m pip install {' '.join(MISSING)}")
    assert "optional" not in message and "guarded" not in message and "in_a_function" not in message
    assert "pytorch3d" not in message  # installed, or else served
    assert not work.exists()  # no scene, no run


def test_the_command_line_prints_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from polargs_plugin.cli import main

    checkout = _checkout_with_missing_imports(tmp_path)
    assert main(["dryrun", str(checkout), "--trainer", "graphdeco", "--workdir", str(tmp_path / "work")]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {checkout}: train.py imports modules") and MISSING[2] in lines[0]
    assert "scene:" not in captured.out


def test_required_imports_follow_the_checkouts_modules(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "inner").mkdir(parents=True)  # a package without __init__.py
    (tmp_path / "pkg" / "inner" / "deep.py").write_text("from ... import beyond\nimport deep_third\n")
    (tmp_path / "pkg" / "inner" / "__init__.py").write_text("from .deep import *\n")
    (tmp_path / "pkg" / "helpers.py").write_text("import helper_third\n")
    (tmp_path / "unused.py").write_text("import never_imported\n")
    (tmp_path / "train.py").write_text(
        "import os, json\n"
        "from pkg import helpers\n"
        "import pkg.inner\n"
        "class A:\n    import in_a_class\n"
        "with open(os.devnull):\n    from in_a_with.sub import x\n"
        "for _ in range(0):\n    import in_a_loop\n"
        "if __name__ == '__main__':\n    import in_main\n"
        "else:\n    import in_main_else\n"
    )
    found = required_imports(tmp_path, tmp_path / "train.py")
    assert set(found) == {"os", "json", "in_a_class", "in_a_with.sub", "in_main", "helper_third", "deep_third"}
    assert found["in_a_with.sub"] == "train.py:7" and found["deep_third"] == "pkg/inner/deep.py:2"
    assert missing_modules(tmp_path, tmp_path / "train.py", {}) == sorted(
        ["deep_third", "helper_third", "in_a_class", "in_a_with", "in_main"])
    served = {"in_a_with": "x", "in_a_with.sub": "x", "in_main": "y"}
    assert missing_modules(tmp_path, tmp_path / "train.py", served) == ["deep_third", "helper_third", "in_a_class"]
    # a served sub-module of a package that is not served (gsplat's torchmetrics.image.lpip): the package must be there
    assert "in_a_with" in missing_modules(tmp_path, tmp_path / "train.py", {"in_a_with.sub": "x"})


def test_a_served_package_still_needs_what_is_not_served(tmp_path: Path) -> None:
    (tmp_path / "train.py").write_text("from pytorch3d.transforms import quaternion_to_matrix\n"
                                       "from pytorch3d import transforms\nimport pytorch3d.ops\n")
    served = trainers.FALLBACKS["pytorch3d"]
    assert missing_modules(tmp_path, tmp_path / "train.py", served) == ([] if is_installed("pytorch3d") else ["pytorch3d"])
    (tmp_path / "train.py").write_text("from pytorch3d.transforms import quaternion_to_matrix\nimport pytorch3d\n")
    assert missing_modules(tmp_path, tmp_path / "train.py", served) == []


def test_install_command_uses_pypi_names_and_torchs_own_index() -> None:
    command = install_command(["cv2", "einops", "PIL", "pytorch3d", "skimage", "sklearn", "torchvision", "yaml"], "py")
    plain, torchvision, pytorch3d = command.split(" && ")
    assert plain == "py -m pip install opencv-python-headless einops pillow scikit-image scikit-learn pyyaml"
    assert torchvision.startswith(f'py -m pip install torchvision "torch=={torch.__version__}"')
    build = torch.__version__.partition("+")[2]
    assert torchvision.endswith(f"--index-url https://download.pytorch.org/whl/{build}" if build else '"')
    assert pytorch3d.startswith("py -m pip install --no-build-isolation") and "facebookresearch/pytorch3d" in pytorch3d
    assert install_command(["torchvision"], "py") == torchvision


def test_pytorch3d_transforms_is_served_only_where_pytorch3d_is_absent(monkeypatch: pytest.MonkeyPatch) -> None:
    spec = trainers.TRAINERS["pgsr"]
    monkeypatch.setattr(trainers, "is_installed", lambda name: True)
    assert trainers.served_modules(spec) == spec.standins
    monkeypatch.setattr(trainers, "is_installed", lambda name: False)
    table = trainers.served_modules(spec)
    assert table["pytorch3d.transforms"] == "polargs_plugin.dryrun.standins.pytorch3d_transforms"
    assert all(table[name] == module for name, module in spec.standins.items())
    if is_installed("pytorch3d"):
        pytest.skip("pytorch3d is installed here: the stand-in is not imported under its name")
    finder = install_standins({name: table[name] for name in ("pytorch3d", "pytorch3d.transforms")})
    try:
        import pytorch3d  # noqa: PLC0415
        from pytorch3d.transforms import quaternion_to_matrix  # noqa: PLC0415

        assert quaternion_to_matrix is p3d.quaternion_to_matrix and pytorch3d.transforms is p3d
        assert not is_installed("pytorch3d")  # the stand-in finder does not count
    finally:
        sys.meta_path.remove(finder)
        for name in ("pytorch3d", "pytorch3d.transforms"):
            sys.modules.pop(name, None)


def test_the_dry_run_process_serves_pytorch3d_transforms(tmp_path: Path) -> None:
    """The launch process of a dry run (graphdeco's placeholder checkout: the fallbacks are served
    to every trainer) whose script imports pytorch3d.transforms as PGSR's model does."""
    checkout = _placeholder_checkout(tmp_path, "graphdeco_2024_train.py")
    script, out = tmp_path / "uses_pytorch3d.py", tmp_path / "out.json"
    script.write_text(
        "import json, torch\nimport pytorch3d.transforms as t\nfrom pytorch3d.transforms import quaternion_to_matrix\n"
        "half = 0.5 ** 0.5\n"
        f"json.dump({{'module': t.__name__, 'matrix': quaternion_to_matrix(torch.tensor([half, 0, 0, half])).tolist()}},"
        f" open({str(out)!r}, 'w'))\n"
    )
    report = tmp_path / "report.json"
    done = subprocess.run([sys.executable, "-m", "polargs_plugin.dryrun.launch", "--trainer", "graphdeco", "--checkout",
                           str(checkout), "--script", str(script), "--report", str(report)],
                          cwd=checkout, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:] + report.read_text()
    assert json.loads(report.read_text())["finished"] is True
    result = json.loads(out.read_text())
    if not is_installed("pytorch3d"):
        assert result["module"] == "polargs_plugin.dryrun.standins.pytorch3d_transforms"
    assert torch.allclose(torch.tensor(result["matrix"]), torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), atol=1e-6)


# ---------------------------------------------------------------- the pytorch3d.transforms stand-in
def _unit_quaternions(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)


def _scipy(q: torch.Tensor) -> Rotation:
    return Rotation.from_quat(q[..., [1, 2, 3, 0]].numpy())  # scipy: scalar last


def test_quaternion_to_matrix_matches_scipy_and_is_a_rotation() -> None:
    q = _unit_quaternions(500)
    R = p3d.quaternion_to_matrix(q)
    assert torch.allclose(R, torch.from_numpy(_scipy(q).as_matrix()), atol=1e-12)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=q.dtype).expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=q.dtype), atol=1e-12)
    assert torch.allclose(p3d.quaternion_to_matrix(3.0 * q), R, atol=1e-12)  # a scaled quaternion: the same rotation
    assert torch.allclose(p3d.quaternion_to_matrix(-q), R, atol=1e-12)
    batched = p3d.quaternion_to_matrix(q[:30].reshape(2, 3, 5, 4).float())
    assert batched.shape == (2, 3, 5, 3, 3) and batched.dtype == torch.float32
    angle = 0.3  # about x, analytically
    about_x = p3d.quaternion_to_matrix(torch.tensor([math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]))
    c, s = math.cos(angle), math.sin(angle)
    assert torch.allclose(about_x, torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]]), atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        p3d.quaternion_to_matrix(torch.zeros(2, 3))


def test_matrix_to_quaternion_inverts_it_everywhere() -> None:
    q = p3d.standardize_quaternion(_unit_quaternions(500, seed=1))
    assert torch.allclose(p3d.matrix_to_quaternion(p3d.quaternion_to_matrix(q)), q, atol=1e-12)
    # half turns (w = 0) and near them, about every axis, and the identity: each branch of the read-out
    special = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0],
                            [1e-9, 0, 0.6, 0.8], [0.5, 0.5, 0.5, 0.5]], dtype=torch.float64)
    back = p3d.matrix_to_quaternion(p3d.quaternion_to_matrix(special))
    assert torch.allclose(p3d.quaternion_to_matrix(back), p3d.quaternion_to_matrix(special), atol=1e-12)
    assert (back[:, 0] >= 0).all() and torch.allclose(back.norm(dim=-1), torch.ones(7, dtype=back.dtype))
    scipy_q = torch.from_numpy(Rotation.random(200, random_state=2).as_quat())[:, [3, 0, 1, 2]]
    ours = p3d.matrix_to_quaternion(torch.from_numpy(_scipy(scipy_q).as_matrix()))
    assert torch.allclose(ours, p3d.standardize_quaternion(scipy_q), atol=1e-12)
    R = p3d.quaternion_to_matrix(q[:4]).requires_grad_()
    p3d.matrix_to_quaternion(R).sum().backward()
    assert torch.isfinite(R.grad).all()


def test_quaternion_algebra_matches_matrix_algebra() -> None:
    a, b = _unit_quaternions(200, seed=3), _unit_quaternions(200, seed=4)
    Ra, Rb = p3d.quaternion_to_matrix(a), p3d.quaternion_to_matrix(b)
    product = p3d.quaternion_multiply(a, b)
    assert torch.allclose(p3d.quaternion_to_matrix(product), Ra @ Rb, atol=1e-12) and (product[:, 0] >= 0).all()
    assert torch.allclose(p3d.quaternion_raw_multiply(a, p3d.quaternion_invert(a)),
                          torch.tensor([1.0, 0, 0, 0], dtype=a.dtype).expand_as(a), atol=1e-12)
    points = torch.randn(200, 3, dtype=a.dtype, generator=torch.Generator().manual_seed(5))
    assert torch.allclose(p3d.quaternion_apply(a, points), (Ra @ points[..., None])[..., 0], atol=1e-12)
    with pytest.raises(ValueError, match="3 coordinates"):
        p3d.quaternion_apply(a, points[:, :2])


def test_axis_angle_conversions_match_scipy() -> None:
    g = torch.Generator().manual_seed(6)
    axis_angle = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    axis_angle = axis_angle * torch.rand(300, 1, generator=g, dtype=torch.float64) * math.pi
    truth = Rotation.from_rotvec(axis_angle.numpy())
    assert torch.allclose(p3d.axis_angle_to_matrix(axis_angle), torch.from_numpy(truth.as_matrix()), atol=1e-12)
    q = p3d.axis_angle_to_quaternion(axis_angle)
    assert torch.allclose(q, torch.from_numpy(truth.as_quat())[:, [3, 0, 1, 2]], atol=1e-12)
    assert torch.allclose(p3d.quaternion_to_axis_angle(q), axis_angle, atol=1e-12)
    assert torch.allclose(p3d.matrix_to_axis_angle(p3d.axis_angle_to_matrix(axis_angle)), axis_angle, atol=1e-10)
    tiny = torch.tensor([[1e-9, -2e-9, 3e-9], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    matrix = p3d.axis_angle_to_matrix(tiny)
    assert torch.allclose(matrix, torch.from_numpy(Rotation.from_rotvec(tiny.detach().numpy()).as_matrix()), atol=1e-15)
    matrix.sum().backward()
    assert torch.isfinite(tiny.grad).all()
    assert torch.allclose(p3d.quaternion_to_axis_angle(p3d.axis_angle_to_quaternion(tiny)), tiny, atol=1e-15)
