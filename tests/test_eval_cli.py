"""`polargs eval` / `polargs mesh`: one-line errors, object-only GT, normals from an SMVP3D folder."""

import json
import warnings

import pytest
import torch

from polargs_plugin.cli import main
from polargs_plugin.types import RenderOut


class NormalStandIn:
    """Renders each view's GT normals (so the normal MAE is 0) through the eval's code path."""

    def __init__(self, normals):
        self.normals = normals

    def render_output(self, view):
        n = self.normals[view.name]
        return RenderOut(color=torch.zeros(3, *n.shape[1:]), depth=torch.ones(1, *n.shape[1:]), normal=n,
                         alpha=torch.ones(1, *n.shape[1:]))


def test_eval_normals_on_an_smvp3d_folder(tmp_path, monkeypatch, capsys, synthetic_scene):
    """The SMVP3D/NeRSP reader loads camera-frame GT normals (`normal/`), so --normals works."""
    import polargs_plugin.service.evaluation as patched
    from polargs_plugin.service import Dataset, Run
    from polargs_plugin.data.nersp import write_nersp
    from polargs_plugin.data.registry import load_views

    scene = synthetic_scene("bumpy_mixed", num_views=3, width=40, height=40)
    write_nersp(scene.views, tmp_path / "smvp3d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        views = load_views(tmp_path / "smvp3d")
    assert all(v.normal_gt is not None for v in views)
    model = NormalStandIn({v.name: s.normal_gt for v, s in zip(views, scene.views)})
    monkeypatch.setattr(patched, "load_run", lambda run_dir, data=None: Run(run_dir, model, Dataset("fake", views, "fake"), {}))
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
        status = main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 2 and len(err) == 1 and err[0].startswith("error: ") and text in err[0], (argv, err)
        assert "Traceback" not in err[0]


def test_eval_uses_object_only_gt_of_a_scene_folder(tmp_path, capsys, synthetic_scene):
    """`--gt SCENE` reads gt_mesh.ply (the sphere without floor); a mesh equal to it scores ~0."""
    import open3d as o3d

    from polargs_plugin.data.scene_format import read_gt_mesh, write_scene

    scene = synthetic_scene("glossy_plane_sphere", num_views=2, width=24, height=24)
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


def test_eval_normals_measure_the_object_not_its_support(tmp_path, monkeypatch, synthetic_scene):
    """With surface masks, glossy_plane_sphere's masks and GT normal maps cover the floor too (as a
    capture's masks may cover the table an object stands on); with `--gt` (region object)
    the normal MAE is the sphere's, like Chamfer. The stand-in renders the GT normals except on floor
    pixels clear of the sphere, where it is off by exactly 90 deg. Independent truth: those pixels
    from the closed-form ray - sphere distance, so the object MAE is 0 and the masks MAE is
    90 deg x their share of each mask."""
    import numpy as np

    import polargs_plugin.service.evaluation as patched
    from polargs_plugin.service import Dataset, Run
    from polargs_plugin.data.registry import load_views
    from polargs_plugin.data.scene_format import read_gt_mesh, write_scene

    write_scene(synthetic_scene("glossy_plane_sphere", num_views=3, width=48, height=48, mask="surface"), tmp_path / "scene")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        views = load_views(tmp_path / "scene")
    normals, expected = {}, []
    for view in views:
        K, w2c = view.K.numpy(), view.world_to_camera.numpy()
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        u, v = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
        dirs = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ w2c[:3, :3]
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        to_centre = np.array([0.0, 0.0, 0.5]) - centre
        miss = np.linalg.norm(np.cross(dirs, to_centre), axis=-1) > 1.03 * 0.5  # ray - centre distance
        gt = view.normal_gt
        wrong = torch.from_numpy(miss)[None] & view.mask.bool() & (gt.norm(dim=0, keepdim=True) > 0)
        side = torch.linalg.cross(gt, torch.tensor([0.3, 0.5, 0.8])[:, None, None].expand_as(gt), dim=0)
        normals[view.name] = torch.where(wrong, side / side.norm(dim=0, keepdim=True).clamp_min(1e-12), gt)
        expected.append(90.0 * float(wrong.sum()) / float((view.mask.bool() & (gt.norm(dim=0, keepdim=True) > 0)).sum()))
    assert min(expected) > 10.0  # the floor is a large share of every mask
    monkeypatch.setattr(patched, "load_run", lambda run_dir, data=None: Run(run_dir, NormalStandIn(normals), Dataset("fake", views, "fake"), {}))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    import open3d as o3d

    o3d.io.write_triangle_mesh(str(run_dir / "tsdf_mesh.ply"), read_gt_mesh(tmp_path / "scene"))
    assert main(["eval", str(run_dir), "--normals", "--quiet"]) == 0
    masks = json.loads((run_dir / "metrics.json").read_text())
    assert masks["normal_region"] == "masks" and masks["normal_mae_deg"] == pytest.approx(np.mean(expected), abs=0.05)
    assert main(["eval", str(run_dir), "--normals", "--gt", str(tmp_path / "scene"), "--num-samples", "5000", "--quiet"]) == 0
    obj = json.loads((run_dir / "metrics.json").read_text())
    assert obj["normal_region"] == "object" and obj["normal_mae_deg"] == pytest.approx(0.0, abs=0.05)


def test_every_figure_eval_prints_is_named_in_its_help_and_in_the_evaluation_guide(tmp_path, capsys, synthetic_scene):
    """Each printed row, and each key of metrics.json's figures, appears in `polargs eval --help` and
    docs/evaluation.md (a mesh file with the scene's views: object region and the visible-surface
    figures; the normal MAE row from a run is added to the same metrics)."""
    import re
    from pathlib import Path

    import open3d as o3d

    from polargs_plugin.cli.eval import format_table
    from polargs_plugin.data.scene_format import read_gt_mesh, write_scene

    write_scene(synthetic_scene("glossy_plane_sphere", num_views=3, width=24, height=24), tmp_path / "scene")
    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), read_gt_mesh(tmp_path / "scene"))
    assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "scene"), "--views", str(tmp_path / "scene"),
                 "--num-samples", "5000", "--quiet"]) == 0
    capsys.readouterr()
    metrics = json.loads((tmp_path / "pred.metrics.json").read_text())
    assert "chamfer_visible" in metrics["chamfer"] and metrics["chamfer"]["region"] == "object"
    metrics.update(normal_mae_deg=1.0, normal_mae_per_view={"view_000": 1.0}, normal_region="object")
    rows = [re.split(r"\s{2,}", line)[0] for line in format_table(metrics).splitlines()]
    rows = [re.sub(r"@ [\d.e-]+$", "@ T", row) for row in rows]
    assert len(rows) == 11 and "normal MAE" in rows and "completeness by view" in rows
    bookkeeping = {"units", "culled", "seed", "visibility_classes"}  # settings and provenance, not figures
    keys = set(metrics["chamfer"]) - bookkeeping | {"normal_mae_deg", "normal_mae_per_view", "normal_region"}
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    help_text = capsys.readouterr().out
    guide = (Path(__file__).resolve().parents[1] / "docs" / "evaluation.md").read_text()
    for text, where in ((help_text, "polargs eval --help"), (guide, "docs/evaluation.md")):
        assert [row for row in rows if row not in text] == [], where
        assert sorted(key for key in keys if not re.search(rf"\b{key}\b", text)) == [], where
    for name in ("many", "few", "grazing"):
        assert name in metrics["chamfer"]["completeness_by_visibility"] and re.search(rf"\({name}\)", help_text)


