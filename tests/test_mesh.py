"""TSDF fusion checked against analytic geometry: exact ray-sphere depth maps -> sphere mesh."""

import itertools
import math

import numpy as np
import open3d as o3d
import pytest
import torch
from torch import Tensor

from polargs_plugin.io import PolarInputError
from polargs_plugin.mesh import (
    MESH_PRESETS,
    keep_largest_cluster,
    mesh_settings,
    read_mesh,
    tsdf_fuse,
    write_mesh,
)
from polargs_plugin.metrics import chamfer_distance
from polargs_plugin.types import RenderOut, View

RADIUS = 1.0
SIZE = 80
FOCAL = 70.0


def look_at(eye: np.ndarray) -> np.ndarray:
    """OpenCV world_to_camera (4, 4) for a camera at ``eye`` looking at the origin."""
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def sphere_depth(K: np.ndarray, w2c: np.ndarray, radius: float, background: float = 0.0):
    """Exact camera-z depth of a sphere at the origin at each pixel centre (u+0.5, v+0.5)."""
    u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    centre = -R.T @ t
    d = d_cam @ R  # world directions (R^T d), z-component of d_cam is 1 so the ray parameter is z
    b = d @ centre
    a = (d * d).sum(-1)
    disc = b * b - a * (centre @ centre - radius**2)
    hit = disc > 0
    s = (-b - np.sqrt(np.where(hit, disc, 0.0))) / a
    depth = np.where(hit, s, background)
    return torch.from_numpy(depth[None]).float(), torch.from_numpy(hit[None])


def sphere_inputs(background: float = 0.0):
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    # Cameras at distance 3 along the 8 cube-corner directions cover the whole sphere.
    eyes = [3.0 * np.array(s) / np.sqrt(3) for s in itertools.product((-1.0, 1.0), repeat=3)]
    depths, masks, w2cs = [], [], []
    for eye in eyes:
        w2c = look_at(eye)
        depth, mask = sphere_depth(K, w2c, RADIUS, background)
        depths.append(depth)
        masks.append(mask)
        w2cs.append(torch.from_numpy(w2c))
    colour = torch.tensor([0.2, 0.6, 0.8]).view(3, 1, 1).expand(3, SIZE, SIZE)
    return depths, [colour] * len(eyes), [torch.from_numpy(K)] * len(eyes), w2cs, masks


@pytest.mark.slow
def test_tsdf_sphere_within_one_and_a_half_voxels():
    voxel = 0.02
    # A background wall at depth 4 in every view: the masks must remove it.
    depths, colours, Ks, w2cs, masks = sphere_inputs(background=4.0)
    mesh = tsdf_fuse(depths, colours, Ks, w2cs, masks=masks, voxel_size=voxel, sdf_trunc=4 * voxel, depth_trunc=6.0)
    truth = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=80)
    cd = chamfer_distance(mesh, truth, num_samples=60_000, seed=1)
    assert cd["chamfer"] < 1.5 * voxel
    assert cd["accuracy_outliers"] == 0.0 and cd["completeness_outliers"] == 0.0
    radii = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert np.abs(radii - RADIUS).max() < 2 * voxel
    colours = np.asarray(mesh.vertex_colors)
    np.testing.assert_allclose(colours.mean(0), [0.2, 0.6, 0.8], atol=2 / 255)


def test_tsdf_alpha_threshold_and_depth_trunc_remove_pixels():
    depths, colours, Ks, w2cs, masks = sphere_inputs()
    voxel = 0.05
    kw = dict(voxel_size=voxel, sdf_trunc=4 * voxel)
    # Depth truncation below the nearest surface point (distance 3 - 1 = 2) leaves nothing.
    assert len(tsdf_fuse(depths, colours, Ks, w2cs, depth_trunc=1.9, **kw).triangles) == 0
    alphas = [torch.zeros_like(d) for d in depths]
    empty = tsdf_fuse(depths, colours, Ks, w2cs, alphas=alphas, alpha_threshold=0.5, depth_trunc=6.0, **kw)
    assert len(empty.triangles) == 0
    full = tsdf_fuse(depths, colours, Ks, w2cs, alphas=[a + 1 for a in alphas], alpha_threshold=0.5, depth_trunc=6.0, **kw)
    assert len(full.triangles) > 0


