"""``kalmansfm consistency`` and the Task 7 options of ``kalmansfm tables --task 7``."""

import argparse

import numpy as np
import pytest

from kalmansfm.cli import main as cli_main
from kalmansfm.cli.tables import add_task7_options
from kalmansfm.experiments import FusionTable, fusion_table
from kalmansfm.report.tables import format_csv


@pytest.fixture
def main():
    return cli_main.main


def test_task2_text_summary_passes(main, capsys):
    assert main(["consistency", "--task", "2", "--runs", "200", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Task 2, method kalman: 200 runs" in out
    assert out.strip().splitlines()[-1] == "PASS: consistent"


def test_task7_pairs_reports_over_confidence_and_progress_goes_to_stderr(main, capsys):
    assert main(["consistency", "--task", "7", "--runs", "120", "--pixel-std", "1"]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip().splitlines()[-1] == "FAIL: over-confident"
    assert "run" in captured.err  # the tqdm bar


def test_task7_batch_csv_has_one_row_per_iteration(main, capsys):
    argv = ["consistency", "--task", "7", "--method", "batch", "--runs", "60", "--pixel-noise", "1"]
    assert main(argv + ["--format", "csv", "--quiet"]) == 0
    captured = capsys.readouterr()
    rows = captured.out.strip().splitlines()
    assert rows[0].startswith("iter,valid_runs,mean_nees,nees_low,nees_high,inside,within1_x")
    assert len(rows) == 25 and rows[-1].startswith("24,60,")
    assert captured.err == ""


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--task", "2", "--method", "batch"], "--method applies to --task 7 only"),
        (["--task", "7", "--runs", "1"], "--runs must be an integer >= 2"),
        (["--task", "7", "--focal", "0"], "--focal must be finite and > 0"),
        (["--task", "7", "--pixel-std", "-2"], "--pixel-std must be finite and > 0"),
        (["--task", "7", "--pixel-noise", "-2"], "--pixel-std must be finite and > 0"),  # the earlier spelling
        (["--task", "5"], "invalid choice"),
        (["--task", "7", "--method", "ekf"], "invalid choice"),
    ],
)
def test_bad_input_exits_2_with_one_line(main, capsys, argv, fragment):
    try:
        code = main(["consistency", *argv, "--quiet"])
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and fragment in err


def _task7_args(*argv):
    parser = argparse.ArgumentParser()
    add_task7_options(parser)
    return parser.parse_args(list(argv))


def run_task7(args):
    """What ``kalmansfm tables --task 7`` computes from its options."""
    return fusion_table(7, method=args.method, seed=args.seed, focal=args.focal, pixel_noise_std=args.pixel_std)


def test_run_task7_returns_a_fusion_table_in_the_task4_6_columns():
    table = run_task7(_task7_args("--seed", "2"))
    assert isinstance(table, FusionTable) and table.task == 7 and table.iterations == 24
    header = format_csv(table).splitlines()
    assert any(line.startswith("iter,truth_x,truth_y,truth_z,meas_x") for line in header)
    np.testing.assert_allclose(table.truth[0], [41.041, 40.0, 58.293], atol=5e-4)
    # defaults reproduce the report's magnitudes: single-pair stds of tens of metres
    assert 5.0 < np.median(table.measured_std) < 100.0


def test_run_task7_batch_reaches_about_a_metre():
    table = run_task7(_task7_args("--method", "batch", "--seed", "0"))
    assert np.all(table.estimate_std[-1] < 2.0) and np.all(table.estimate_std[-1] > 0.3)
    assert np.all(np.abs(table.estimate[-1] - table.truth[-1]) < 4 * table.estimate_std[-1])


def test_task7_options_reject_unknown_method():
    with pytest.raises(SystemExit):
        _task7_args("--method", "ekf")


def test_task7_default_method_is_one_constant_shown_by_help(main, capsys):
    from kalmansfm.experiments.consistency import run_consistency, task7_consistency
    from kalmansfm.experiments.tables import fusion_table as table_of
    from kalmansfm.structure.fusion.landmark import TASK7_DEFAULT_METHOD

    with pytest.raises(SystemExit):
        main(["consistency", "--help"])
    assert f"Task 7 estimator (default: {TASK7_DEFAULT_METHOD})" in " ".join(capsys.readouterr().out.split())
    with pytest.raises(SystemExit):
        main(["tables", "--help"])
    assert f"(default: {TASK7_DEFAULT_METHOD})" in " ".join(capsys.readouterr().out.split())
    assert main(["consistency", "--task", "7", "--runs", "2", "--quiet"]) == 0
    assert f"method {TASK7_DEFAULT_METHOD}:" in capsys.readouterr().out
    assert run_consistency(7, runs=2).method == TASK7_DEFAULT_METHOD
    for f in (task7_consistency, table_of):
        assert TASK7_DEFAULT_METHOD in (f.__kwdefaults__ or {}).values() or TASK7_DEFAULT_METHOD in f.__defaults__


@pytest.mark.parametrize("command", ["tables", "consistency"])
def test_pixel_std_is_the_spelling_of_every_command_and_pixel_noise_still_works(command):
    from kalmansfm.cli.main import build_parser

    parser = build_parser()
    base = [command, "--task", "7"]
    assert parser.parse_args(base + ["--pixel-std", "2.5"]).pixel_std == 2.5
    assert parser.parse_args(base + ["--pixel-noise", "2.5"]).pixel_std == 2.5
    sub = parser._subparsers._group_actions[0].choices[command]
    text = sub.format_help()
    assert "--pixel-std PX" in text and "--pixel-noise" not in text
    assert "--pixel-std" in parser._subparsers._group_actions[0].choices["fuse"].format_help()


def test_consistency_csv_reads_back_to_the_study_exactly(main, capsys):
    from kalmansfm.experiments.consistency import run_consistency

    assert main(["consistency", "--task", "2", "--runs", "20", "--format", "csv", "--quiet"]) == 0
    rows = [line.split(",") for line in capsys.readouterr().out.strip().splitlines()[1:]]
    study = run_consistency(2, runs=20)
    assert [float(r[2]) for r in rows] == study.mean_nees.tolist()  # full precision, not 6 digits
    assert [float(r[6]) for r in rows] == study.within_1sigma[:, 0].tolist()
