"""The render op's guarantees as a researcher meets them, checked and printed as one table:

    python benchmarks/check_embedding.py [--device cpu|cuda]

1. d/d rays_d through a view-dependent field: ngp-warp against a pure-torch float64 pipeline on
   the same samples and against central finite differences of that pipeline;
2. a second derivative through rendering: refused in float32 (one line), and in float64 equal
   to the pure-torch pipeline's;
3. transposed rays (``(R @ d.T).T``, not contiguous) and [H, W, 3] rays;
4. a batch in which every ray misses: the result keeps a grad_fn and ``backward`` runs;
5. ``torch.compile(fullgraph=True)`` of ``composite``: no graph break, the same values and
   gradients as eager;
6. ``torch.autograd.gradcheck`` of ``composite`` in float64;
7. ``torch.func.grad`` and ``vmap`` of the hash-grid encoding equal to autograd; ``jacrev`` refused.
"""

from __future__ import annotations

import argparse

import torch

from ngp_warp import HashGridEncoding, MarchOptions, OccupancyGrid, composite, render_rays
from ngp_warp._reference import composite as composite_ref

CENTRE = torch.tensor([0.1, -0.05, 0.0])
MARCH = MarchOptions(step_size=0.02)


def field(positions: torch.Tensor, directions: torch.Tensor, shine: torch.Tensor):
    """A blob whose colour depends on the view direction."""
    sigma = 5.0 * torch.exp(-((positions - CENTRE.to(positions)) ** 2).sum(-1) / 0.3)
    return sigma, torch.sigmoid(positions + directions * shine)


def setup(device: str, n: int = 16):
    grid = OccupancyGrid(torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]), resolution=8).to(device)
    grid.update(0, lambda p: torch.ones(p.shape[0], device=device))
    g = torch.Generator().manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3.0
    d = torch.nn.functional.normalize(CENTRE + (torch.rand(n, 3, generator=g) - 0.5) * 0.8 - o, dim=-1)
    return grid, o.to(device), d.to(device)


def torch_render(rays_o, rays_d, shine, out):
    """float64 pure-torch pipeline on ``out``'s samples (distances held fixed)."""
    ri, t = out["ray_indices"], 0.5 * (out["t_starts"] + out["t_ends"]).double()
    sigmas, rgbs = field(rays_o[ri] + t[:, None] * rays_d[ri], rays_d[ri], shine)
    rgb, opacity, _, _ = composite_ref.composite(sigmas, rgbs, out["t_starts"], out["t_ends"], ri, rays_o.shape[0])
    return rgb + 0.5 * (1 - opacity[:, None])


def rays_d_gradient(device: str) -> tuple[bool, str]:
    grid, o, d = setup(device)
    shine = torch.tensor([1.5, -0.7, 0.9], device=device)
    dd = d.clone().requires_grad_(True)
    out = render_rays(o, dd, grid, lambda p, v: field(p, v, shine), MARCH, background=0.5, return_samples=True)
    out["rgb"][0, 0].backward()
    d64 = d.double().requires_grad_(True)
    torch_render(o.double(), d64, shine.double(), out)[0, 0].backward()
    eps, step = 1e-6, torch.zeros_like(d64)
    step[0, 1] = eps
    plus, minus = (torch_render(o.double(), d.double() + s, shine.double(), out)[0, 0] for s in (step, -step))
    ours, theirs, fd = float(dd.grad[0, 1]), float(d64.grad[0, 1]), float((plus - minus) / (2 * eps))
    return abs(ours - theirs) < 1e-3 and abs(theirs - fd) < 1e-4, f"ngp-warp {ours:.4f}, torch {theirs:.4f}, FD {fd:.4f}"


def second_order(device: str) -> tuple[bool, str]:
    grid, o, d = setup(device, 8)
    shine = torch.tensor([1.5, -0.7, 0.9], device=device, requires_grad=True)
    oo = o.clone().requires_grad_(True)
    out = render_rays(oo, d, grid, lambda p, v: field(p, v, shine), MARCH, background=0.5)
    (g,) = torch.autograd.grad(out["rgb"].sum(), oo, create_graph=True)
    try:
        torch.autograd.grad(g.square().sum(), shine)
        refused = "not refused"
    except RuntimeError as e:
        refused = f"float32 refused ({str(e).split(':')[0]})"
    s64, o64 = shine.detach().double().requires_grad_(True), o.double().requires_grad_(True)
    out = render_rays(o64, d.double(), grid, lambda p, v: field(p, v, s64), MARCH, background=0.5, return_samples=True)
    (g,) = torch.autograd.grad(out["rgb"].sum(), o64, create_graph=True)
    (ours,) = torch.autograd.grad(g.square().sum(), s64)
    o_ref = o.double().requires_grad_(True)
    (g,) = torch.autograd.grad(torch_render(o_ref, d.double(), s64, out).sum(), o_ref, create_graph=True)
    (theirs,) = torch.autograd.grad(g.square().sum(), s64)
    ok = refused.startswith("float32 refused") and torch.allclose(ours, theirs)
    return ok, f"{refused}; float64 {ours[0]:.4f} vs torch {theirs[0]:.4f}"


