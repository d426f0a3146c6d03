"""`polargs eval` / `polargs mesh`: one-line errors, object-only GT, normals from an SMVP3D folder."""

import json
import warnings

import pytest
import torch

from polargs_plugin.cli import main
from polargs_plugin.data.synthetic import generate_scene
from polargs_plugin.types import RenderOut


class NormalStandIn:
    """Renders each view's GT normals (so the normal MAE is 0) through the eval's code path."""

    def __init__(self, normals):
        self.normals = normals

    def render(self, view):
        n = self.normals[view.name]
        return RenderOut(color=torch.zeros(3, *n.shape[1:]), depth=torch.ones(1, *n.shape[1:]), normal=n,
                         alpha=torch.ones(1, *n.shape[1:]))


def test_eval_normals_on_an_smvp3d_folder(tmp_path, monkeypatch, capsys):
    """The SMVP3D/NeRSP reader loads camera-frame GT normals (`normal/`), so --normals works."""
    import polargs_plugin.cli.mesh as cli_mesh
    from polargs_plugin.data.nersp import write_nersp
    from polargs_plugin.data.registry import load_views

    scene = generate_scene("bumpy_mixed", num_views=3, width=40, height=40)
    write_nersp(scene.views, tmp_path / "smvp3d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        views = load_views(tmp_path / "smvp3d")
    assert all(v.normal_gt is not None for v in views)
    model = NormalStandIn({v.name: s.normal_gt for v, s in zip(views, scene.views)})
    monkeypatch.setattr(cli_mesh, "load_run", lambda run_dir: (model, views))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    assert main(["eval", str(run_dir), "--normals", "--quiet"]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["normal_mae_deg"] == pytest.approx(0.0, abs=0.05) and len(metrics["normal_mae_per_view"]) == 3


def test_eval_and_mesh_errors_are_one_line(tmp_path, capsys):
    mesh_file = tmp_path / "m.ply"
    import open3d as o3d

    o3d.io.write_triangle_mesh(str(mesh_file), o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=8))
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        (["eval", str(mesh_file), "--gt", str(empty)], "no ground-truth mesh in this folder"),
        (["eval", str(mesh_file), "--gt", str(tmp_path / "nope.ply")], "not found"),
        (["eval", str(empty), "--gt", str(mesh_file)], "tsdf_mesh.ply"),
        (["eval", str(mesh_file)], "nothing to do"),
        (["mesh", str(empty)], "summary.json"),
        (["mesh", str(tmp_path / "missing")], "run folder not found"),
    ]
    for argv, text in cases:
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and err[0].startswith("error: ") and text in err[0], (argv, err)
        assert "Traceback" not in err[0]


def test_eval_uses_object_only_gt_of_a_scene_folder(tmp_path, capsys):
    """`--gt SCENE` reads gt_mesh.ply (the sphere without floor); a mesh equal to it scores ~0."""
    import open3d as o3d

    from polargs_plugin.data.scene_format import read_gt_mesh, write_scene

    scene = generate_scene("glossy_plane_sphere", num_views=2, width=24, height=24)
    write_scene(scene, tmp_path / "scene")
    gt = read_gt_mesh(tmp_path / "scene")
    full = read_gt_mesh(tmp_path / "scene", object_only=False)
    assert len(gt.triangles) < len(full.triangles)
    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), gt)
    assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "scene"), "--num-samples", "20000", "--quiet"]) == 0
    metrics = json.loads((tmp_path / "pred.metrics.json").read_text())
    assert metrics["gt"].endswith("gt_mesh.ply") and metrics["chamfer"]["region"] == "all"
    assert abs(metrics["chamfer"]["signed_distance_median"]) < 1e-4
    assert "signed distance" in capsys.readouterr().out
