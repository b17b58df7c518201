"""The one error every scene reader raises, and the number checks they share."""

from __future__ import annotations

import math


class DataError(ValueError):
    """A scene on disk is missing or malformed; ``str(e)`` is one line naming the file and the problem."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def short(v) -> str:
    """``repr(v)`` cut to 40 characters, for messages."""
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def number(d: dict, key: str, where: str, positive: bool = False) -> float:
    """``d[key]`` as a finite float (positive when asked), else :class:`DataError` naming ``where``."""
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DataError(f"{where}: {key} must be a number, got {short(v)}")
    if not math.isfinite(v):
        raise DataError(f"{where}: {key} is not finite")
    if positive and v <= 0:
        raise DataError(f"{where}: {key} must be positive, got {v}")
    return float(v)
