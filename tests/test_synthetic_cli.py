"""`polargs generate`: writes a readable scene folder, pictures on request, rejects bad arguments."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from polargs_plugin.cli import main
from polargs_plugin.data.scene_format import read_scene_folder


def test_generate_writes_scene_and_pictures(tmp_path, capsys):
    out = tmp_path / "bumpy"
    rc = main(["generate", "--scene", "bumpy_mixed", "--out", str(out), "--views", "3", "--size", "40x32",
               "--seed", "2", "--pictures"])
    assert rc == 0
    views = read_scene_folder(out)
    assert len(views) == 3 and (views[0].width, views[0].height) == (40, 32)
    # The principal point sits at the image centre of the requested size (pixel centres at +0.5).
    assert torch.allclose(views[0].K[:2, 2], torch.tensor([20.0, 16.0], dtype=torch.float64))
    aolp_picture = cv2.imread(str(out / "pictures" / "view_001_aolp_dolp.png"), cv2.IMREAD_UNCHANGED)
    assert aolp_picture is not None and aolp_picture.shape == (32, 40, 3)
    printed = capsys.readouterr().out
    assert "bumpy_mixed" in printed and "3 x 40x32" in printed and "13 pictures" in printed
    assert (out / "pictures" / "overview.png").is_file()


def test_generate_seed_controls_noise(tmp_path):
    images = []
    for folder, seed in (("a", "1"), ("b", "1"), ("c", "5")):
        main(["generate", "--scene", "shiny_torus", "--out", str(tmp_path / folder), "--views", "1",
              "--size", "24x24", "--seed", seed])
        images.append(cv2.imread(str(tmp_path / folder / "polar" / "view_000_045.png")))
    assert np.array_equal(images[0], images[1]) and not np.array_equal(images[0], images[2])


def test_generate_a_family_scene_with_its_visibility(tmp_path, capsys):
    """--scene family:K (as ablate spells it; ``family --seed K`` too): the seed's scene; its views
    and size override; the per-view visibility of the object's triangles is written and reported."""
    from polargs_plugin.data.family import family_settings
    from polargs_plugin.data.scene_format import read_scene

    out = tmp_path / "family"
    assert main(["generate", "--scene", "family:16", "--out", str(out), "--views", "3", "--size", "36x36"]) == 0
    scene = read_scene(out)
    assert scene.name == "family-16" and len(scene.views) == 3 and scene.views[0].width == 36
    assert scene.meta["family"]["layout"] == family_settings(16).layout
    assert scene.meta["noise_std"] == family_settings(16).noise_std  # the seed's noise: --noise not given
    assert scene.visibility is not None and scene.visibility.shape[0] == 3
    printed = capsys.readouterr().out
    assert "family-16" in printed and "visibility  of the seen surface: many" in printed
    other = tmp_path / "spelt-apart"
    assert main(["generate", "--scene", "family", "--seed", "16", "--out", str(other), "--views", "3", "--size", "36x36"]) == 0
    for name in ("scene.json", "polar/view_002_090.png"):
        assert (other / name).read_bytes() == (out / name).read_bytes(), name


def test_generate_writes_an_environment_lit_scene_and_a_second_block_family_seed(tmp_path):
    """The bundled glazed_pot and a family seed of the second block that draws surroundings: the
    folder records the environment and the family's lighting, and its diffuse/specular split adds
    up to the images where nothing clipped."""
    from polargs_plugin.data.family import LIT_SEED_START, family_scene
    from polargs_plugin.data.scene_format import read_scene

    seed = next(s for s in range(LIT_SEED_START, LIT_SEED_START + 20) if family_scene(s).lighting == "environment")
    for name, scene_arg in (("pot", "glazed_pot"), ("lit", f"family:{seed}")):
        out = tmp_path / name
        assert main(["generate", "--scene", scene_arg, "--out", str(out), "--views", "2", "--size", "40x40"]) == 0
        scene = read_scene(out)
        assert scene.meta["environment"]["softboxes"], name
        if name == "lit":
            assert scene.meta["family"]["lighting"] == "environment" and scene.meta["lights"] == []
        for i, view in enumerate(scene.views):
            keep = view.mask[0] & ~scene.overexposed_masks[i][0]
            err = (view.image - scene.diffuse_gt[i] - scene.specular_gt[i])[:, keep]
            assert keep.sum() > 50 and err.abs().mean() < 0.01
            assert float(scene.specular_gt[i][:, view.mask[0]].mean()) > 0.005  # the surroundings are mirrored


