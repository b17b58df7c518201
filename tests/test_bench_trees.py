"""benchmarks/bench_trees.py: source trees run by turns, each from its own folder."""

import subprocess

import pytest

from benchmark_scripts import load_benchmark
from data_fixtures import nerf_synthetic

bench_trees = load_benchmark("bench_trees")


def _commit(name: str) -> str | None:
    done = subprocess.run(["git", "-C", str(bench_trees.ROOT), "rev-parse", "--verify", f"{name}^{{commit}}"],
                          capture_output=True, text=True)
    return done.stdout.strip()[:10] if done.returncode == 0 else None


def test_each_round_turns_the_order_over():
    assert bench_trees.order(["a", "b"], 3) == ["a", "b", "b", "a", "a", "b"]
    assert bench_trees.order(["a", "b", "c"], 2) == ["a", "b", "c", "c", "b", "a"]


def test_two_commits_run_by_turns_each_from_its_own_tree(tmp_path, capsys):
    head, parent = _commit("HEAD"), _commit("HEAD~1")
    if head is None or parent is None:
        pytest.skip("not a git checkout with two commits")
    nerf_synthetic(tmp_path / "scene", n_train=3, n_test=2, size=(16, 12))
    result = bench_trees.main(["--trees", "HEAD~1,HEAD", "--rounds", "1", "--out", str(tmp_path / "bench"), "--",
                               "train", str(tmp_path / "scene"), "--steps", "2", "--device", "cpu", "--no-video",
                               "--quiet", "--target-samples", "4096"])
    assert list(result["runs"]) == [parent, head]
    for runs in result["runs"].values():
        assert len(runs) == 1 and runs[0]["steps"] == 2
        assert runs[0]["command"] > runs[0]["start_up"] + runs[0]["training"] + runs[0]["evaluation"] > 0
    for commit in (head, parent):
        assert (tmp_path / "bench" / f"tree-{commit}" / "ngp_warp" / "kernels" / "__init__.py").is_file()
    table = capsys.readouterr().out
    assert f"| {parent} | 1 |" in table and f"| {head} | 2 |" in table


def test_a_folder_holding_a_tree_is_taken_as_it_is(tmp_path):
    tree = tmp_path / "base"
    (tree / "ngp_warp" / "kernels").mkdir(parents=True)
    for init in ("ngp_warp/__init__.py", "ngp_warp/kernels/__init__.py"):
        (tree / init).write_text("")
    assert bench_trees.unpack(str(tree), tmp_path / "out") == ("base", tree.resolve())
    bench_trees.check_import(tree)  # a run there imports this package and its kernels


def test_a_tree_that_would_import_another_package_is_refused(tmp_path):
    empty = tmp_path / "tree"
    empty.mkdir()  # no ngp_warp here: the run would import the installed one
    with pytest.raises(SystemExit, match="would import ngp_warp from"):
        bench_trees.check_import(empty)
    (empty / "ngp_warp").mkdir()
    (empty / "ngp_warp" / "__init__.py").write_text("")  # kernels left to the installed package's hook
    with pytest.raises(SystemExit, match="would import ngp_warp from"):
        bench_trees.check_import(empty)
