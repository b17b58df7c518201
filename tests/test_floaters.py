"""benchmarks/floaters.py: which training images hold a point, and how clear their view of it is."""

import contextlib
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmark_scripts import load_benchmark

floaters = load_benchmark("floaters")

WIDTH, HEIGHT, FOCAL, NEAR = 40, 30, 20.0, 0.5


class WallAt:
    """A model whose every ray meets one sample at distance ``wall`` from its origin, of weight
    ``weight`` (so the transmittance past the wall is 1 − weight)."""

    def __init__(self, wall: float, weight: float):
        self.wall, self.weight, self.march = wall, weight, SimpleNamespace(near=NEAR)

    def precision(self):
        return contextlib.nullcontext()

    def render(self, origins, directions, field, background, return_samples):
        n = origins.shape[0]
        return {"ray_offsets": torch.arange(n + 1), "ray_indices": torch.arange(n),
                "weights": torch.full((n,), self.weight), "t_starts": torch.full((n,), self.wall - 0.01),
                "t_ends": torch.full((n,), self.wall + 0.01)}


def trainer_with(model) -> SimpleNamespace:
    """Two OpenGL cameras at x = 0 and x = 1 looking down −z, and ``model``."""
    c2w = torch.zeros(2, 3, 4)
    c2w[:, :, :3] = torch.eye(3)
    c2w[1, 0, 3] = 1.0
    train = SimpleNamespace(c2w=c2w, intrinsics=torch.tensor([[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]] * 2),
                            width=WIDTH, height=HEIGHT, names=["a/0000.jpg", "a/0001.jpg"])
    return SimpleNamespace(scene=SimpleNamespace(train=train), model=model, device="cpu", field=None,
                           weights=SimpleNamespace(averaged_in_field=contextlib.nullcontext))


def test_project_holds_points_in_the_image_past_the_near():
    trainer = trainer_with(WallAt(3.0, 0.5))
    points = np.array([[0.0, 0.0, -2.0],     # on camera 0's axis; 10 px left of camera 1's centre
                       [0.0, 0.0, -0.3],     # within the near of camera 0
                       [0.0, 0.0, 2.0],      # behind both
                       [-3.0, 0.0, -2.0]])   # beside camera 0's image (u = 20 − 30 < 0)
    u, v, distance, held = floaters.project(trainer, points)
    assert u[0].tolist() == pytest.approx([20.0, 10.0]) and v[0].tolist() == pytest.approx([15.0, 15.0])
    assert distance[0].tolist() == pytest.approx([2.0, math.sqrt(5.0)])
    assert held.tolist() == [[True, True], [False, False], [False, False], [False, False]]


def test_training_transmittance_is_what_lies_in_front_of_the_point():
    trainer = trainer_with(WallAt(3.0, 0.75))  # a wall 3 in front of every camera, 3/4 opaque
    points = np.array([[0.0, 0.0, -2.0], [0.5, 0.0, -5.0], [0.0, 0.0, -0.3]])
    held = floaters.project(trainer, points)[3]
    clear = floaters.training_transmittance(trainer, points, held)
    assert held[2].tolist() == [False, False] and clear[2].tolist() == [0.0, 0.0]  # held by none: 0
    assert clear[0].tolist() == pytest.approx([1.0, 1.0])    # nearer than the wall from both cameras
    assert clear[1].tolist() == pytest.approx([0.25, 0.25])  # behind it


def test_rows_and_holders_print_one_line_each(capsys):
    trainer = trainer_with(WallAt(3.0, 0.75))
    points = np.array([[0.0, 0.0, -2.0], [0.5, 0.0, -5.0], [0.2, 0.1, -4.0]])
    floaters.print_row(trainer, "label", points, np.array([2.0, 5.0, 4.0]), np.array([0.4, 1.0, 0.8]), 0.25)
    floaters.print_holders(trainer, points)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| label | 0.250 |") and lines[0].count("|") == 10
    assert [line.split(" | ")[:2] for line in lines[3:]] == [["| 0000.jpg", "3"], ["| 0001.jpg", "3"]]
