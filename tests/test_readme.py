"""The README's embedding example runs as written (a few iterations, small batches)."""

import re
from pathlib import Path

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
