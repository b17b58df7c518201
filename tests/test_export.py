"""Mesh and point-cloud export: marching cubes of an analytic density (the demo scene's SDF),
cropping to occupied cells, vertex colours, the similarity to the original frame, points."""

import math

import pytest
import torch

from ngp_warp import _wp
from ngp_warp._reference.export import points_occupied as points_occupied_ref
from ngp_warp._reference.scene import albedo, object_distances, scene_sdf
from ngp_warp.outputs.export import crop_to_occupied, extract_mesh, point_cloud, vertex_normals
from ngp_warp.kernels import scene as S
from ngp_warp.ops.occupancy import OccupancyGrid

BOX = torch.tensor([-S.BOUND] * 3 + [S.BOUND] * 3)
DIAGONAL = 2 * S.BOUND * math.sqrt(3)
SHARPNESS = 0.02  # σ goes from 0 to 100 over a few hundredths around the surface
THRESHOLD = 50.0  # σ = 50 exactly where the SDF is 0


def analytic_sigma(x: torch.Tensor) -> torch.Tensor:
    return (100.0 * torch.sigmoid(-scene_sdf(x.double().cpu()) / SHARPNESS)).float().to(x.device)


def analytic_albedo(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    p = x.double().cpu()
    return albedo(p, object_distances(p).argmin(-1)).float().to(x.device)


def sdf_gradient(p: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    p = p.double()
    g = torch.stack([scene_sdf(p + eps * e) - scene_sdf(p - eps * e) for e in torch.eye(3, dtype=torch.float64)], -1)
    return g / g.norm(dim=-1, keepdim=True)


def surface_samples(n: int, seed: int = 0) -> torch.Tensor:
    """Points on the analytic surface: random points pulled onto it along the SDF gradient."""
    gen = torch.Generator().manual_seed(seed)
    p = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 1.2
    for _ in range(30):
        p = p - scene_sdf(p)[:, None] * sdf_gradient(p)
    return p[scene_sdf(p).abs() < 1e-7]


def nearest_distance(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.cdist(q, points.double()).amin(-1) for q in queries.double().split(256)])


def pack(occupied: torch.Tensor) -> torch.Tensor:
    """bool [levels, R, R, R] → the grid's bitfield (bit id & 7 of byte id >> 3)."""
    bits = occupied.reshape(-1).to(torch.uint8)
    bits = torch.cat([bits, bits.new_zeros(-bits.numel() % 8)]).reshape(-1, 8)
    return (bits << torch.arange(8, dtype=torch.uint8)).sum(-1).to(torch.uint8)


@pytest.fixture(scope="module")
def scene_mesh():
    return extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=96)


def test_mesh_lies_on_and_covers_the_analytic_surface(scene_mesh):
    v = scene_mesh.vertices.double()
    assert scene_mesh.faces.shape[0] > 1000
    assert scene_sdf(v).abs().mean() < 0.01 * DIAGONAL / 10  # far inside the 1 % bound
    assert scene_sdf(v).abs().max() < 3 / 95 * S.BOUND  # within a voxel
    covered = nearest_distance(surface_samples(1000), v)  # every object is meshed, not only some
    assert covered.mean() < 0.01 * DIAGONAL and covered.max() < 0.05


def test_mesh_faces_outwards_and_takes_colours_head_on(scene_mesh):
    v = scene_mesh.vertices
    normals = vertex_normals(v, scene_mesh.faces).double()
    assert (normals * sdf_gradient(v)).sum(-1).median() > 0.99
    colour_error = (scene_mesh.colors.float() / 255 - analytic_albedo(v, None)).abs().amax(-1)
    assert colour_error.median() < 0.01  # textures change across a few voxels only
    facing = extract_mesh(analytic_sigma, lambda x, d: (1 - d) / 2, BOX, threshold=THRESHOLD, resolution=48)
    seen = facing.colors.float() / 255 * 2 - 1  # = -d = the outward normal
    assert (seen.double() * sdf_gradient(facing.vertices)).sum(-1).median() > 0.95


def test_similarity_maps_vertices_and_keeps_faces_outward():
    plain = extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=40)
    angle = 0.7
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = 1.7 * torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                                    [0, 0, 1]], dtype=torch.float64)
    m[:3, 3] = torch.tensor([0.3, -2.0, 5.0])
    for mirror in (False, True):
        if mirror:
            m[:, 0] = -m[:, 0]
        mapped = extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=40,
                              world_from_scene=m.float())
        expected = plain.vertices.double() @ m[:3, :3].T + m[:3, 3]
        assert torch.allclose(mapped.vertices.double(), expected, atol=1e-4)
        assert torch.equal(mapped.colors, plain.colors)
        a, b, c = (mapped.vertices.double()[mapped.faces[:, k]] for k in range(3))
        volume = (a * torch.linalg.cross(b, c)).sum() / 6  # > 0 for outward faces
        assert abs(volume) > 0.1 and volume > 0
    with pytest.raises(ValueError, match="similarity"):
        extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=8,
                     world_from_scene=torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0])))


