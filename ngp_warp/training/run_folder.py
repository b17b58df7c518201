"""A training run's output folder: one run's files only, whatever interrupts it.

A run writes ``checkpoint.pt``, ``training_curve.csv``, ``metrics.json``, ``renders/``,
``depth/``, the orbit video and ``normalisation.json`` into its folder (:data:`RUN_OUTPUTS`).
A new run into a folder that holds another run's outputs is refused unless it resumes that run
or is told to overwrite it; an overwriting run deletes the old outputs just before its own first
write (:meth:`RunFolder.claim`), so that until then the old run stays whole, and afterwards no
file of it is left beside the new one. SIGTERM (sent by ``timeout``, systemd and Slurm)
interrupts the run as Ctrl-C does (:func:`sigterm_as_interrupt`), so the same handler saves its
checkpoint.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import signal
import threading
from pathlib import Path

from ngp_warp.atomic import remove_stale_partials

CHECKPOINT = "checkpoint.pt"
TRAINING_CURVE = "training_curve.csv"
REFINED_TRANSFORMS = "transforms_refined.json"  # with camera_refinement (ngp_warp.training.refined_transforms)
RUN_OUTPUTS = (CHECKPOINT, TRAINING_CURVE, "metrics.json", "renders", "depth", "orbit.mp4", "orbit.gif",
               "normalisation.json", REFINED_TRANSFORMS)
OUTPUT_FOLDERS = ("renders", "depth")
log = logging.getLogger("ngp_warp.training.run_folder")
SIGTERM_EXIT = 128 + signal.SIGTERM  # 143, as a shell reports a process ended by SIGTERM


class RunFolderError(ValueError):
    """An output folder that a run may not write into; the message is one line."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's KeyboardInterrupt."""


def check_output_names(folder: Path) -> None:
    """RunFolderError when one of the run's outputs in ``folder`` exists as the wrong kind
    (``renders`` a file, ``metrics.json`` a folder, ...), before any long work starts."""
    for name in RUN_OUTPUTS:
        entry = Path(folder) / name
        want_dir = name in OUTPUT_FOLDERS
        if entry.exists() and entry.is_dir() != want_dir:
            kind = "a file" if want_dir else "a folder"
            raise RunFolderError(f"{entry} is {kind}; move it away (the run writes its "
                                 f"{'folder' if want_dir else 'file'} {name} there)")


class RunFolder:
    """The output folder ``path`` of one training run.

    Args:
        path: the folder (created by :meth:`claim`, not here).
        resume: the run continues the one saved in the folder.
        overwrite: the run replaces the one in the folder (its outputs go at :meth:`claim`).
        flags: how the command spells (resume, overwrite), for messages; None: not offered.

    Raises:
        RunFolderError: ``path`` is a file, an output has the wrong kind, or the folder holds
            another run and neither ``resume`` nor ``overwrite`` is set.
    """

    def __init__(self, path: Path, resume: bool = False, overwrite: bool = False,
                 flags: tuple[str | None, str] = ("--resume", "--overwrite")):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise RunFolderError(f"{self.path} is a file, not an output folder")
        check_output_names(self.path)
        self.previous = [name for name in RUN_OUTPUTS if (self.path / name).exists()]
        if self.previous and not (resume or overwrite):
            ways = " or ".join(f"{verb} it with {flag}" for verb, flag in zip(("continue", "replace"), flags) if flag)
            raise RunFolderError(f"{self.path} holds another run ({', '.join(self.previous)}); {ways}, "
                                 f"or choose another --out")
        self._stale = [] if resume else list(self.previous)
        self.claimed = False

    def claim(self) -> None:
        """Before the run's first write: create the folder, delete the temporary files a killed
        run left there and, when overwriting, the previous run's outputs, with a warning naming
        the other files kept there (videos, meshes: perhaps made from the previous run)."""
        if self.claimed:
            return
        self.path.mkdir(parents=True, exist_ok=True)
        remove_stale_partials(self.path)
        for name in self._stale:
            entry = self.path / name
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink(missing_ok=True)
        kept = sorted(p.name for p in self.path.iterdir() if p.is_file()) if self._stale else []
        if kept:
            log.warning(f"ngp-warp: {self.path}: replaced the previous run's outputs; other files there are kept, "
                        f"perhaps made from it: {', '.join(kept[:4])}{' ...' if len(kept) > 4 else ''}")
        self.claimed = True


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block, SIGTERM raises :class:`Terminated` (a KeyboardInterrupt) in the main
    thread, so that ``except KeyboardInterrupt`` cleanup runs for it too; the previous handler
    comes back after. Elsewhere than the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_terminated(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