def tilted_plane_depth(slope: float, K: np.ndarray, z0: float = 2.0) -> torch.Tensor:
    """Camera-z depth of the plane z = z0 + slope * x at the pixel centres (u + 0.5, v + 0.5)."""
    u = np.arange(SIZE) + 0.5
    x_over_z = (u - K[0, 2]) / K[0, 0]
    depth = np.broadcast_to(z0 / (1 - slope * x_over_z), (SIZE, SIZE))
    return torch.from_numpy(depth[None].copy()).float()


def test_tsdf_uses_half_pixel_centres():
    # A plane tilted about the y axis: depth changes by ~0.02 per pixel column, so reading the
    # pixel half a column off would bias the fused surface by ~0.008 along its normal.
    slope, z0, voxel = 0.5, 2.0, 0.02
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    depth = tilted_plane_depth(slope, K, z0)
    colour = torch.full((3, SIZE, SIZE), 0.5)
    mesh = tsdf_fuse([depth], [colour], [torch.from_numpy(K)], [torch.eye(4, dtype=torch.float64)],
                     voxel_size=voxel, sdf_trunc=4 * voxel, depth_trunc=5.0)
    p = np.asarray(mesh.vertices)
    assert len(p) > 1000
    signed = (p[:, 2] - z0 - slope * p[:, 0]) / np.hypot(1.0, slope)
    assert abs(signed.mean()) < 0.002
    assert np.abs(signed).max() < voxel


def test_keep_largest_cluster_drops_floater():
    big = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=10)
    small = o3d.geometry.TriangleMesh.create_sphere(radius=0.1, resolution=10).translate((3.0, 0, 0))
    mesh = keep_largest_cluster(big + small)
    assert len(mesh.triangles) == len(big.triangles)
    assert np.asarray(mesh.vertices)[:, 0].max() <= 1.0 + 1e-9
    # Counts are triangles, not area: the small sphere has as many as the big one and is kept at
    # fraction 0.5, a 24-triangle sphere (7 % of 360) is not.
    both = keep_largest_cluster(big + small, min_fraction=0.5)
    assert len(both.triangles) == len(big.triangles) + len(small.triangles)
    tiny = o3d.geometry.TriangleMesh.create_sphere(radius=0.1, resolution=3).translate((3.0, 0, 0))
    assert len(keep_largest_cluster(big + tiny, min_fraction=0.5).triangles) == len(big.triangles)


