"""``./dev bench --results DIR``: each benchmark's output lands in ``DIR/bench_<name>.md`` under the command that
rewrites it (docs/performance.md links these files as the latest results)."""

from __future__ import annotations

from pathlib import Path

from bench.__main__ import main, write_result


def test_a_result_file_names_the_command_that_rewrites_it(tmp_path: Path) -> None:
    path = write_result(tmp_path / "results", "train", ["--sections", "3"], "ratio 5.79x\n", 0, 12.3, "0.5 0.4 0.3",
                        "abc1234")
    text = path.read_text()
    assert path.name == "bench_train.md"
    assert text.startswith("# bench_train: latest result\n")
    assert f"Written by `./dev bench --results {tmp_path / 'results'} train --sections 3`" in text
    assert "commit abc1234" in text and "exit status 0, 12 s" in text and "0.5 0.4 0.3 before" in text
    assert "```\nratio 5.79x\n```" in text


def test_results_without_a_directory_is_a_usage_error(tmp_path: Path) -> None:
    assert main(["--results"]) == 2
    assert main(["--results", str(tmp_path), "no_such_bench"]) == 2
    assert not list(tmp_path.iterdir())
