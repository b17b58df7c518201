"""Range checks shared by the configuration dataclasses, and the boxes' value check."""

import math
from numbers import Integral, Real

import torch


def check_aabb_values(aabb: torch.Tensor) -> None:
    """ValueError unless the [6] box ``aabb`` (min xyz, max xyz) is finite with max > min on
    every axis. It reads the values: one host synchronisation for a GPU tensor."""
    if not bool(torch.isfinite(aabb).all() and (aabb[3:] > aabb[:3]).all()):
        raise ValueError(f"aabb must be finite with max > min on every axis, got {aabb.tolist()}")


def check_numbers(config, counts=(), positive=(), non_negative=(), optional=()) -> None:
    """ValueError for the first of ``config``'s settings that is not: an int ≥ 1 (``counts``), a
    number > 0 (``positive``), a number ≥ 0 (``non_negative``). Only the settings named in
    ``optional`` may be None."""
    for name in (*counts, *positive, *non_negative):
        value = getattr(config, name)
        if value is None and name in optional:
            continue
        if name in counts:
            if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
                raise ValueError(f"{name} must be an integer ≥ 1, got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, Real) or not (value > 0 if name in positive else value >= 0):
            raise ValueError(f"{name} must be a number {'>' if name in positive else '≥'} 0, got {value!r}")


def check_distances(**values) -> None:
    """ValueError for the first keyword argument that is not a finite number ≥ 0 (a bool is not
    a number here)."""
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, Real) or not 0 <= value < math.inf:
            raise ValueError(f"{name} must be a finite number ≥ 0, got {value!r}")
