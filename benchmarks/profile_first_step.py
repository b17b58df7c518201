"""Where a run's first steps' time goes: Warp's module loads, CUDA-graph captures and the rest.

    python benchmarks/profile_first_step.py SCENE [--device cuda] [--steps 200] [--compile-first]
        [--cprofile 30] [--set KEY=VALUE ...]

A training run's clock starts at its first step, and that step does more than train: each
kernel file's compiled Warp module is loaded at its first launch on the device, the field's
CUDA graphs are captured (one per bucket of sample counts, so captures go on for a while), and
torch makes its first CUDA calls. This script times, in one fresh process:

1. the start: importing torch, importing ngp_warp (Warp with it), loading the scene, building
   the Trainer;
2. the first step, phase by phase (as ``profile_train_step.py``), and inside it the seconds in
   Warp's module loads and in graph captures;
3. steps 2 to ``--steps``: their seconds, the loads and captures among them, and the median
   step of the last tenth (the pace the first steps are measured against);
4. the first and second test-view render at full size (the evaluation's first call pays its
   own loads and captures).

Kernels must be compiled on disk beforehand, or the loads include compiling them:
``--compile-first`` runs a 3-step child process first. ``--cprofile N`` runs the first step
under cProfile and prints its N functions of largest cumulative time.
"""

from __future__ import annotations

import time

_T0 = time.perf_counter()
import torch  # noqa: E402  (timed: the start's first part)

_T_TORCH = time.perf_counter()
import argparse  # noqa: E402
import contextlib  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import ngp_warp.ops.graphs as graphs  # noqa: E402
from ngp_warp._warp_private import _probe  # noqa: E402  (any Warp kernel: its module's class)
from ngp_warp.training.config import TrainConfig, apply_overrides, cpu_sizes  # noqa: E402
from ngp_warp.training.trainer import Trainer  # noqa: E402

_T_NGP = time.perf_counter()
from bench_train import scene_or_usage_error  # noqa: E402
from profile_train_step import time_phases  # noqa: E402


class Tally:
    """Seconds and calls of a wrapped function, since the last :meth:`take`."""

    def __init__(self):
        self.seconds, self.calls = 0.0, 0

    def wrap(self, fn, slow: float = 0.0):
        """``fn`` timed; only calls longer than ``slow`` seconds count (a loaded module's
        ``load`` returns at once)."""
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent = time.perf_counter() - start
                if spent > slow:
                    self.seconds += spent
                    self.calls += 1
        return timed

    def take(self) -> tuple[float, int]:
        taken = (self.seconds, self.calls)
        self.seconds, self.calls = 0.0, 0
        return taken


@contextlib.contextmanager
def counting(loads: Tally, captures: Tally):
    """Within: Warp's module loads (calls of a module's ``load`` over 1 ms) counted in ``loads``
    and CUDA-graph captures in ``captures``; the originals back afterwards."""
    module_class = type(_probe.module)
    load, capture = module_class.load, graphs.capture_graph
    module_class.load, graphs.capture_graph = loads.wrap(load, slow=1e-3), captures.wrap(capture)
    try:
        yield
    finally:
        module_class.load, graphs.capture_graph = load, capture


def timed_call(fn, sync) -> float:
    start = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=200, help="steps timed after the first (≥ 10)")
    ap.add_argument("--compile-first", action="store_true", help="compile the kernels in a child process first")
    ap.add_argument("--cprofile", type=int, default=0, metavar="N", help="profile the first step: top N functions")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    if args.steps < 10:
        ap.error(f"--steps must be at least 10, got {args.steps}")
    if args.compile_first:
        child = [sys.executable, __file__, args.scene, "--device", args.device, "--steps", "10",
                 *[arg for setting in args.set for arg in ("--set", setting)]]
        subprocess.run(child, check=True, capture_output=True)
    try:
        base = TrainConfig(steps=10**9)  # the sizes `ngp-warp train` takes on the device; --set wins
        cfg = apply_overrides(cpu_sizes(base) if args.device == "cpu" else base, args.set)
    except ValueError as e:
        ap.error(str(e))

    loads, captures = Tally(), Tally()
    with counting(loads, captures):
        profile_first_steps(ap, args, cfg, loads, captures)


def profile_first_steps(ap, args, cfg: TrainConfig, loads: Tally, captures: Tally) -> None:
    """Print the start, the first step, the steps after it and the first renders (module
    docstring), with the loads and captures of each."""
    start = time.perf_counter()
    scene = scene_or_usage_error(ap, args.scene)
    scene_s = time.perf_counter() - start
    start = time.perf_counter()
    trainer = Trainer(scene, cfg, device=args.device)
    sync = torch.cuda.synchronize if trainer.device.type == "cuda" else (lambda: None)
    sync()
    trainer_s = time.perf_counter() - start
    build_loads = loads.take()
    print(f"start: import torch {_T_TORCH - _T0:.2f} s, ngp_warp {_T_NGP - _T_TORCH:.2f} s, scene "
          f"{scene_s:.2f} s, Trainer {trainer_s:.2f} s (Warp module loads {build_loads[0]:.2f} s in "
          f"{build_loads[1]})")

    spent = time_phases(trainer)
    profiler = cProfile.Profile() if args.cprofile else None
    first = timed_call((lambda: profiler.runcall(trainer.step)) if profiler else trainer.step, sync)
    first_loads, first_captures = loads.take(), captures.take()
    print(f"\nfirst step: {first:.3f} s; Warp module loads {first_loads[0]:.3f} s in {first_loads[1]}, "
          f"graph captures {first_captures[0]:.3f} s in {first_captures[1]}")
    print("| phase (first step) | seconds |\n| --- | ---: |")
    for name, seconds in spent.items():
        print(f"| {name} | {seconds:.3f} |")

    times = [timed_call(trainer.step, sync) for _ in range(args.steps)]
    later_loads, later_captures = loads.take(), captures.take()
    pace = statistics.median(times[-max(1, len(times) // 10):])
    print(f"\nsteps 2-{args.steps + 1}: {sum(times):.3f} s, {1e3 * pace:.2f} ms a step at the end; "
          f"beyond that pace {sum(times) - pace * len(times):.3f} s; Warp module loads "
          f"{later_loads[0]:.3f} s in {later_loads[1]}, graph captures {later_captures[0]:.3f} s in "
          f"{later_captures[1]}; the first step is {first - pace:.3f} s beyond the pace")

    view, camera = scene.test, scene.test.camera(0)
    render = lambda: trainer.render_image(**camera)  # noqa: E731
    renders = [timed_call(render, sync) for _ in range(2)]
    render_loads, render_captures = loads.take(), captures.take()
    print(f"test view {view.width}x{view.height}: first render {renders[0]:.3f} s, second {renders[1]:.3f} s; "
          f"Warp module loads {render_loads[0]:.3f} s in {render_loads[1]}, graph captures "
          f"{render_captures[0]:.3f} s in {render_captures[1]}")
    if profiler:
        print(f"\nthe first step under cProfile, top {args.cprofile} by cumulative time:")
        pstats.Stats(profiler, stream=sys.stdout).sort_stats("cumulative").print_stats(args.cprofile)


if __name__ == "__main__":
    main()