def test_keep_largest_cluster_spares_the_pieces_it_is_told_to():
    big = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=10)
    tiny = o3d.geometry.TriangleMesh.create_sphere(radius=0.1, resolution=3).translate((3.0, 0, 0))
    vertices = np.asarray((big + tiny).vertices)
    in_tiny = vertices[:, 0] > 2.0
    kept = keep_largest_cluster(big + tiny, min_fraction=0.5, spared=in_tiny)
    assert len(kept.triangles) == len(big.triangles) + len(tiny.triangles)
    # under the share: a tiny sphere with a third of its vertices spared is dropped
    part = in_tiny & (np.cumsum(in_tiny) <= in_tiny.sum() // 3)
    assert len(keep_largest_cluster(big + tiny, min_fraction=0.5, spared=part).triangles) == len(big.triangles)
    with pytest.raises(ValueError, match="spared must be"):
        keep_largest_cluster(big + tiny, min_fraction=0.5, spared=np.ones(3, dtype=bool))


def test_mesh_settings_presets_and_overrides():
    assert MESH_PRESETS["paper"] == {"voxel_size": 0.008, "sdf_trunc": 0.04, "depth_trunc": 10.0}
    s = mesh_settings("paper", voxel_size=0.004)
    assert s["sdf_trunc"] == pytest.approx(0.02)  # keeps the paper's 5-voxel truncation
    assert mesh_settings("synthetic", sdf_trunc=0.1)["sdf_trunc"] == 0.1
    with pytest.raises(ValueError, match="unknown mesh preset"):
        mesh_settings("nope")
    with pytest.raises(ValueError, match="voxel_size"):
        mesh_settings("paper", voxel_size=-1)


def test_tsdf_rejects_mismatched_inputs():
    depths, colours, Ks, w2cs, masks = sphere_inputs()
    with pytest.raises(ValueError, match="colors"):
        tsdf_fuse(depths, colours[:3], Ks, w2cs)
    with pytest.raises(ValueError, match=r"colour 0 must be \(3"):
        tsdf_fuse(depths, [c[:, :10] for c in colours], Ks, w2cs)


def test_write_and_read_mesh_atomic(tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=8)
    path = write_mesh(tmp_path / "sub" / "mesh.ply", mesh)
    back = read_mesh(path)
    np.testing.assert_allclose(np.asarray(back.vertices), np.asarray(mesh.vertices), atol=1e-6)
    with pytest.raises(PolarInputError):
        write_mesh(tmp_path / "mesh.unknownformat", mesh)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]  # nothing half-written
    with pytest.raises(PolarInputError, match="not found"):
        read_mesh(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("not a mesh")
    with pytest.raises(PolarInputError, match="no triangles"):
        read_mesh(tmp_path / "junk.ply")


class AnalyticSphereModel:
    """Stands in for a trained model: renders the exact unit sphere (depth, normal, alpha)."""

    def render_output(self, view: View) -> RenderOut:
        K, w2c = view.K.numpy(), view.world_to_camera.numpy()
        depth, hit = sphere_depth(K, w2c, RADIUS)
        u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
        points = depth[0].numpy()[..., None] * np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        normal = (points - w2c[:3, 3]) / RADIUS * hit[0].numpy()[..., None]  # sphere centre is at t
        colour = torch.full((3, SIZE, SIZE), 0.5)
        alpha = hit.float()
        normal = torch.from_numpy(normal.transpose(2, 0, 1)).float()
        return RenderOut(color=colour, depth=depth, normal=normal, alpha=alpha, median_depth=depth)


@pytest.mark.slow
def test_mesh_and_eval_commands_round_trip(tmp_path, monkeypatch, capsys):
    import json

    import polargs_plugin.cli.mesh as mesh_cli
    import polargs_plugin.service.evaluation as evaluation
    from polargs_plugin.service import Dataset, Run
    from polargs_plugin.cli import main

    depths, _, Ks, w2cs, masks = sphere_inputs()
    model = AnalyticSphereModel()
    views = []
    for i, (K, w2c, mask) in enumerate(zip(Ks, w2cs, masks)):
        view = View(name=f"v{i}", K=K, world_to_camera=w2c, stokes=torch.zeros(3, 3, SIZE, SIZE), mask=mask)
        # GT normals = rendered normals turned by exactly 0.3 rad towards a perpendicular m.
        n = model.render_output(view).normal.double()
        m = torch.nn.functional.normalize(torch.cross(n, torch.tensor([1.0, 0, 0]).double().view(3, 1, 1).expand_as(n), dim=0), dim=0)
        view.normal_gt = (math.cos(0.3) * n + math.sin(0.3) * m).float()
        views.append(view)
    for module in (mesh_cli, evaluation):  # the run is the analytic model, not a folder
        monkeypatch.setattr(module, "load_run", lambda run_dir, data=None: Run(run_dir, model, Dataset("fake", views, "fake"), {}))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    gt_path = write_mesh(tmp_path / "gt.ply", o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=80))

    assert main(["mesh", str(run_dir), "--voxel", "0.02", "--alpha-threshold", "0.5"]) == 0
    info = json.loads((run_dir / "tsdf_mesh.json").read_text())
    assert info["voxel_size"] == 0.02 and info["sdf_trunc"] == pytest.approx(0.08) and info["views"] == 8
    assert info["incidence_trunc"] == 2.0  # the default: truncation widened at grazing incidence
    assert main(["mesh", str(run_dir), "--voxel", "0.02", "--incidence-trunc", "1", "--out", str(tmp_path / "fixed.ply")]) == 0
    assert json.loads((tmp_path / "fixed.json").read_text())["incidence_trunc"] == 1.0

    assert main(["eval", str(run_dir), "--gt", str(gt_path), "--normals", "--cull", "--num-samples", "60000", "--quiet"]) == 0
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["chamfer"]["chamfer"] < 1.5 * 0.02 and metrics["chamfer"]["culled"] is True
    assert metrics["normal_mae_deg"] == pytest.approx(math.degrees(0.3), abs=1e-3)
    printed = capsys.readouterr().out
    assert "Chamfer (mean)" in printed and "normal MAE" in printed

    capsys.readouterr()
    # ordinary errors: one `error:` line, exit status 2, no traceback
    assert main(["eval", str(tmp_path / "missing"), "--gt", str(gt_path)]) == 2
    assert main(["eval", str(gt_path), "--gt", str(gt_path), "--normals"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("error: ") for line in err)
    assert "neither a run folder nor a mesh file" in err[0] and "needs a run folder" in err[1]


def test_tsdf_of_exact_depth_has_no_signed_bias():
    """Depth bias, part 1 (docs/evaluation.md "Depth bias"): TSDF fusion of exact depth maps puts
    the surface on the sphere; the median signed distance is far below a voxel."""
    from polargs_plugin.metrics import signed_distances

    depths, colours, Ks, w2cs, masks = sphere_inputs()
    mesh = tsdf_fuse(depths, colours, Ks, w2cs, masks=masks, voxel_size=0.02, sdf_trunc=0.08)
    signed = signed_distances(np.asarray(mesh.vertices), o3d.geometry.TriangleMesh.create_sphere(RADIUS, resolution=200))
    assert abs(np.median(signed)) < 0.1 * 0.02


def _surface_disks(radius: float, n: int) -> tuple[Tensor, Tensor, float]:
    """``n`` points spread evenly on the sphere (a Fibonacci lattice) and the rotations whose
    z axis is the outward normal there: (n, 3) means, (n, 4) wxyz quaternions, and the spacing."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), math.pi * (1 + 5**0.5) * i
    normals = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    z = np.array([0.0, 0.0, 1.0])
    quats = np.concatenate([(1 + normals @ z)[:, None], np.cross(np.broadcast_to(z, normals.shape), normals)], 1)
    quats[quats[:, 0] < 1e-6] = [0.0, 1.0, 0.0, 0.0]
    return (torch.tensor(radius * normals, dtype=torch.float32), torch.tensor(quats, dtype=torch.float32),
            math.sqrt(4 * math.pi / n) * radius)


def test_thick_gaussians_on_the_surface_render_in_front_of_it():
    """Depth bias, part 2: Gaussians centred on a sphere render their median depth in front of
    it when round (about 1.4 scales) and on it when flat, so the rendered depth and TSDF
    cannot make a mesh sit inside; an inside mesh means the trained centres sit inside."""
    from polargs_plugin.backends.reference.rasterizer import rasterize

    radius, n = RADIUS, 6000
    means, quats, spacing = _surface_disks(radius, n)
    _, _, Ks, w2cs, masks = sphere_inputs()
    offsets = {}
    for name, thickness in (("flat", 1e-3), ("round", 1.0)):
        scales = torch.tensor([[spacing, spacing, spacing * thickness]] * n, dtype=torch.float32)
        errors = []
        for K, w2c, mask in list(zip(Ks, w2cs, masks))[:2]:
            out = rasterize(means, quats, scales, torch.full((n,), 0.9), torch.full((n, 3), 0.5), K.float(), w2c.float(),
                            SIZE, SIZE)
            gt, _ = sphere_depth(K.numpy(), w2c.numpy(), radius)
            inner = torch.nn.functional.max_pool2d((~mask).float()[None], 5, 1, 2)[0] == 0
            errors.append((out.median_depth - gt)[inner])
        offsets[name] = float(torch.cat(errors).median()) / spacing
    assert abs(offsets["flat"]) < 0.15  # curvature of tangent disks only
    assert -2.0 < offsets["round"] < -0.8  # in front of the surface, ~1.4 scales


def test_the_screen_dilation_widens_the_silhouette_of_surface_gaussians():
    """Depth bias, part 3: flat Gaussians centred on the sphere cover a wider silhouette than the
    sphere's, by more than a pixel with vanilla 3DGS's dilation (eps2d = 0.3 px^2) and by a
    quarter of that without it. A training that must keep every view's silhouette therefore
    recesses its Gaussians by about that much (docs/evaluation.md "Depth bias")."""
    from polargs_plugin.backends.reference.rasterizer import rasterize

    n = 6000
    means, quats, spacing = _surface_disks(RADIUS, n)
    scales = torch.tensor([[spacing, spacing, spacing * 1e-3]] * n, dtype=torch.float32)
    _, _, Ks, w2cs, masks = sphere_inputs()
    widening = {}
    for eps2d in (0.3, 0.01):
        outs = []
        for K, w2c, mask in list(zip(Ks, w2cs, masks))[:2]:
            out = rasterize(means, quats, scales, torch.full((n,), 0.9), torch.full((n, 3), 0.5), K.float(), w2c.float(),
                            SIZE, SIZE, eps2d=eps2d)
            # (covered area - sphere's area) / the sphere's perimeter: the mean widening in pixels
            area = float(mask.sum())
            outs.append((float((out.alpha[0] > 0.5).sum()) - area) / (2 * math.sqrt(math.pi * area)))
        widening[eps2d] = float(np.mean(outs))
    assert 1.0 < widening[0.3] < 1.8  # 1.35 px: several grazing disks add up along a ray
    assert abs(widening[0.01]) < 0.35 * widening[0.3]  # 0.32 px: the tangent disks' curvature


def _grazing_plane(slope: float):
    """One camera's exact depth of the plane z = 2 + slope * x, the cosine of each pixel's incidence,
    and the plane's points at the pixel centres (the surface the view sees)."""
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    with np.errstate(divide="ignore"):
        depth = tilted_plane_depth(slope, K)
    depth = torch.where((depth > 0) & (depth < 5), depth, torch.zeros_like(depth))
    u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)])
    normal = np.array([-slope, 0.0, 1.0]) / np.hypot(1.0, slope)
    cosine = np.abs(np.einsum("i,ihw->hw", normal, rays)) / np.linalg.norm(rays, axis=0)
    seen = depth[0].numpy() > 0
    points = (depth[0].numpy() * rays)[:, seen].T
    return depth, torch.from_numpy(cosine[None]).float(), torch.from_numpy(K), points, cosine[seen]


