"""Progress bars a person can read wherever the output goes: tqdm's bar on a terminal; in a
log file or a pipe, a plain line every :data:`LOG_EVERY` seconds (tqdm's carriage-return
refreshes would otherwise pile up into one line hundreds of updates long)."""

from __future__ import annotations

import sys

from tqdm import tqdm

LOG_EVERY = 10.0  # seconds between plain lines when the output is not a terminal


class _Lines:
    """A stream for tqdm that writes each refresh as a line of its own."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").rstrip()
        if text:
            self.stream.write(text + "\n")

    def flush(self) -> None:
        self.stream.flush()


def progress(iterable=None, **kwargs) -> tqdm:
    """``tqdm(iterable, **kwargs)`` on a terminal (``file``, default stderr); on anything else,
    plain lines at most every :data:`LOG_EVERY` seconds, and the last state when it closes."""
    stream = kwargs.pop("file", None) or sys.stderr
    isatty = getattr(stream, "isatty", None)
    if not (isatty and isatty()):
        kwargs.update(file=_Lines(stream), mininterval=LOG_EVERY, maxinterval=LOG_EVERY, ascii=True, ncols=80)
    else:
        kwargs["file"] = stream
    return tqdm(iterable, **kwargs)
