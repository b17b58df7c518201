"""Progress output: tqdm's bar on a terminal, plain lines in a log."""

import io

from ngp_warp import progress as P


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_plain_lines_and_a_terminal_the_bar(monkeypatch):
    monkeypatch.setattr(P, "LOG_EVERY", 0.0)  # a line at every update
    log = io.StringIO()
    with P.progress(total=5, desc="train", unit="step", file=log) as bar:
        for _ in range(5):
            bar.update(1)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and len(lines) >= 5
    assert lines[-1].startswith("train: 100%") and "5/5" in lines[-1]
    terminal = Terminal()
    with P.progress(total=5, desc="train", file=terminal) as bar:
        bar.update(5)
    assert "\r" in terminal.getvalue()  # tqdm's own refresh in place