def strides_and_shapes(device: str) -> tuple[bool, str]:
    grid, o, d = setup(device, 24)
    shine = torch.tensor([1.5, -0.7, 0.9], device=device)
    fn = lambda p, v: field(p, v, shine)  # noqa: E731
    flat = render_rays(o, d, grid, fn, MARCH, background=0.5)["rgb"]
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1))).Q.to(device)
    transposed = (rotation @ (d @ rotation).T).T
    diff = float((render_rays(o, transposed, grid, fn, MARCH, background=0.5)["rgb"] - flat).abs().max())
    image = render_rays(o.reshape(4, 6, 3), d.reshape(4, 6, 3), grid, fn, MARCH, background=0.5)["rgb"]
    ok = not transposed.is_contiguous() and diff < 1e-4 and image.shape == (4, 6, 3)
    return ok, f"transposed rays: max difference {diff:.1e}; [4, 6, 3] rays -> rgb {list(image.shape)}"


def all_miss(device: str) -> tuple[bool, str]:
    grid, _, _ = setup(device)
    shine = torch.tensor([1.5, -0.7, 0.9], device=device, requires_grad=True)
    o = torch.tensor([[0.0, 3.0, 0.0]], device=device)
    d = torch.tensor([[0.0, 1.0, 0.0]], device=device)
    out = render_rays(o, d, grid, lambda p, v: field(p, v, shine), MARCH, background=0.5)
    out["rgb"].sum().backward()
    ok = out["n_samples"] == 0 and out["rgb"].grad_fn is not None and shine.grad is not None
    return ok, f"n_samples {out['n_samples']}, grad_fn {type(out['rgb'].grad_fn).__name__}, backward ran"


def samples(device: str, dtype=torch.float32):
    g = torch.Generator().manual_seed(2)
    n_rays, s = 5, 40
    ray_indices = torch.sort(torch.randint(0, n_rays, (s,), generator=g)).values.to(device)
    t0 = torch.rand(s, generator=g, dtype=dtype).to(device)
    t1 = t0 + 0.3 * torch.rand(s, generator=g, dtype=dtype).to(device)
    sigmas = (3 * torch.rand(s, generator=g, dtype=dtype)).to(device).requires_grad_(True)
    rgbs = torch.rand(s, 3, generator=g, dtype=dtype).to(device).requires_grad_(True)
    return sigmas, rgbs, t0, t1, ray_indices, n_rays


def compiled_composite(device: str) -> tuple[bool, str]:
    sigmas, rgbs, t0, t1, ray_indices, n_rays = samples(device)

    def loss(sigmas, rgbs):
        rgb, opacity, depth = composite(sigmas, rgbs, t0, t1, ray_indices, n_rays)
        return rgb.square().sum() + opacity.sum() + 0.3 * depth.sum()

    torch._dynamo.reset()
    value = torch.compile(loss, fullgraph=True, backend="aot_eager")(sigmas, rgbs)
    grads = torch.autograd.grad(value, (sigmas, rgbs))
    eager = loss(sigmas, rgbs)
    expected = torch.autograd.grad(eager, (sigmas, rgbs))
    diff = max(float((a - b).abs().max()) for a, b in zip(grads, expected))
    return bool(torch.allclose(value, eager)) and diff < 1e-6, f"fullgraph, gradient difference to eager {diff:.1e}"


def gradcheck_composite(device: str) -> tuple[bool, str]:
    sigmas, rgbs, t0, t1, ray_indices, n_rays = samples(device, torch.float64)
    ok = torch.autograd.gradcheck(lambda a, b: composite(a, b, t0, t1, ray_indices, n_rays), (sigmas, rgbs))
    return ok, "float64 through the public op (the pure-torch twin)"


def func_encoding(device: str) -> tuple[bool, str]:
    enc = HashGridEncoding(n_levels=4, log2_hashmap_size=10).to(device)
    with torch.no_grad():
        enc.params.uniform_(-1, 1, generator=torch.Generator(device).manual_seed(3))
    x = torch.rand(64, 3, device=device, generator=torch.Generator(device).manual_seed(4))
    points = x.clone().requires_grad_(True)
    expected = torch.autograd.grad(enc(points).square().sum(), points)[0]
    got = torch.func.grad(lambda p: enc(p).square().sum())(x)
    with torch.no_grad():
        batched, eager = torch.vmap(enc)(x.view(8, 8, 3)), enc(x)
    diff = max(float((got - expected).abs().max()), float((batched.view(64, -1) - eager).abs().max()))
    try:
        torch.func.jacrev(enc)(x[:2])
        refused = False
    except ValueError:
        refused = True
    return diff == 0.0 and refused, f"grad and vmap equal to autograd (difference {diff:.1e}); jacrev refused"


CASES = {"d/d rays_d, view-dependent field": rays_d_gradient, "second derivative": second_order,
         "strides and leading shapes": strides_and_shapes, "every ray misses": all_miss,
         "torch.compile(composite)": compiled_composite, "gradcheck(composite)": gradcheck_composite,
         "torch.func on the encoding": func_encoding}


def run(device: str) -> list[tuple[str, bool, str]]:
    return [(name, *case(device)) for name, case in CASES.items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    results = run(parser.parse_args().device)
    print("| case | holds | measured |\n|---|---|---|")
    for name, ok, detail in results:
        print(f"| {name} | {'yes' if ok else '**no**'} | {detail} |")
    if not all(ok for _, ok, _ in results):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
