"""LPIPS availability checks and metrics.json entries (nothing is downloaded)."""

import importlib.util
from types import SimpleNamespace

import pytest
import torch

from ngp_warp.outputs import lpips


def fake_install(tmp_path, monkeypatch, packages=("torchmetrics", "torchvision"), head=True, backbone=True):
    """Pretend packages are installed under tmp_path, with or without the weight files."""
    real = importlib.util.find_spec

    def find_spec(name, *args):
        if name in ("torchmetrics", "torchvision"):
            return SimpleNamespace(origin=str(tmp_path / name / "__init__.py")) if name in packages else None
        return real(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    if head:
        (tmp_path / "torchmetrics/functional/image/lpips_models").mkdir(parents=True)
        (tmp_path / "torchmetrics/functional/image/lpips_models/alex.pth").write_bytes(b"x")
    if backbone:
        (tmp_path / "hub/checkpoints").mkdir(parents=True)
        (tmp_path / "hub/checkpoints" / lpips.BACKBONE_FILES["alex"]).write_bytes(b"x")


@pytest.mark.parametrize("setup, reason", [
    ({"packages": ()}, "torchmetrics is not installed"),
    ({"packages": ("torchmetrics",)}, "torchvision is not installed"),
    ({"head": False}, "no LPIPS head alex.pth"),
    ({"backbone": False}, "alex backbone's weights are not in"),
    ({}, None),
])
def test_each_missing_piece_is_named(tmp_path, monkeypatch, setup, reason):
    fake_install(tmp_path, monkeypatch, **setup)
    found = lpips.unavailable_reason("alex")
    assert found == reason if reason is None else reason in found


def test_not_computed_without_weights(tmp_path, monkeypatch):
    fake_install(tmp_path, monkeypatch, backbone=False)
    value, note = lpips.lpips_or_reason(torch.rand(8, 8, 3), torch.rand(8, 8, 3))
    assert value is None and note.startswith("not computed: the alex backbone")
    assert lpips.lpips_summary([value, value], note) == {"lpips": None, "lpips_note": note}
    with pytest.raises(ValueError, match="net must be one of"):
        lpips.unavailable_reason("resnet")


def test_computed_through_the_metric(monkeypatch):
    calls = []

    class FakeMetric:  # stands in for torchmetrics' module: mean |a - b| of [1, 3, H, W] inputs in [0, 1]
        def __call__(self, a, b):
            calls.append((a.shape, float(a.min()), float(a.max())))
            return (a - b).abs().mean()

        def reset(self):
            pass

    monkeypatch.setattr(lpips, "unavailable_reason", lambda net: None)
    monkeypatch.setattr(lpips, "_metric", lambda net, device: FakeMetric())
    pred, target = torch.rand(6, 5, 3) * 1.4 - 0.2, torch.rand(6, 5, 3)
    value, note = lpips.lpips_or_reason(pred, target)
    assert calls[0][0] == (1, 3, 6, 5) and calls[0][1] >= 0 and calls[0][2] <= 1
    assert value == pytest.approx(float((pred.clamp(0, 1) - target).abs().mean()))
    assert lpips.lpips_summary([value, 0.5], note) == {"lpips": pytest.approx((value + 0.5) / 2), "lpips_note": note}
    with pytest.raises(ValueError, match="differ"):
        lpips.lpips_or_reason(pred, target[:5])


def test_this_machine_says_why(monkeypatch):
    value, note = lpips.lpips_or_reason(torch.rand(4, 4, 3), torch.rand(4, 4, 3))
    if lpips.unavailable_reason() is not None:
        assert value is None and note == f"not computed: {lpips.unavailable_reason()}"
    else:
        assert 0 <= value < 1
