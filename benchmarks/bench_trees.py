"""Source trees of ngp-warp running the same command by turns, so that a change's effect on a
run's wall clock, steps and PSNR is read against the host's drift between runs.

    python benchmarks/bench_trees.py --trees c7e2fb2,HEAD [--rounds 4] [--out bench_trees] -- \
        train ../shared/data/lego_half --seconds 15 --device cuda --no-video --quiet

Each tree is a commit's ``ngp_warp/`` and ``kernels/`` (``git archive``), unpacked under
``--out``, or a folder holding such a tree, and put first on ``PYTHONPATH``; every run is
``python -P -m ngp_warp.cli COMMAND --out RUN --overwrite``, so that no tree comes from the
installed package and the trees load alike (where each tree's package and kernels import from
is checked before the first run). The order turns
over every round (A B, B A, A B, ...), so each tree runs first as often as the others: a run can
leave work behind for the next (its files' writeback) and a host drifts. Prints a row per run
(the command's own seconds, metrics.json's wall clock by phase, steps, PSNR) as it ends, then
each tree's means. Kernels compile in the first run of a tree whose kernels are new: warm them
first (a short run of each tree) where that matters.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("start_up", "training", "checkpoint", "evaluation", "video")  # metrics.json's wall_seconds


def _git(*args: str) -> bytes:
    done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True)
    if done.returncode != 0:
        raise SystemExit(f"git {' '.join(args)}: {done.stderr.decode(errors='replace').strip()}")
    return done.stdout


def _is_tree(folder: Path) -> bool:
    return all((folder / "ngp_warp" / part / "__init__.py").is_file() for part in ("", "kernels"))


def unpack(tree: str, out: Path) -> tuple[str, Path]:
    """The commit ``tree`` names (its short hash) and the folder holding its ``ngp_warp`` package
    (``kernels/`` moved to ``ngp_warp/kernels/``, as the install maps it); or, where ``tree`` is
    a folder that holds such a package, kernels included, already (a tree unpacked elsewhere, for
    a machine without the repository's history), its name and that folder."""
    if _is_tree(Path(tree)):
        return Path(tree).resolve().name, Path(tree).resolve()
    commit = _git("rev-parse", "--verify", f"{tree}^{{commit}}").decode().strip()
    folder = out / f"tree-{commit[:10]}"
    if not _is_tree(folder):
        partial = out / f".tree-{commit[:10]}.partial"  # renamed once whole: an interrupted unpack is redone
        shutil.rmtree(partial, ignore_errors=True)
        with tarfile.open(fileobj=io.BytesIO(_git("archive", "--format=tar", commit, "ngp_warp", "kernels"))) as tar:
            members = tar.getmembers()
            for member in members:
                if member.name == "kernels" or member.name.startswith("kernels/"):
                    member.name = f"ngp_warp/{member.name}"
            try:
                tar.extractall(partial, members=members, filter="data")
            except TypeError:  # a Python before 3.11.4, without extraction filters
                tar.extractall(partial, members=members)
        shutil.rmtree(folder, ignore_errors=True)
        partial.rename(folder)
    return commit[:10], folder


def _environment(folder: Path) -> dict:
    paths = [str(folder), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


WHERE = "import ngp_warp, ngp_warp.kernels; print(ngp_warp.__file__); print(ngp_warp.kernels.__file__)"


def check_import(folder: Path) -> None:
    """SystemExit unless a run started as :func:`run_once` starts it imports ngp_warp, and its
    kernels, from ``folder`` (an installed package's import hook could supply either)."""
    done = subprocess.run([sys.executable, "-P", "-c", WHERE], env=_environment(folder), capture_output=True,
                          text=True)
    imported = [Path(line).resolve() for line in done.stdout.split()] if done.returncode == 0 else []
    if len(imported) != 2 or any(folder.resolve() not in path.parents for path in imported):
        shown = ", ".join(map(str, imported)) or done.stderr.strip()[-300:]
        raise SystemExit(f"{folder}: a run would import ngp_warp from {shown} instead")


def run_once(folder: Path, command: list[str], run: Path) -> dict:
    """One run of ``command`` with the tree in ``folder`` (started in the current folder, which
    ``-P`` keeps off the import path): its seconds, steps, PSNR and phases."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-P", "-m", "ngp_warp.cli", *command, "--out", str(run), "--overwrite"],
                          env=_environment(folder), capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{folder.name}: {' '.join(command)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    metrics = json.loads((run / "metrics.json").read_text())
    return {"command": seconds, "steps": metrics["steps"], "psnr": metrics["psnr"],
            **{phase: metrics["wall_seconds"].get(phase) for phase in PHASES}}


def order(trees: list, rounds: int) -> list:
    """The runs' trees: every round all of them, each round in the reverse order of the last."""
    return [tree for r in range(rounds) for tree in (trees if r % 2 == 0 else trees[::-1])]


def _cell(value) -> str:
    return "–" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trees", required=True,
                        help="comma-separated commits (HEAD, a hash, a branch) or folders holding an ngp_warp package")
    parser.add_argument("--rounds", type=int, default=4, help="runs of each tree")
    parser.add_argument("--out", type=Path, default=Path("bench_trees"))
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the ngp-warp command, without --out")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given (after --)")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    trees = list(dict.fromkeys(unpack(tree, out) for tree in args.trees.split(",")))
    names = [name for name, _ in trees]
    trees = [(name if names.count(name) == 1 else f"{name}-{k + 1}", folder) for k, (name, folder) in enumerate(trees)]
    for _, folder in trees:
        check_import(folder)
    columns = ("tree", "run", "command", *PHASES, "steps", "psnr")
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns), flush=True)
    rows: dict[str, list[dict]] = {}
    for k, (name, folder) in enumerate(order(trees, args.rounds)):
        row = run_once(folder, command, out / f"run-{name}")
        rows.setdefault(name, []).append(row)
        print("| " + " | ".join([name, str(k + 1), *(_cell(row[c]) for c in columns[2:])]) + " |", flush=True)
    print("\nmeans:\n| tree | runs | " + " | ".join(columns[2:]) + " |\n|" + "---|" * (len(columns)), flush=True)
    means = {}
    for name, runs in rows.items():
        means[name] = {c: None if any(r[c] is None for r in runs) else sum(r[c] for r in runs) / len(runs)
                       for c in columns[2:]}
        print(f"| {name} | {len(runs)} | " + " | ".join(_cell(means[name][c]) for c in columns[2:]) + " |", flush=True)
    return {"runs": rows, "means": means}


if __name__ == "__main__":
    main()