def test_a_mesh_too_large_for_memory_is_refused_before_sampling():
    calls = []

    def sigma(x):
        calls.append(x.shape[0])
        return analytic_sigma(x)

    with pytest.raises(ValueError, match=r"100000×100000×100000 density grid needs about 1.6e\+07 GB .*lower the resolution"):
        extract_mesh(sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=100_000)
    assert calls == []


def test_occupancy_crop_drops_triangles_in_empty_cells():
    grid = OccupancyGrid(BOX, resolution=16)
    occupied = torch.zeros(1, 16, 16, 16, dtype=torch.bool)
    occupied[0, 8:] = True  # x >= 0 only
    grid.bitfield.copy_(pack(occupied))
    mesh = extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=64, grid=grid)
    voxel = 2 * S.BOUND / 63
    assert mesh.vertices[:, 0].min() >= -voxel - 1e-6  # the marched box starts at the occupied cells
    assert mesh.vertices[:, 0].max() > 0.9  # the sphere and torus (x > 0) are there
    v = torch.tensor([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [-0.2, 0.1, 0.0], [0.5, 0.5, 0.5]])
    faces = torch.tensor([[0, 1, 2], [1, 2, 1], [3, 2, 1]])
    kept_v, kept_f = crop_to_occupied(v, faces, grid)
    assert torch.equal(kept_f, torch.tensor([[0, 1, 2], [3, 2, 1]]))  # the all-empty face is gone
    grid.bitfield.zero_()
    with pytest.raises(ValueError, match="no occupied cell"):
        extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=8, grid=grid)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_points_occupied_kernel_matches_twin(device):
    from ngp_warp.kernels import export as K

    grid = OccupancyGrid(torch.tensor([-1.0, -0.5, 0.0, 1.0, 1.5, 0.5]), resolution=8, levels=3).to(device)
    occupied = torch.rand(3, 8, 8, 8) < 0.5
    grid.bitfield.copy_(pack(occupied).to(device))
    points = (torch.rand(5000, 3) * 2 - 1) * torch.tensor([5.0, 5.0, 3.0]) + torch.tensor([0.0, 0.5, 0.25])
    out = torch.empty(5000, dtype=torch.uint8, device=device)
    _wp.launch(K.points_occupied, 5000, [_wp.to_wp(points.to(device), dtype=_wp.wp.vec3), grid.aabb, 3, 8,
                                        grid.bitfield, out], device)
    expected, margin = points_occupied_ref(points, grid.aabb_host, 8, 3, occupied)
    clear = margin > 1e-4
    assert torch.equal(out.cpu().bool()[clear], expected[clear])
    assert expected.any() and not expected.all()


def test_no_surface_is_an_error():
    with pytest.raises(ValueError, match="no surface at"):
        extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=500.0, resolution=16)
    with pytest.raises(ValueError, match="threshold"):
        extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=-1.0, resolution=16)


