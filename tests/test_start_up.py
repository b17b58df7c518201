"""What a run does before its clock starts: the modules torch's first backward imports."""

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

