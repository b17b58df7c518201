"""What a run does before its clock starts: the module a CUDA-graph capture's backward imports."""

import subprocess
import sys
import textwrap

SYMBOLIC_SHAPES = "torch.fx.experimental.symbolic_shapes"


def test_a_graphed_training_field_imports_what_the_captures_backward_would():
    # in a fresh interpreter: the module is not imported by ngp_warp itself, nor for a field
    # without graphs (whose backward does not import it), but is once a graphed TrainingField
    # exists, so the first capture finds it loaded (sympy: seconds where Python compiles it,
    # counted as start-up instead of training)
    code = textwrap.dedent(f"""
        import sys
        import torch
        from ngp_warp.ops.field import FieldConfig, NGPField
        from ngp_warp.training.train_step import TrainingField
        before = "{SYMBOLIC_SHAPES}" in sys.modules
        aabb = torch.tensor([-1.0, -1, -1, 1, 1, 1])
        field = NGPField(aabb, FieldConfig(log2_hashmap_size=12, n_levels=2))
        TrainingField(field, rows=64, graphs=False)
        eager = "{SYMBOLIC_SHAPES}" in sys.modules
        TrainingField(field, rows=64, graphs=True)  # captured at its first call, not here
        print(before, eager, "{SYMBOLIC_SHAPES}" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False", "True"]


def test_a_cpu_run_does_not_import_it(tmp_path):
    # a CPU step's backward (no graphs) never needs the module: the command must not pay for it
    code = textwrap.dedent(f"""
        import sys
        from ngp_warp.cli import main
        from ngp_warp.data.scene import write_demo_scene
        write_demo_scene(sys.argv[1], width=16, height=16, n_train=4, n_test=1, supersample=1)
        code = main(["train", sys.argv[1], "--out", sys.argv[2], "--steps", "2", "--device", "cpu", "--quiet",
                     "--no-video", "--target-samples", "1024"])
        print(code, "{SYMBOLIC_SHAPES}" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "scene"), str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-2:] == ["0", "False"]
