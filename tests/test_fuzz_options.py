"""Every numeric option of every subcommand given values it cannot take, and every path option
given a place it cannot use: each ends in exit code 2 with one error line, no traceback, before
any work, and the trained folder ("golden") the commands point at stays byte-for-byte the same."""

from pathlib import Path

import pytest

from ngp_warp.cli import main
from test_fuzz_cli import assert_one_error_line, folder_digest, golden, scene  # noqa: F401  (fixtures)

COUNT = ["0", "-1", "1.5", "abc", "nan", "", "1e400", "9" * 30]  # not a positive int
SEED = ["-1", "1.5", "abc", "", "9" * 30]  # not an int in [0, 2^63)
POSITIVE = ["0", "-1", "nan", "inf", "-inf", "abc", "", "1e400"]  # not a positive finite number
TRAINING = {"--steps": COUNT, "--seconds": POSITIVE, "--downscale": COUNT, "--seed": SEED,
            "--target-samples": COUNT, "--frames": COUNT + ["1000000000"], "--checkpoint-every": POSITIVE}


def commands(scene: str, golden: str, tmp: str) -> dict[str, tuple[list[str], dict[str, list[str]]]]:
    """{subcommand: (a valid command line, {option: values it cannot take})}."""
    out = ["--out", f"{tmp}/new"]
    return {
        "train": (["train", scene, *out, "--steps", "2"], TRAINING),
        "demo": (["demo", *out, "--steps", "2"], TRAINING),
        "fit-many": (["fit-many", f"{scene}*", *out, "--steps", "2"], {**TRAINING, "--gpus": COUNT}),
        "render": (["render", golden, "--video", f"{tmp}/v.gif", "--frames", "2"],
                   {"--frames": COUNT + ["1000000000"], "--fps": POSITIVE + ["1e-300", "5000"]}),
        "export": (["export", golden, "--mesh", f"{tmp}/m.ply", "--resolution", "8"],
                   {"--resolution": COUNT, "--threshold": POSITIVE, "--max-points": COUNT[:-1]}),  # huge: all
        "view": (["view", golden, "--port", "1"],
                 {"--port": COUNT + ["65536", "70000"], "--resolution": COUNT, "--moving-resolution": COUNT,
                  "--steps": COUNT, "--seconds": POSITIVE, "--downscale": COUNT, "--seed": SEED,
                  "--target-samples": COUNT}),
        "process": (["process", f"{tmp}/photos", *out], {"--frames": COUNT + ["1000000000"],
                                                          "--fps": POSITIVE + ["5000"]}),
    }


CASES = [(name, option, value) for name, (_, bad) in commands("s", "g", "t").items()
         for option, values in bad.items() for value in values]
PATHS = {  # a place a path option cannot use, per subcommand (TMP: this case's folder)
    "train --out: a file": ["train", "SCENE", "--out", "TMP/file"],
    "train --out: under a file": ["train", "SCENE", "--out", "TMP/file/run"],
    "train: a missing scene": ["train", "TMP/missing", "--out", "TMP/new"],
    "train: a file as the scene": ["train", "TMP/file", "--out", "TMP/new"],
    "eval: a file as the run": ["eval", "TMP/file"],
    "eval: a folder without a run": ["eval", "TMP"],
    "render --video: a folder": ["render", "GOLDEN", "--video", "TMP"],
    "render --video: no folder": ["render", "GOLDEN", "--video", "TMP/missing/v.gif"],
    "render --path: missing": ["render", "GOLDEN", "--video", "TMP/v.gif", "--path", "TMP/missing.json"],
    "render --path: not json": ["render", "GOLDEN", "--video", "TMP/v.gif", "--path", "TMP/file"],
    "export --mesh: a folder": ["export", "GOLDEN", "--mesh", "TMP"],
    "export --points: not ply": ["export", "GOLDEN", "--points", "TMP/p.txt"],
    "export: nothing asked": ["export", "GOLDEN"],
    "view: a missing folder": ["view", "TMP/missing", "--port", "1"],
    "fit-many: a missing manifest": ["fit-many", "TMP/missing.txt", "--out", "TMP/new"],
    "fit-many --out: a file": ["fit-many", "SCENE*", "--out", "TMP/file"],
    "process: a missing input": ["process", "TMP/missing", "--out", "TMP/new"],
    "process --out: the input": ["process", "TMP", "--out", "TMP"],
}


def _run(argv: list[str], capsys) -> int:
    capsys.readouterr()
    try:
        return main(argv)
    except SystemExit as e:  # argparse's own errors: usage line + one error line
        return e.code


@pytest.mark.parametrize("name, option, value", CASES)
def test_an_option_value_it_cannot_take_is_one_line(name, option, value, scene, golden, tmp_path, capsys):
    before = folder_digest(golden)
    valid, _ = commands(str(scene), str(golden), str(tmp_path))[name]
    argv = [a for a in valid]
    if option in argv:
        argv[argv.index(option) + 1] = value
    else:
        argv += [option, value]
    if name != "process":
        argv += ["--device", "cpu"]
    assert_one_error_line(_run(argv + ["--quiet"], capsys), capsys)
    assert folder_digest(golden) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize("case", sorted(PATHS))
def test_a_path_it_cannot_use_is_one_line(case, scene, golden, tmp_path, capsys):
    (tmp_path / "file").write_text("not a scene, a run or a camera path")
    before = folder_digest(golden)
    argv = [a.replace("SCENE", str(scene)).replace("GOLDEN", str(golden)).replace("TMP", str(tmp_path))
            for a in PATHS[case]]
    if argv[0] != "process":
        argv += ["--device", "cpu"]
    assert_one_error_line(_run(argv + ["--quiet"], capsys), capsys)
    assert folder_digest(golden) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


LEGAL_EXTREMES = {  # the edges of what each option takes: they work
    "train: one step, one frame, one sample": (["train", "SCENE", "--out", "TMP/run", "--steps", "1", "--frames", "1",
                                                "--target-samples", "1", "--checkpoint-every", "1e-9"], "TMP/run/orbit"),
    "train: a downscale to 2 pixels": (["train", "SCENE", "--out", "TMP/run", "--steps", "1", "--downscale", "8",
                                        "--no-video", "--seed", str(2**63 - 1)], "TMP/run/metrics.json"),
    "render: a frame a hundred seconds": (["render", "GOLDEN", "--video", "TMP/v.gif", "--frames", "1",
                                           "--fps", "0.01"], "TMP/v.gif"),
    "render: a thousand frames a second": (["render", "GOLDEN", "--video", "TMP/v.gif", "--frames", "2",
                                            "--fps", "1000"], "TMP/v.gif"),
    "export: one point": (["export", "GOLDEN", "--points", "TMP/p.ply", "--max-points", "1"], "TMP/p.ply"),
}


@pytest.mark.parametrize("case", sorted(LEGAL_EXTREMES))
def test_legal_extremes_work(case, scene, golden, tmp_path, capsys):
    argv, made = LEGAL_EXTREMES[case]
    argv = [a.replace("SCENE", str(scene)).replace("GOLDEN", str(golden)).replace("TMP", str(tmp_path)) for a in argv]
    assert _run(argv + ["--device", "cpu", "--quiet"], capsys) == 0, capsys.readouterr().err
    made = Path(made.replace("TMP", str(tmp_path)))
    assert made.exists() or any(made.parent.glob(made.name + ".*")), sorted(made.parent.iterdir())