def _fuse_plane(depth, cosine, K, cap: float, views: int = 1, min_views: int = 1):
    return tsdf_fuse([depth] * views, [torch.full((3, SIZE, SIZE), 0.5)] * views, [K] * views,
                     [torch.eye(4, dtype=torch.float64)] * views, voxel_size=0.02, sdf_trunc=0.08, depth_trunc=5.0,
                     keep_largest=False, incidences=[cosine] * views, max_trunc_scale=cap, min_views=min_views)


def test_incidence_aware_truncation_covers_more_of_a_grazing_plane():
    # Incidence cosines 0.16-0.83: a fixed truncation of 4 voxels along the rays is a band about one
    # voxel thick across the steepest part of the plane.
    slope, voxel = 2.0, 0.02
    depth, cosine, K, points, point_cosine = _grazing_plane(slope)
    covered = {}
    for cap in (1.0, 2.0):
        mesh = _fuse_plane(depth, cosine, K, cap)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        distance = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
        covered[cap] = float((distance[point_cosine < 0.5] < voxel).mean())
        # the wider band puts the surface on the plane as closely as the fixed one (0.3 voxel in the mean)
        p = np.asarray(mesh.vertices)
        off_plane = np.abs((p[:, 2] - 2.0 - slope * p[:, 0]) / np.hypot(1.0, slope))
        assert off_plane.mean() < 0.35 * voxel and off_plane.max() < 1.5 * voxel
    assert covered[2.0] > covered[1.0] + 0.05, covered