def test_generate_refuses_a_seed_that_disagrees_with_the_scene_and_an_unknown_scene(tmp_path, capsys):
    out = tmp_path / "x"
    assert main(["generate", "--scene", "family:16", "--seed", "3", "--out", str(out), "--small"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --seed") and "family:16" in err and "\n" not in err and not out.exists()
    for wrong in ("family:x", "no_such_scene"):
        with pytest.raises(SystemExit) as stopped:
            main(["generate", "--scene", wrong, "--out", str(out)])
        err = capsys.readouterr().err
        assert stopped.value.code == 2 and f"unknown scene '{wrong}'" in err and "family:K" in err


def test_generate_small_option(tmp_path):
    assert main(["generate", "--scene", "glossy_plane_sphere", "--out", str(tmp_path / "s"), "--small"]) == 0
    views = read_scene_folder(tmp_path / "s")
    assert len(views) == 8 and views[0].stokes.shape[-2:] == (48, 48)


def test_generate_masks_mark_the_object_or_every_surface(tmp_path):
    """Default masks are the GT object's silhouettes (gt_mesh.ply, the sphere: the floor is
    background); --mask surface gives the whole scene's (mesh.ply, the floor included). Truth: the
    meshes ray-cast again by `metrics.mesh_silhouettes`."""
    import json

    from polargs_plugin.data.scene_format import read_gt_mesh
    from polargs_plugin.metrics import mesh_silhouettes

    for kind in ("object", "surface"):
        out = tmp_path / kind
        extra = [] if kind == "object" else ["--mask", "surface"]
        assert main(["generate", "--scene", "glossy_plane_sphere", "--out", str(out), "--views", "3", "--size", "40x40"] + extra) == 0
        views = read_scene_folder(out)
        mesh = read_gt_mesh(out, object_only=kind == "object")
        for view, silhouette in zip(views, mesh_silhouettes(mesh, views)):
            assert np.array_equal(view.mask[0].numpy(), silhouette)
        assert json.loads((out / "scene.json").read_text())["mask"] == kind
    sphere, everything = read_scene_folder(tmp_path / "object"), read_scene_folder(tmp_path / "surface")
    assert all(2 * int(a.mask.sum()) < int(b.mask.sum()) for a, b in zip(sphere, everything))


@pytest.mark.parametrize(
    "extra",
    [["--size", "12by12"], ["--size", "4x4"], ["--views", "0"], ["--bits", "12"], ["--scene", "nope"], ["--mask", "floor"]],
)
def test_generate_rejects_bad_arguments(tmp_path, extra, capsys):
    argv = ["generate", "--scene", "shiny_torus", "--out", str(tmp_path / "o")] + extra
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert "error" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_generate_refuses_a_non_empty_folder_and_overwrite_replaces_the_scene(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["generate", "--scene", "shiny_torus", "--out", str(out), "--views", "3", "--size", "16x16"]) == 0
    capsys.readouterr()
    assert main(["generate", "--scene", "bumpy_mixed", "--out", str(out), "--views", "1", "--size", "16x16"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: exists and is not empty") and "--overwrite" in err
    assert len(read_scene_folder(out)) == 3
    assert main(["generate", "--scene", "bumpy_mixed", "--out", str(out), "--views", "1", "--size", "16x16",
                 "--overwrite"]) == 0
    assert len(read_scene_folder(out)) == 1  # no view of the previous scene left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no staging folder left
    other = tmp_path / "notes"
    other.mkdir()
    (other / "mine.txt").write_text("keep")
    assert main(["generate", "--scene", "shiny_torus", "--out", str(other), "--small", "--overwrite"]) == 2
    assert "not" in capsys.readouterr().err and (other / "mine.txt").read_text() == "keep"


def test_floor_texture_speckles_the_floor_and_is_refused_for_a_scene_without_one(tmp_path, capsys):
    import json

    from polargs_plugin.data.scene_format import read_scene
    from polargs_plugin.data.scenes import FLOOR_TEXTURES, Material, evaluate_albedo

    plain, speckled = tmp_path / "plain", tmp_path / "speckled"
    for out, extra in ((plain, []), (speckled, ["--floor-texture", "speckle"])):
        assert main(["generate", "--scene", "glossy_plane_sphere", "--out", str(out), "--views", "2", "--size", "96x96",
                     "--noise", "0", "--mask", "surface"] + extra) == 0
    kinds = [m["texture"]["kind"] for m in json.loads((speckled / "scene.json").read_text())["materials"]]
    assert kinds == ["uniform", "speckle"]
    a, b = read_scene(plain), read_scene(speckled)
    for view, diffuse_a, diffuse_b in zip(a.views, a.diffuse_gt, b.diffuse_gt):
        depth = view.depth_gt[0].numpy().astype(np.float64)
        v, u = np.mgrid[0:96, 0:96] + 0.5
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view.K.numpy()).T
        w2c = view.world_to_camera.numpy()
        points = (rays * depth[..., None] - w2c[:3, 3]) @ w2c[:3, :3]  # world points of the GT depth
        floor = (depth > 0) & (np.abs(points[..., 2]) < 1e-3) & (diffuse_a[0].numpy() > 0.02)
        assert floor.mean() > 0.2
        # Same lights and shading: the floor's diffuse colour changes by the ratio of the albedos.
        albedo = {kind: evaluate_albedo(points[floor], Material("floor", (1.0, 1.0, 1.0), FLOOR_TEXTURES[kind]))[:, 0]
                  for kind in ("checker", "speckle")}
        ratio = diffuse_b[0].numpy()[floor] / diffuse_a[0].numpy()[floor]
        error = np.abs(ratio / (albedo["speckle"] / albedo["checker"]) - 1)
        assert np.median(error) < 1e-3 and np.quantile(error, 0.98) < 0.02
        assert np.std(albedo["speckle"]) > 1.5 * np.std(albedo["checker"])  # about 0.27-0.3 against 0.15
        sphere = (depth > 0) & (points[..., 2] > 0.01)
        assert torch.equal(diffuse_a[:, torch.from_numpy(sphere)], diffuse_b[:, torch.from_numpy(sphere)])
    capsys.readouterr()
    out = tmp_path / "torus"
    assert main(["generate", "--scene", "shiny_torus", "--out", str(out), "--small", "--floor-texture", "speckle"]) == 2
    assert capsys.readouterr().err.strip() == "error: --floor-texture: scene shiny_torus has no floor to texture"
    assert not out.exists()
