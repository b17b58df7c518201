"""GraphedDensity: bucket sizes, and replays equal to the eager density pass (CUDA)."""

import pytest
import torch

from ngp_warp.field import FieldConfig, NGPField
from ngp_warp.graphs import GraphedDensity, bucket_size


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