def test_incidence_aware_truncation_changes_nothing_at_normal_incidence_and_counts_views():
    depth, cosine, K, _, _ = _grazing_plane(0.2)
    facing = torch.ones_like(cosine)  # every pixel seen head-on: scale 1 everywhere
    plain, scaled = _fuse_plane(depth, facing, K, 1.0), _fuse_plane(depth, facing, K, 2.0)
    def in_order(mesh):  # open3d's hash map lists the vertices in no fixed order
        vertices = np.asarray(mesh.vertices)
        return vertices[np.lexsort(vertices.T)]

    np.testing.assert_array_equal(in_order(plain), in_order(scaled))
    # one integration pass per truncation level, but a voxel's weight still counts views
    depth, cosine, K, _, _ = _grazing_plane(2.0)
    assert len(_fuse_plane(depth, cosine, K, 2.0, views=2, min_views=2).triangles) > 0
    assert len(_fuse_plane(depth, cosine, K, 2.0, views=2, min_views=3).triangles) == 0


def test_incidence_aware_truncation_rejects_bad_input():
    depth, cosine, K, _, _ = _grazing_plane(0.5)
    with pytest.raises(ValueError, match="max_trunc_scale must be a number >= 1"):
        _fuse_plane(depth, cosine, K, 0.5)
    with pytest.raises(ValueError, match="needs one incidence map per depth map"):
        tsdf_fuse([depth], [torch.full((3, SIZE, SIZE), 0.5)], [K], [torch.eye(4)], max_trunc_scale=2.0)
    with pytest.raises(ValueError, match=r"incidence 0 must be \(1, 80, 80\)"):
        _fuse_plane(depth, cosine[0], K, 2.0)


