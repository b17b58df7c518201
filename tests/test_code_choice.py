"""benchmarks/code_choice.py's candidate codes for a held-out view, on hand-made cameras."""

import torch

from ngp_warp.outputs.evaluate import psnr_whole_and_halves

from benchmark_scripts import load_benchmark

code_choice = load_benchmark("code_choice")


def test_candidate_codes_follow_the_cameras_nearest_the_view():
    gen = torch.Generator().manual_seed(0)
    codes = torch.randn(5, 4, generator=gen)
    centres = torch.tensor([[4.0, 0, 0], [1.0, 0, 0], [0, 3.0, 0], [0, 0, 2.0], [-5.0, 0, 0]])
    view = torch.tensor([0.5, 0.0, 0.0])  # distances 3.5, 0.5, 3.04, 2.06, 5.5: order 1, 3, 2
    nearest, two, three, mean = code_choice.candidate_codes(codes, centres, view)
    assert torch.equal(nearest, codes[1])
    torch.testing.assert_close(two, (codes[1] + codes[3]) / 2)
    d = (centres[[1, 3, 2]] - view).norm(dim=-1)
    w = (1 / d) / (1 / d).sum()
    torch.testing.assert_close(three, (codes[[1, 3, 2]] * w[:, None]).sum(0))
    torch.testing.assert_close(mean, codes.mean(0))


def test_psnr_whole_and_halves_split_the_image_at_half_its_width():
    gt = torch.full((4, 6, 3), 0.5)
    rgb = gt.clone()
    rgb[:, 3:] += 0.1  # the right half off by 0.1: 20 dB there, exact on the left
    whole, left, right = psnr_whole_and_halves(rgb, gt)
    assert abs(right - 20.0) < 1e-4 and left > 60 and abs(whole - 23.0103) < 1e-3
