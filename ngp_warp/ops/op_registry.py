"""Modules a torch.library op refers to by number: an op's schema takes tensors and scalars, so
the compiled encoding and march name their :class:`~ngp_warp.HashGridEncoding` or
:class:`~ngp_warp.OccupancyGrid` by ``id``. Each registers itself when built or unpickled; the
registry holds weak references only."""

from __future__ import annotations

import weakref

_OBJECTS: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def register(obj) -> None:
    """Make ``obj`` known to the ops under ``id(obj)``."""
    _OBJECTS[id(obj)] = obj


def lookup(key: int):
    """The object registered under ``key``."""
    return _OBJECTS[key]
