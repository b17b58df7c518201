"""What a run does before its clock starts: the module a CUDA-graph capture's backward imports."""

import subprocess
import sys
import textwrap

import pytest

from ngp_warp.training.config import TrainConfig
from ngp_warp.training.train_step import uses_graphs

SYMBOLIC_SHAPES = "torch.fx.experimental.symbolic_shapes"


AT_START = f"""
    import sys
    import torch
    print("{SYMBOLIC_SHAPES}" in sys.modules)
"""


def _fresh_python(code: str, *args: str) -> list[str]:
    """The last line of what ``code`` prints in a new interpreter (after importing sys and torch),
    split; skips the test where torch itself loads the module at import."""
    code = textwrap.dedent(AT_START) + textwrap.dedent(code)
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    if lines[0] == "True":
        pytest.skip(f"this torch imports {SYMBOLIC_SHAPES} at its own import")
    return lines[-1].split()


def test_a_graphed_training_field_imports_what_the_captures_backward_would():
    # not imported by ngp_warp itself, nor for a field without graphs (whose backward does not
    # import it), but once a graphed TrainingField exists, so the first capture finds it loaded
    # (sympy: seconds where Python compiles it, counted as start-up instead of training)
    seen = _fresh_python(f"""
        from ngp_warp.ops.field import FieldConfig, NGPField
        from ngp_warp.training.train_step import TrainingField
        field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(log2_hashmap_size=12, n_levels=2))
        TrainingField(field, rows=64, graphs=False)
        eager = "{SYMBOLIC_SHAPES}" in sys.modules
        TrainingField(field, rows=64, graphs=True)  # captured at its first call, not here
        print(eager, "{SYMBOLIC_SHAPES}" in sys.modules)
    """)
    assert seen == ["False", "True"]


def test_the_command_line_imports_it_alongside_the_scene_only_for_graphs():
    seen = _fresh_python(f"""
        from ngp_warp.training.train_step import capture_imports_alongside
        with capture_imports_alongside(False):
            pass
        unwanted = "{SYMBOLIC_SHAPES}" in sys.modules
        with capture_imports_alongside(True):
            pass  # joined at the block's end
        print(unwanted, "{SYMBOLIC_SHAPES}" in sys.modules)
    """)
    assert seen == ["False", "True"]


def test_graphs_are_cuda_training_with_pruning():
    config = TrainConfig()
    assert uses_graphs(config, "cuda") and not uses_graphs(config, "cpu")
    assert not uses_graphs(TrainConfig(cuda_graph=False), "cuda")
    assert not uses_graphs(TrainConfig(prune=False), "cuda")


def test_a_cpu_run_does_not_import_it(tmp_path):
    # a CPU step's backward (no graphs) never needs the module: the command must not pay for it
    seen = _fresh_python(f"""
        from ngp_warp.cli import main
        from ngp_warp.data.scene import write_demo_scene
        write_demo_scene(sys.argv[1], width=16, height=16, n_train=4, n_test=1, supersample=1)
        code = main(["train", sys.argv[1], "--out", sys.argv[2], "--steps", "2", "--device", "cpu", "--quiet",
                     "--no-video", "--target-samples", "1024"])
        print(code, "{SYMBOLIC_SHAPES}" in sys.modules)
    """, str(tmp_path / "scene"), str(tmp_path / "run"))
    assert seen == ["0", "False"]


@pytest.mark.cuda
def test_the_first_capture_imports_no_sympy():
    # what the pre-import is for: the first graphed forward and backward load no such module
    seen = _fresh_python("""
        from ngp_warp.ops.field import FieldConfig, NGPField
        from ngp_warp.training.train_step import TrainingField
        torch.manual_seed(0)
        field = NGPField(torch.tensor([-1.0, -1, -1, 1, 1, 1]), FieldConfig(log2_hashmap_size=12, n_levels=2)).cuda()
        training_field = TrainingField(field, rows=256, graphs=True)
        loaded = set(sys.modules)
        positions = torch.rand(256, 3, device="cuda") * 2 - 1
        directions = torch.nn.functional.normalize(torch.randn(256, 3, device="cuda"), dim=-1)
        sigma, rgb = training_field(positions, directions)
        (sigma.sum() + rgb.sum()).backward()
        torch.cuda.synchronize()
        assert training_field.graphed_forward is not None
        new = [m for m in set(sys.modules) - loaded if m.startswith(("sympy", "torch.fx.experimental"))]
        print(len(new), sorted(new)[:3])
    """)
    assert seen[0] == "0", seen