class _HalfTransparentSphere:
    """A stand-in for a trained model: renders the exact sphere of :func:`sphere_inputs`, opaque
    (alpha 0.9) where the surface point lies above z = 0 and partly transparent (alpha 0.35, so
    no median depth) below, as flat Gaussians render the surface views see at grazing angles."""

    def __init__(self, views):
        self.views = {view.name: view for view in views}

    def render_output(self, view):
        depth, hit = sphere_depth(view.K.numpy(), view.world_to_camera.numpy(), RADIUS)
        K, w2c = view.K.numpy(), view.world_to_camera.numpy()
        u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
        cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * depth[0].numpy()[..., None]
        world_z = ((cam - w2c[:3, 3]) @ w2c[:3, :3])[..., 2]
        alpha = torch.from_numpy(np.where(hit[0].numpy(), np.where(world_z > 0, 0.9, 0.35), 0.0)[None]).float()
        median = torch.where(alpha >= 0.5, depth, torch.zeros_like(depth))
        return RenderOut(color=torch.full((3, SIZE, SIZE), 0.5), depth=depth, normal=torch.zeros(3, SIZE, SIZE),
                         alpha=alpha, median_depth=median)


def test_partial_alpha_fuses_the_partly_transparent_surface_inside_the_masks():
    """The lower half of the sphere renders partly transparent: the default fusion keeps it (the
    mesh is the whole sphere, within 1.5 voxels), with the partial fusion turned off, or without
    masks, the mesh stops at the equator."""
    from polargs_plugin.service.mesh import MeshSettings, fuse_model

    depths, _, Ks, w2cs, masks = sphere_inputs()
    views = [View(name=f"v{i}", K=K, world_to_camera=w2c, stokes=torch.zeros(3, 3, SIZE, SIZE), mask=mask)
             for i, (K, w2c, mask) in enumerate(zip(Ks, w2cs, masks))]
    model = _HalfTransparentSphere(views)
    voxel = 0.02
    settings = dict(voxel=voxel, sdf_trunc=4 * voxel, incidence_trunc=1.0)
    whole = fuse_model(model, views, MeshSettings(**settings))
    truth = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=80)
    assert chamfer_distance(whole.mesh, truth, num_samples=40_000, seed=1)["chamfer"] < 1.5 * voxel
    assert np.asarray(whole.mesh.vertices)[:, 2].min() < -0.95 * RADIUS
    assert whole.info["partial_alpha"] == MeshSettings.partial_alpha
    for off in (MeshSettings(partial_alpha=0.5, **settings), MeshSettings(masks=False, **settings)):
        half = fuse_model(model, views, off)
        assert np.asarray(half.mesh.vertices)[:, 2].min() > -0.2 * RADIUS
        assert half.info["partial_alpha"] is None


