"""`monolib bench NAME`: a command per benchmark with its own arguments; none, or an unknown one, is an error."""
import pytest

from monolib import cli


def test_each_benchmark_is_its_own_command():
    parser = cli.build_parser()
    assert set(cli.BENCHMARKS) == {"frames", "render", "localizers", "localize", "imagenet", "allocator", "cell",
                                   "selection", "grid"}
    args = parser.parse_args(["bench", "render", "c736e94", "--study", "smoke", "--out", "x.json"])
    assert (args.benchmark, args.commit, args.study, args.out) == ("render", "c736e94", "smoke", "x.json")
    args = parser.parse_args(["bench", "frames", "--width", "128"])
    assert (args.benchmark, args.width, args.height, args.study) == ("frames", 128, 192, "quick")
    assert not hasattr(parser.parse_args(["bench", "selection"]), "out")  # it writes the study's own pages


@pytest.mark.parametrize("argv", [["bench"], ["bench", "speed"], ["bench", "render"],
                                  ["bench", "grid", "--study", "x"]])
def test_no_benchmark_an_unknown_one_or_a_missing_argument_is_an_error(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.build_parser().parse_args(argv)
    assert exc.value.code == 2
    assert "error:" in capsys.readouterr().err
