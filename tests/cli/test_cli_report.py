
import fake_run  # tests/unit/report (see tests/conftest.py)
import pytest

import kalmansfm.cli.main as cli
from kalmansfm.io import RunSummary, summary_json


def test_report_rebuilds_the_html_and_prints_its_path(tmp_path, capsys):
    run = fake_run.write_fake_run(tmp_path / "run")
    assert cli.main(["report", str(run), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(run / "report.html")
    assert err == ""
    assert "kalmansfm report" in (run / "report.html").read_text()


def test_open_hands_a_file_uri_to_the_browser(tmp_path, capsys, monkeypatch):
    (tmp_path / "summary.json").write_text(summary_json(RunSummary(command="track", input="x")))
    opened = []
    monkeypatch.setattr("webbrowser.open", lambda url, *a, **k: opened.append(url) or True)
    assert cli.main(["report", str(tmp_path), "--open", "--quiet"]) == 0
    assert opened == [(tmp_path / "report.html").resolve().as_uri()]


def test_missing_summary_exits_2_with_one_line(tmp_path, capsys):
    assert cli.main(["report", str(tmp_path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and "summary.json: not found" in err
    assert not (tmp_path / "report.html").exists()


def test_help_describes_the_folder(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["report", "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "DIR" in out and "--open" in out and "summary.json" in out
