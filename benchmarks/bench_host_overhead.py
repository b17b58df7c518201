"""Host overhead of one eager training-path step on tiny inputs, where Python, autograd and
launches are all the cost: a march, the encoding forward and backward, ``composite_packed``
forward and backward.

    python benchmarks/bench_host_overhead.py LABEL

Prints the best of five means over 500 steps. Compare two trees in one session (RESULTS.md)."""
import sys
import time

import torch

from ngp_warp import HashGridEncoding, MarchOptions, OccupancyGrid, ray_marching
from ngp_warp.ops.composite import composite_packed

torch.manual_seed(0)
grid = OccupancyGrid(torch.tensor([-1.0, -1, -1, 1, 1, 1]), resolution=8)
grid.update(0, lambda p: torch.ones(p.shape[0]))
o = torch.nn.functional.normalize(torch.randn(8, 3), dim=-1) * 3
d = torch.nn.functional.normalize(-o, dim=-1)
march = MarchOptions(step_size=0.2)
enc = HashGridEncoding(n_levels=2, log2_hashmap_size=8, base_resolution=4)
x = torch.rand(64, 3)


def step():
    s = ray_marching(o, d, grid, march, validate=False)
    f = enc(x).sum()
    sig = torch.rand(s.n_samples, requires_grad=True)
    rgb = torch.rand(s.n_samples, 3, requires_grad=True)
    c = composite_packed(sig, rgb, s.t_starts, s.t_ends, s.ray_offsets, 1e-4)[0]
    (c.sum() + f).backward()


for _ in range(200):
    step()
best = []
for _ in range(5):
    t = time.perf_counter()
    for _ in range(500):
        step()
    best.append((time.perf_counter() - t) / 500 * 1e6)
print(sys.argv[1] if len(sys.argv) > 1 else "", f"{min(best):.0f} us per step (min of 5 x 500)")
