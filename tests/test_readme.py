"""The README's embedding example runs as written (a few iterations, small batches)."""

import re
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_render_example_trains():
    text = README.read_text()
    code = re.search(r"## Embedding the render op.*?```python\n(.*?)```", text, re.S).group(1)
    assert "render_rays" in code
    code = code.replace("range(1000)", "range(4)")
    target_color = torch.tensor([0.2, 0.6, 0.9])

    def next_batch(n=256):
        o = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) * 4.0
        d = torch.nn.functional.normalize(torch.randn(n, 3) * 0.2 - o, dim=-1)
        device = scope["device"]  # the example picks its device before asking for batches
        return o.to(device), d.to(device), target_color.expand(n, 3).to(device)

    scope = {"next_batch": next_batch}
    exec(compile(code, str(README), "exec"), scope)
    assert scope["out"]["rgb"].shape == (256, 3)
    assert torch.isfinite(scope["loss"])
    assert scope["field"].encoding.params.grad is not None


@pytest.mark.cuda
def test_readme_graph_example_replays_new_rays():
    import ngp_warp
    from ngp_warp.outputs.bench import make_rays, scene_grid

    text = README.read_text()
    code = re.findall(r"## Embedding the render op.*?```python\n.*?```.*?```python\n(.*?)```", text, re.S)[0]
    assert "capture_graph" in code
    grid = scene_grid("shell", "cuda")
    rays_o, rays_d = make_rays(1000, "cuda")
    new_o, new_d = make_rays(2000, "cuda")
    new_o, new_d = new_o[1000:], new_d[1000:]
    n = ngp_warp.ray_marching(rays_o, rays_d, grid, validate=False).n_samples * 2
    scope = {"torch": torch, "ngp_warp": ngp_warp, "grid": grid, "rays_o": rays_o, "rays_d": rays_d, "N": n,
             "new_o": new_o, "new_d": new_d, "sigmas": torch.rand(n, device="cuda").requires_grad_(True),
             "rgbs": torch.rand(n, 3, device="cuda").requires_grad_(True),
             "grad_rgb": torch.rand(1000, 3, device="cuda")}
    exec(compile(code, str(README), "exec"), scope)
    assert torch.equal(scope["rays_o"], new_o) and scope["grads"][0].abs().sum() > 0
    eager = scope["step"]()
    for got, want in zip(scope["grads"], eager):
        torch.testing.assert_close(got, want)