def test_point_cloud_puts_opaque_rays_at_their_expected_depth():
    n = 400
    o = torch.randn(n, 3)
    d = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    t = torch.rand(n) * 3 + 0.5
    opacity = torch.rand(n)
    rgb = torch.rand(n, 3)
    shift = torch.eye(4)
    shift[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    points, colors = point_cloud(o, d, t * opacity, opacity, rgb, world_from_scene=shift)
    keep = opacity > 0.5
    assert torch.allclose(points, o[keep] + d[keep] * t[keep, None] + shift[:3, 3], atol=1e-5)
    assert torch.equal(colors, (rgb[keep] * 255 + 0.5).to(torch.uint8))
    with pytest.raises(ValueError, match="depth"):
        point_cloud(o, d, t[:-1], opacity, rgb)


@pytest.mark.cuda
def test_cpu_and_cuda_meshes_agree():
    cpu = extract_mesh(analytic_sigma, analytic_albedo, BOX, threshold=THRESHOLD, resolution=64)
    gpu = extract_mesh(analytic_sigma, analytic_albedo, BOX.cuda(), threshold=THRESHOLD, resolution=64)
    assert gpu.vertices.is_cuda and gpu.vertices.shape == cpu.vertices.shape
    assert gpu.faces.shape == cpu.faces.shape
    assert nearest_distance(gpu.vertices.cpu(), cpu.vertices).max() < 1e-5
    assert nearest_distance(cpu.vertices, gpu.vertices.cpu()).max() < 1e-5
    area = [torch.linalg.cross(m.vertices[m.faces[:, 1]] - m.vertices[m.faces[:, 0]],
                               m.vertices[m.faces[:, 2]] - m.vertices[m.faces[:, 0]]).norm(dim=-1).sum().cpu()
            for m in (cpu, gpu)]
    assert torch.allclose(area[0], area[1], rtol=1e-5)


def test_export_command_refuses_bad_outputs_before_loading(tmp_path):
    from argparse import Namespace

    from ngp_warp.cli import UserError
    from ngp_warp.cli.export import cmd_export

    args = Namespace(dir=str(tmp_path), mesh=None, points=None, resolution=8, threshold=None, max_points=10,
                     scene=None, device="cpu", quiet=True)
    with pytest.raises(UserError, match="nothing to export"):
        cmd_export(args)
    args.mesh = "mesh.obj"
    with pytest.raises(UserError, match="expected a .ply path"):
        cmd_export(args)
    args.mesh, args.points = "mesh.ply", "missing/points.ply"
    with pytest.raises(UserError, match="does not exist"):
        cmd_export(args)


@pytest.mark.slow
def test_trained_demo_mesh_lies_on_the_analytic_surface(tmp_path):
    """1000 CPU steps on a small demo scene (300 gave a mean distance of 0.059, over the bound),
    meshed through the export path at the default threshold."""
    from ngp_warp.training.demo import demo_config
    from ngp_warp.data.loading import load_scene
    from ngp_warp.outputs.export import default_threshold
    from ngp_warp.data.scene import write_demo_scene
    from ngp_warp.training.trainer import Trainer

    scene = load_scene(write_demo_scene(tmp_path / "scene", width=64, height=64, n_train=30, n_test=2))
    trainer = Trainer(scene, demo_config("cpu", 1000, None, 0), device="cpu")
    trainer.train(show_progress=False)
    field = trainer.field
    with trainer.weights.averaged_in_field():
        mesh = extract_mesh(field.density, lambda x, d: field(x, d)[1], field.aabb, threshold=default_threshold(scene),
                            resolution=128, grid=trainer.grid, world_from_scene=scene.world_from_scene)
    assert scene_sdf(mesh.vertices.double()).abs().mean() < 0.01 * DIAGONAL
    assert nearest_distance(surface_samples(1000), mesh.vertices).mean() < 0.01 * DIAGONAL


def test_training_points_of_a_refined_run_come_from_its_refined_poses(tmp_path):
    """The field of a run with camera refinement was fitted through the refined rays, so its
    training points are those of the same field seen from the refined cameras."""
    from dataclasses import replace

    from ngp_warp.training.config import TrainConfig
    from ngp_warp.data.loading import load_scene
    from ngp_warp.outputs.export import training_points
    from ngp_warp.ops.field import FieldConfig
    from ngp_warp.data.scene import write_demo_scene
    from ngp_warp.training.trainer import Trainer

    scene = load_scene(write_demo_scene(tmp_path / "scene", width=24, height=24, n_train=6, n_test=1, supersample=1))
    config = TrainConfig(steps=60, target_samples=1 << 13, grid_resolution=32, steps_per_diagonal=256,
                         camera_refinement=True, field=FieldConfig(n_levels=8, log2_hashmap_size=14, hidden=32))
    trainer = Trainer(scene, config, device="cpu")
    trainer.train(show_progress=False)
    with torch.no_grad():
        trainer.cameras.omega.copy_((torch.rand(6, 3, generator=torch.Generator().manual_seed(0)) - 0.5) * 0.2)
    points, colors = training_points(trainer, 10**9)
    assert points.shape[0] > 500

    refined, given = trainer.cameras.refined_c2w(scene.train.c2w).cpu(), trainer.train_split
    trainer.cameras = None  # the same field, the poses given instead
    trainer.scene = replace(scene, train=replace(scene.train, c2w=refined))
    trainer.train_split = replace(given, c2w=refined)
    expected = training_points(trainer, 10**9)
    assert torch.equal(points, expected[0]) and torch.equal(colors, expected[1])
    trainer.scene, trainer.train_split = scene, given
    original = training_points(trainer, 10**9)[0]  # from the poses as given: elsewhere
    assert original.shape != points.shape or not torch.equal(original, points)
