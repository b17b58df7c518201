"""``--gpus N``: the command line run as N ranks on this machine, started before torch loads.

The ``ngp-warp`` process that reads ``--gpus N`` imports nothing heavy: it starts N processes of
``python -m ngp_warp.cli`` with the same arguments (``--gpus`` left out) and the environment
torchrun gives its workers (``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``,
``MASTER_PORT`` of a free local port: ``env://``), then waits for them, as torchrun's agent
would, without loading torch itself (seconds of start-up a command saves). Several machines
still go through ``torchrun --nnodes``.

The ranks check the command line themselves: rank 0 alone reports a mistake in the arguments
or too few GPUs (one line); a mistake found later (a scene that cannot be read) each rank
reports. When a rank fails, the others get SIGTERM (rank 0 saves its checkpoint), then SIGKILL
after :data:`GRACE_SECONDS`; so do all of them when this process gets SIGTERM (SIGINT for Ctrl-C).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

GRACE_SECONDS = 30.0  # after SIGTERM, before SIGKILL
RANKED_COMMANDS = ("train", "fit-many")  # the subcommands with --gpus


GPUS_FORMS = ("--gpus", "--gpu", "--gp", "--g")  # argparse takes any prefix that names one option


def _gpus_value(argv: list[str], i: int) -> tuple[str | None, int]:
    """(the value of ``--gpus`` if ``argv[i]`` starts one, else None; how many items it spans)."""
    name, eq, value = argv[i].partition("=")
    if name not in GPUS_FORMS:
        return None, 1
    if eq:
        return value, 1
    return (argv[i + 1], 2) if i + 1 < len(argv) else (None, 1)


def ranks_asked(argv: list[str]) -> int:
    """N of ``--gpus N`` (or ``--gpus=N``, or a prefix such as ``--gpu N``) in a ``train`` or
    ``fit-many`` command line; 1 when absent or not a whole number (the parser reports it)."""
    if not argv or argv[0] not in RANKED_COMMANDS:
        return 1
    asked = 1
    for i in range(len(argv)):
        value, _ = _gpus_value(argv, i)
        if value is not None:
            asked = int(value) if value.isdecimal() and value.isascii() else 1  # the last, as argparse
    return asked


def without_gpus(argv: list[str]) -> list[str]:
    """``argv`` without its ``--gpus N``."""
    rest, i = [], 0
    while i < len(argv):
        value, span = _gpus_value(argv, i)
        if value is None:
            rest.append(argv[i])
        i += span
    return rest


def _free_port() -> int:
    """A port free now; rank 0 binds it seconds later, after loading torch (a race torchrun's
    own free-port choice has too)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(n_ranks: int, argv: list[str], command: list[str] | None = None) -> int:
    """Run ``command`` (default ``python -m ngp_warp.cli``) with ``argv`` as ``n_ranks`` ranks
    and wait for them. The ranks run in sessions of their own (as torchrun starts them): this
    process passes a Ctrl-C or a SIGTERM on to them once. Returns 0 when every rank succeeded,
    2 when every rank that failed by itself exited with 2 (a user mistake, reported by rank 0),
    130 after Ctrl-C, 143 after SIGTERM, else 1."""
    command = command or [sys.executable, "-m", "ngp_warp.cli"]
    shared = {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port()), "WORLD_SIZE": str(n_ranks),
              "LOCAL_WORLD_SIZE": str(n_ranks), "GROUP_RANK": "0",
              "TORCHELASTIC_USE_AGENT_STORE": "False",  # rank 0 holds the store, also under an outer torchrun
              "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}  # as torchrun sets it
    ranks: list[subprocess.Popen] = []
    terminated = []
    previous = signal.signal(signal.SIGTERM, lambda *_: terminated.append(True))
    try:
        for r in range(n_ranks):
            ranks.append(subprocess.Popen([*command, *argv], start_new_session=True,
                                          env={**os.environ, **shared, "RANK": str(r), "LOCAL_RANK": str(r)}))
        failed = _wait(ranks, terminated)
    except KeyboardInterrupt:
        previous_int = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C waits for the ranks' saves
        try:
            _stop(ranks, signal.SIGINT)
        finally:
            signal.signal(signal.SIGINT, previous_int)
        return 130
    except BaseException:
        _stop(ranks, signal.SIGTERM)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
    if terminated:
        return 128 + signal.SIGTERM
    return 0 if not failed else 2 if set(failed) == {2} else 1


def _wait(ranks: list[subprocess.Popen], terminated: list) -> list[int]:
    """Wait for every rank; at the first failure (or a SIGTERM to this process) stop the rest.
    Returns the exit codes of the ranks that failed by themselves."""
    while True:
        codes = [p.poll() for p in ranks]
        failed = [c for c in codes if c not in (None, 0)]
        if None not in codes:
            return failed
        if failed or terminated:
            _stop(ranks, signal.SIGTERM)
            return failed
        time.sleep(0.05)


def _stop(ranks: list[subprocess.Popen], sig: signal.Signals) -> None:
    """Send ``sig`` to the ranks still running, wait :data:`GRACE_SECONDS` for them and kill
    those left."""
    running = [p for p in ranks if p.poll() is None]
    for p in running:
        p.send_signal(sig)
    deadline = time.monotonic() + GRACE_SECONDS
    for p in running:
        try:
            p.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
