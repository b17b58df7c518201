"""CUDA graphs: GraphedDensity's bucket sizes and replays equal to the eager density pass, and a
captured march + composite + backward replayed on new rays equal to the eager op (CUDA)."""

import pytest
import torch

from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.outputs.bench import make_rays, scene_grid
from ngp_warp.ops.composite import composite_packed
from ngp_warp.ops.graphs import GraphedDensity, bucket_size, capture_graph
from ngp_warp.ops.raymarch import ray_marching


def test_bucket_sizes_cover_n_with_at_most_a_sixteenth_to_spare():
    for n in [1, 100, 4096, 4097, 65535, 65536, 65537, 450_123, 3_000_001]:
        size = bucket_size(n)
        assert size >= n and size % 4096 == 0
        assert size < n + max(4096, n / 16)
    assert len({bucket_size(n) for n in range((1 << 16) + 1, (1 << 17) + 1, 97)}) == 16


@pytest.mark.cuda
def test_replays_equal_the_eager_density_at_any_size():
    torch.manual_seed(0)
    aabb = torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    field = NGPField(aabb, FieldConfig(n_levels=8, log2_hashmap_size=15, finest_resolution=256.0)).cuda()
    with torch.no_grad():
        field.encoding.params.uniform_(-1, 1)
    graphed = GraphedDensity(field.density)
    for n in [5000, 5003, 70_000, 5000, 300_000, 70_001]:  # repeats, new buckets, a larger buffer
        x = torch.rand(n, 3, device="cuda") * 2.2 - 1.1  # some outside the box (σ = 0)
        with torch.no_grad():
            eager = field.density(x)
        got = graphed(x)
        assert got.shape == (n,) and eager.std() > 0
        torch.testing.assert_close(got, eager, rtol=1e-5, atol=1e-6)
    assert len(graphed.graphs) == 2  # the larger buffer dropped the graphs captured before it


@pytest.mark.cuda
def test_a_captured_render_op_with_backward_replays_the_eager_op_on_new_rays():
    torch.manual_seed(0)
    grid = scene_grid("shell", "cuda")
    all_o, all_d = make_rays(6000, "cuda")
    rays_o, rays_d = all_o[:2000].clone(), all_d[:2000].clone()
    count = ray_marching(rays_o, rays_d, grid, validate=False).n_samples
    capacity = count + count // 4  # room for the other rays' counts
    sigmas = (torch.rand(capacity, device="cuda") * 20).requires_grad_(True)
    rgbs = torch.rand(capacity, 3, device="cuda").requires_grad_(True)
    g_rgb = torch.rand(2000, 3, device="cuda")

    def step():
        m = ray_marching(rays_o, rays_d, grid, validate=False, capacity=capacity)
        rgb, opacity, depth, _ = composite_packed(sigmas, rgbs, m.t_starts, m.t_ends, m.ray_offsets, 1e-4)
        g_sigmas, g_rgbs = torch.autograd.grad(rgb, (sigmas, rgbs), g_rgb)
        return rgb.detach(), opacity.detach(), depth.detach(), g_sigmas, g_rgbs

    graph, replayed = capture_graph(step, "cuda")
    previous = None
    for k in (1, 2):  # new rays written into the captured inputs
        rays_o.copy_(all_o[2000 * k : 2000 * (k + 1)])
        rays_d.copy_(all_d[2000 * k : 2000 * (k + 1)])
        graph.replay()
        eager = step()
        assert eager[1].min() < 0.5 < eager[1].max() and eager[3].abs().sum() > 0
        for got, want in zip(replayed, eager):
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
        if previous is not None:
            assert not torch.equal(previous, replayed[0])  # the replay followed the new rays
        previous = replayed[0].clone()
