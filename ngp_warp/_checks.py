"""Range checks shared by the configuration dataclasses."""

from numbers import Integral, Real


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
