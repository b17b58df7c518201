"""A dependency-free progress bar for long work (training, rendering)."""

from __future__ import annotations

import sys
import time


class Progress:
    """Prints ``label [####....] 42/100 12.3s  key=value ...`` to stderr.

    On a terminal the line redraws in place (at most 10 times a second); elsewhere (CI, logs)
    a line is printed every ``log_every`` seconds. ``total`` may be a step count or ``None``
    with ``seconds`` as the budget.
    """

    def __init__(self, label: str, total: int | None = None, seconds: float | None = None,
                 enabled: bool = True, log_every: float = 10.0, stream=None):
        self.label, self.total, self.seconds = label, total, seconds
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.log_every = log_every
        self.start = time.perf_counter()
        self._last = -1e9
        self._done = 0
        self._fields = ""

    def _fraction(self, done: int) -> float:
        fracs = []
        if self.total:
            fracs.append(done / self.total)
        if self.seconds:
            fracs.append((time.perf_counter() - self.start) / self.seconds)
        return min(1.0, max(fracs)) if fracs else 0.0

    def update(self, done: int, **fields) -> None:
        """Record progress ``done`` (steps or items) and the values to show."""
        self._done = done
        if fields:
            self._fields = "  ".join(f"{k}={v}" for k, v in fields.items())
        now = time.perf_counter()
        if not self.enabled or now - self._last < (0.1 if self.tty else self.log_every):
            return
        self._last = now
        self._draw(now)

    def _draw(self, now: float) -> None:
        frac = self._fraction(self._done)
        bar = "#" * int(frac * 24) + "." * (24 - int(frac * 24))
        count = f"{self._done}/{self.total}" if self.total else f"{self._done}"
        line = f"{self.label} [{bar}] {count} {now - self.start:6.1f}s  {self._fields}"
        if self.tty:
            self.stream.write("\r" + line[:200] + "\x1b[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        """Draw the final state and end the line."""
        if not self.enabled:
            return
        self._draw(time.perf_counter())
        if self.tty:
            self.stream.write("\n")
        self.stream.flush()