def test_a_dataset_without_depth_maps_gets_its_visibility_and_normals_from_the_gt_mesh(tmp_path, monkeypatch, capsys,
                                                                                        synthetic_scene):
    """An SMVP3D/NeRSP folder carries cameras (and normal maps) but no depth maps. `polargs eval --views`
    of it ray-casts the GT depth from the `--gt` mesh (hidden by the whole scene), and its
    visible-surface figures equal those the scene folder's own depth maps give (same samples; the
    generator's maps are the same ray casts, so only samples at a silhouette pixel could differ).
    A run whose views lack GT normals gets the normal MAE against normals ray-cast from the GT
    mesh: the stand-in renders the generator's GT normals, so the MAE is the maps' difference,
    under 0.1 deg."""
    import open3d as o3d

    import polargs_plugin.service.evaluation as patched
    from polargs_plugin.data.nersp import write_nersp
    from polargs_plugin.data.registry import load_views
    from polargs_plugin.data.scene_format import write_scene
    from polargs_plugin.metrics import RAY_CAST_SOURCE
    from polargs_plugin.service import Dataset, Run

    scene = synthetic_scene("glossy_plane_sphere", num_views=4, width=40, height=40)
    write_scene(scene, tmp_path / "scene")
    write_nersp(scene.views, tmp_path / "smvp3d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        views = load_views(tmp_path / "smvp3d")
    assert all(v.depth_gt is None for v in views)
    vertices, triangles = scene.object_mesh()
    centre = vertices.mean(axis=0)
    pred = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(centre + 0.97 * (vertices - centre)),
                                     o3d.utility.Vector3iVector(triangles))
    o3d.io.write_triangle_mesh(str(tmp_path / "pred.ply"), pred)
    figures = {}
    for dataset in ("smvp3d", "scene"):
        out = tmp_path / f"{dataset}.json"
        assert main(["eval", str(tmp_path / "pred.ply"), "--gt", str(tmp_path / "scene"), "--views",
                     str(tmp_path / dataset), "--num-samples", "20000", "--quiet", "--out", str(out)]) == 0
        figures[dataset] = json.loads(out.read_text())
    cast, own = figures["smvp3d"]["chamfer"], figures["scene"]["chamfer"]
    assert cast["visibility_classes"]["source"] == RAY_CAST_SOURCE
    assert own["visibility_classes"]["source"] == "ground-truth depth maps"
    assert figures["smvp3d"]["occluder"] == str(tmp_path / "scene" / "mesh.ply")
    assert cast["visible_fraction"] == pytest.approx(own["visible_fraction"], abs=0.005)
    for key in ("chamfer_visible", "completeness_visible"):
        assert cast[key] == pytest.approx(own[key], rel=0.005), key
    for cls in ("many", "few", "grazing"):
        assert cast["visibility_shares"][cls] == pytest.approx(own["visibility_shares"][cls], abs=0.005), cls
    assert RAY_CAST_SOURCE in capsys.readouterr().out  # the table says where the visibility came from

    bare = [v.replaced(normal_gt=None) for v in views]
    model = NormalStandIn({v.name: s.normal_gt for v, s in zip(views, scene.views)})
    monkeypatch.setattr(patched, "load_run", lambda run_dir, data=None: Run(run_dir, model, Dataset("fake", bare, "fake"), {}))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    o3d.io.write_triangle_mesh(str(run_dir / "tsdf_mesh.ply"), pred)
    assert main(["eval", str(run_dir), "--normals", "--quiet"]) == 2
    assert "no ground-truth normal maps and no --gt mesh" in capsys.readouterr().err
    assert main(["eval", str(run_dir), "--normals", "--gt", str(tmp_path / "scene"), "--num-samples", "20000",
                 "--quiet"]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["normal_source"] == RAY_CAST_SOURCE and metrics["normal_region"] == "object"
    assert len(metrics["normal_mae_per_view"]) == 4 and metrics["normal_mae_deg"] < 0.1
    assert metrics["chamfer"]["visibility_classes"]["source"] == RAY_CAST_SOURCE
    assert metrics["chamfer"]["chamfer_visible"] == pytest.approx(own["chamfer_visible"], rel=0.005)
