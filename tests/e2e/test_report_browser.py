"""The report in a real browser (headless Chromium) when one is installed.

Conditional by design, never skipped: the test is parametrised with the
browser it found.  With Chromium (``/usr/bin/chromium``, or ``chromium`` /
``chromium-browser`` on PATH) it loads the report offline, checks that the
page's script ran to the end without an error or console message, and that a
screenshot is a non-blank PNG.  Without Chromium the parameter is
``no-chromium-plain-html-checks`` and the same test asserts the plain HTML
checks instead, so a run without a browser is visible in the test id rather
than passing silently.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import cv2
import fake_run  # tests/unit/report (see tests/conftest.py)
import numpy as np
import pytest
import report_checks

from kalmansfm.report import build_report


def find_chromium() -> str | None:
    if Path("/usr/bin/chromium").is_file():
        return "/usr/bin/chromium"
    return shutil.which("chromium") or shutil.which("chromium-browser")


CHROMIUM = find_chromium()


def run_chromium(browser: str, profile: Path, *arguments: str) -> subprocess.CompletedProcess:
    command = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--host-resolver-rules=MAP * ~NOTFOUND",  # any attempt to reach the network fails
        f"--user-data-dir={profile}",
        *arguments,
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)


def console_lines(stderr: str) -> list[str]:
    """Chromium's log lines of console messages and uncaught errors."""
    return [line for line in stderr.splitlines() if ":CONSOLE" in line or "Uncaught" in line]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    return build_report(fake_run.write_fake_run(tmp_path_factory.mktemp("browser") / "run"))


@pytest.mark.parametrize("browser", [CHROMIUM], ids=["chromium" if CHROMIUM else "no-chromium-plain-html-checks"])
def test_report_loads_in_a_browser(browser, report, tmp_path):
    """With Chromium: script ran, no console errors, screenshot non-blank. Without: plain HTML checks."""
    parsed = report_checks.assert_self_contained(report.read_text(encoding="utf-8"))
    if browser is None:
        assert {"player-frames", "shape-data", "js-status"} <= parsed.ids
        assert len(parsed.images) >= 8
        return

    # the console check itself must see an error on a page that has one
    broken = tmp_path / "broken.html"
    broken.write_text("<!DOCTYPE html><html><body><script>notDefined();</script></body></html>")
    result = run_chromium(
        browser, tmp_path / "profile-broken", "--enable-logging=stderr", "--v=0", "--dump-dom", broken.as_uri()
    )
    assert any("Uncaught ReferenceError" in line for line in console_lines(result.stderr)), result.stderr[-2000:]

    dom = run_chromium(
        browser, tmp_path / "profile-dom", "--enable-logging=stderr", "--v=0", "--dump-dom", report.as_uri()
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    status = re.search(r"<p id=\"js-status\"[^>]*>", dom.stdout).group(0)
    assert 'data-ready="yes"' in status, "the page script did not run to its end"
    assert "data-errors" not in status, status
    assert console_lines(dom.stderr) == []
    # the player's script replaced the first frame by itself, as a data URI
    assert 'id="player-label">frame 0 (1 of 8)' in dom.stdout

    screenshot = tmp_path / "report.png"
    shot = run_chromium(
        browser,
        tmp_path / "profile-shot",
        "--hide-scrollbars",
        f"--screenshot={screenshot}",
        "--window-size=1280,2000",
        report.as_uri(),
    )
    assert shot.returncode == 0, shot.stderr[-2000:]
    image = cv2.imread(str(screenshot))
    assert image is not None and image.shape == (2000, 1280, 3)
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert grey.std() > 20, "screenshot is (nearly) blank"
    colourful = np.ptp(image.astype(int), axis=2) > 80
    assert colourful.mean() > 0.002, "no coloured figures or overlays visible"


@pytest.mark.parametrize("browser", [CHROMIUM], ids=["chromium" if CHROMIUM else "no-chromium-plain-html-checks"])
def test_a_real_footage_report_folds_its_table_and_hides_unreliable_points(browser, hotel_run, tmp_path):
    """cmu_hotel (conftest.py): after the page script, 180 of the 200 per-track rows are folded away,
    the unreliable points sit behind an unchecked box, and nothing went wrong in the console."""
    report = hotel_run.out / "report.html"
    document = report.read_text(encoding="utf-8")
    parsed = report_checks.assert_self_contained(document)
    assert {"view3d-unreliable", "shape-data", "player-frames"} <= parsed.ids
    if browser is None:
        assert 'data-fold="20"' in document and "show all 200 rows" in document
        return
    dom = run_chromium(
        browser, tmp_path / "profile-hotel", "--enable-logging=stderr", "--v=0", "--dump-dom", report.as_uri()
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    status = re.search(r"<p id=\"js-status\"[^>]*>", dom.stdout).group(0)
    assert 'data-ready="yes"' in status and "data-errors" not in status, status
    assert console_lines(dom.stderr) == []
    table = re.search(r'<table class="sortable folded" data-fold="20">(.*?)</table>', dom.stdout, re.S).group(1)
    assert table.count("<tr hidden") == 180 and table.count("<tr>") == 1 + 20
    assert re.search(r'<input id="view3d-unreliable" type="checkbox">', dom.stdout)
