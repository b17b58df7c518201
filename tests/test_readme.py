"""The README's and docs/'s code blocks run as written (a few iterations, small batches), and
the docs build without warnings."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
EMBEDDING = ROOT / "docs" / "embedding.md"


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.S)


def block_with(path: Path, word: str) -> str:
    (code,) = [b for b in python_blocks(path) if word in b]
    return code


@pytest.mark.parametrize("page", [README, EMBEDDING])
def test_the_render_example_trains(page):
    code = block_with(page, "render_rays").replace("range(1000)", "range(4)")
    target_color = torch.tensor([0.2, 0.6, 0.9])

    def next_batch(n=256):
        o = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1) * 4.0
        d = torch.nn.functional.normalize(torch.randn(n, 3) * 0.2 - o, dim=-1)
        device = scope["device"]  # the example picks its device before asking for batches
        return o.to(device), d.to(device), target_color.expand(n, 3).to(device)

    scope = {"next_batch": next_batch}
    exec(compile(code, str(page), "exec"), scope)
    assert scope["out"]["rgb"].shape == (256, 3)
    assert torch.isfinite(scope["loss"])
    assert scope["field"].encoding.params.grad is not None


def test_the_compile_example_traces_the_composite():
    import ngp_warp

    g = torch.Generator().manual_seed(0)
    n_rays, s = 4, 30
    scope = {"torch": torch, "ngp_warp": ngp_warp, "n_rays": n_rays,
             "ray_indices": torch.sort(torch.randint(0, n_rays, (s,), generator=g)).values,
             "t_starts": torch.rand(s, generator=g)}
    scope["t_ends"] = scope["t_starts"] + 0.1
    torch._dynamo.reset()
    exec(compile(block_with(EMBEDDING, "torch.compile"), str(EMBEDDING), "exec"), scope)
    sigmas = torch.rand(s, generator=g).requires_grad_(True)
    value = scope["loss_fn"](sigmas, torch.rand(s, 3, generator=g))
    assert torch.autograd.grad(value, sigmas)[0].abs().sum() > 0


def test_the_docs_build_without_warnings(tmp_path):
    pytest.importorskip("mkdocs")  # the test extra installs it
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(tmp_path / "site")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "site" / "embedding" / "index.html").is_file()


@pytest.mark.cuda
def test_the_graph_example_replays_new_rays():
    import ngp_warp
    from ngp_warp.outputs.bench import make_rays, scene_grid

    code = block_with(EMBEDDING, "capture_graph")
    grid = scene_grid("shell", "cuda")
    rays_o, rays_d = make_rays(1000, "cuda")
    new_o, new_d = make_rays(2000, "cuda")
    new_o, new_d = new_o[1000:], new_d[1000:]
    n = ngp_warp.ray_marching(rays_o, rays_d, grid, validate=False).n_samples * 2
    scope = {"torch": torch, "ngp_warp": ngp_warp, "grid": grid, "rays_o": rays_o, "rays_d": rays_d, "N": n,
             "new_o": new_o, "new_d": new_d, "sigmas": torch.rand(n, device="cuda").requires_grad_(True),
             "rgbs": torch.rand(n, 3, device="cuda").requires_grad_(True),
             "grad_rgb": torch.rand(1000, 3, device="cuda")}
    exec(compile(code, str(EMBEDDING), "exec"), scope)
    assert torch.equal(scope["rays_o"], new_o) and scope["grads"][0].abs().sum() > 0
    eager = scope["step"]()
    for got, want in zip(scope["grads"], eager):
        torch.testing.assert_close(got, want)