def test_partial_alpha_rejects_bad_values():
    from polargs_plugin.service.mesh import MeshSettings

    for bad in (dict(partial_alpha=-0.1), dict(partial_alpha=float("nan")), dict(alpha_threshold=1.5)):
        with pytest.raises(PolarInputError, match="must be a number in"):
            MeshSettings(**bad).tsdf("run")


class _CutSphere:
    """A stand-in for a trained model: the exact sphere of :func:`sphere_inputs`, with a band of
    its surface (world z in [-0.95, -0.8] radii) not rendered, so the cap below it fuses into a
    small piece of its own, and, in view v0 only, a patch in front of the sphere (a floater)."""

    def render_output(self, view):
        depth, hit = sphere_depth(view.K.numpy(), view.world_to_camera.numpy(), RADIUS)
        K, w2c = view.K.numpy(), view.world_to_camera.numpy()
        u, v = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
        cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * depth[0].numpy()[..., None]
        world_z = ((cam - w2c[:3, 3]) @ w2c[:3, :3])[..., 2] / RADIUS
        shown = hit[0].numpy() & ~((world_z > -0.95) & (world_z < -0.8))
        depth = torch.where(torch.from_numpy(shown)[None], depth, torch.zeros_like(depth))
        if view.name == "v0":
            patch = torch.from_numpy((np.abs(u - SIZE / 2) < 4) & (np.abs(v - SIZE / 2) < 4))[None]
            depth = torch.where(patch, depth - 0.6, depth)
        alpha = (depth > 0).float()
        return RenderOut(color=torch.full((3, SIZE, SIZE), 0.5), depth=depth, normal=torch.zeros(3, SIZE, SIZE),
                         alpha=alpha, median_depth=depth)


def test_small_pieces_inside_every_mask_survive_and_floaters_do_not():
    """The cap below the unrendered band is a small piece inside every view's mask: it stays with
    ``spare_pieces_in_masks`` and goes with the default size-only rule; the floater in front of the sphere in one view sticks
    out of the other views' silhouettes and goes either way."""
    from polargs_plugin.service.mesh import MeshSettings, fuse_model

    _, _, Ks, w2cs, masks = sphere_inputs()
    views = [View(name=f"v{i}", K=K, world_to_camera=w2c, stokes=torch.zeros(3, 3, SIZE, SIZE), mask=mask)
             for i, (K, w2c, mask) in enumerate(zip(Ks, w2cs, masks))]
    settings = dict(voxel=0.02, sdf_trunc=0.08, incidence_trunc=1.0)
    spared = fuse_model(_CutSphere(), views, MeshSettings(spare_pieces_in_masks=True, **settings))
    dropped = fuse_model(_CutSphere(), views, MeshSettings(**settings))
    for result in (spared, dropped):
        radii = np.linalg.norm(np.asarray(result.mesh.vertices), axis=1)
        assert radii.max() < RADIUS + 0.05  # no floater
    assert np.asarray(spared.mesh.vertices)[:, 2].min() < -0.97 * RADIUS  # the cap
    assert np.asarray(dropped.mesh.vertices)[:, 2].min() > -0.9 * RADIUS
    assert spared.info["spared_pieces_in_masks"] and not dropped.info["spared_pieces_in_masks"]
