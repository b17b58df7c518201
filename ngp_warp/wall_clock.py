"""Where a command's wall-clock time goes: start-up from the moment ``ngp_warp`` is first
imported (torch, Warp and the kernels' modules included), then each phase the command names."""

from __future__ import annotations

import time

IMPORTED_AT = time.perf_counter()  # ngp_warp/__init__.py imports this module before anything else
_commands_started = 0


def command_started() -> float:
    """When the command now starting began (``time.perf_counter``): the import of ngp_warp for a
    process's first command, now for a later one in the same process (tests, scripts)."""
    global _commands_started
    _commands_started += 1
    return IMPORTED_AT if _commands_started == 1 else time.perf_counter()


class WallClock:
    """Seconds per phase, in the order first marked: ``mark(phase)`` gives ``phase`` the time
    since the previous mark (the first mark since the import of ``ngp_warp``)."""

    def __init__(self, started: float):
        self.seconds: dict[str, float] = {}
        self._last = started

    def mark(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now

    def shift(self, seconds: float, source: str, target: str) -> None:
        """Count ``seconds`` of phase ``source`` under ``target`` instead (work of one kind done
        within another's mark, e.g. training during the start-up)."""
        if seconds > 0:
            self.seconds[source] = self.seconds.get(source, 0.0) - seconds
            self.seconds[target] = self.seconds.get(target, 0.0) + seconds

    def summary(self) -> str:
        """One line: ``wall clock 21.4 s: start-up 4.1 s, training 15.2 s, ...``."""
        parts = ", ".join(f"{phase.replace('_', '-')} {s:.1f} s" for phase, s in self.seconds.items())
        return f"wall clock {sum(self.seconds.values()):.1f} s: {parts}"
