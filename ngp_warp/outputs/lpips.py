"""LPIPS (Zhang et al. 2018) for metrics.json, through torchmetrics, only from files already on
this machine: nothing is ever downloaded.

It needs the optional packages torchmetrics and torchvision, torchmetrics' LPIPS head
(``lpips_models/<net>.pth``, shipped inside torchmetrics) and the ImageNet backbone's weights in
torch's hub cache (``<torch.hub.get_dir()>/checkpoints/``). When any is missing, metrics.json
holds ``"lpips": null`` and a ``"lpips_note"`` saying which.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

LPIPS_NET = "alex"  # the backbone instant-ngp's and nerfstudio's papers report LPIPS with
BACKBONE_FILES = {  # torchvision's ImageNet weights, as torch.hub caches them
    "alex": "alexnet-owt-7be5be79.pth",
    "vgg": "vgg16-397923af.pth",
    "squeeze": "squeezenet1_1-b8a52dc0.pth",
}
_metrics: dict = {}


def unavailable_reason(net: str = LPIPS_NET) -> str | None:
    """None when LPIPS with backbone ``net`` can run from local files, else why not (one line)."""
    if net not in BACKBONE_FILES:
        raise ValueError(f"net must be one of {', '.join(BACKBONE_FILES)}, got {net!r}")
    for package in ("torchmetrics", "torchvision"):
        if importlib.util.find_spec(package) is None:
            return f"{package} is not installed"
    head = Path(importlib.util.find_spec("torchmetrics").origin).parent / "functional/image/lpips_models" / f"{net}.pth"
    if not head.is_file():
        return f"torchmetrics has no LPIPS head {head.name}"
    backbone = Path(torch.hub.get_dir()) / "checkpoints" / BACKBONE_FILES[net]
    if not backbone.is_file():
        return f"the {net} backbone's weights are not in {backbone.parent} ({backbone.name})"
    return None


def _metric(net: str, device: torch.device):
    key = (net, str(device))
    if key not in _metrics:
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        _metrics[key] = LearnedPerceptualImagePatchSimilarity(net_type=net, normalize=True).to(device).eval()
    return _metrics[key]


def lpips_or_reason(pred: torch.Tensor, target: torch.Tensor, net: str = LPIPS_NET) -> tuple[float | None, str]:
    """LPIPS of one image pair, or None and why it was not computed.

    Args:
        pred, target: [H, W, 3] float images in [0, 1], same shape and device.
        net: backbone, ``alex``, ``vgg`` or ``squeeze``.

    Returns:
        (distance, note): the distance (lower is closer) and what computed it, or (None,
        "not computed: ...").
    """
    return lpips_scorer(net)(pred, target)


def lpips_scorer(net: str = LPIPS_NET):
    """:func:`lpips_or_reason` as a function of the image pair, what this machine has looked up
    once (an evaluation scores hundreds of views; the lookup searches the import path)."""
    reason = unavailable_reason(net)

    @torch.no_grad()
    def score(pred: torch.Tensor, target: torch.Tensor) -> tuple[float | None, str]:
        for name, t in (("pred", pred), ("target", target)):
            if not isinstance(t, torch.Tensor) or t.dim() != 3 or t.shape[-1] != 3 or not t.is_floating_point():
                raise ValueError(f"{name} must be a float [H, W, 3] tensor")
        if pred.shape != target.shape or pred.device != target.device:
            raise ValueError(f"pred and target differ: {list(pred.shape)} on {pred.device}, "
                             f"{list(target.shape)} on {target.device}")
        if reason is not None:
            return None, f"not computed: {reason}"
        metric = _metric(net, pred.device)
        images = [t.float().clamp(0, 1).permute(2, 0, 1)[None] for t in (pred, target)]
        value = float(metric(*images))
        metric.reset()
        return value, f"torchmetrics LPIPS, {net} backbone, images in [0, 1]"

    return score


def lpips_summary(values: list[float | None], note: str) -> dict:
    """metrics.json's entries from per-image values and the last note: ``{"lpips": mean or
    None, "lpips_note": note}`` (None when any image has none)."""
    if not values or any(v is None for v in values):
        return {"lpips": None, "lpips_note": note if note.startswith("not computed") else "not computed: no images"}
    return {"lpips": sum(values) / len(values), "lpips_note": note}
