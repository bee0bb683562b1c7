"""Every ``--help``: each useful default once, none for required options or missing defaults, no stray ``%%``."""

import argparse
import re

import pytest

from kalmansfm.cli.main import SUBCOMMANDS, build_parser, main


def help_text(command, capsys):
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def option_entries(text):
    """The help of each option, joined onto one line: {"--out": "output folder", ...}."""
    entries, current = {}, []
    for line in text.split("options:", 1)[1].splitlines():
        match = re.match(r"^  (-\S.*?)(?:  +(.*))?$", line)
        if match:
            current = re.findall(r"(?:^|[ ,])(--?[a-z][\w-]*)", match.group(1))
            for name in current:
                entries[name] = match.group(2) or ""
        elif current and line.startswith("    "):
            for name in current:
                entries[name] += " " + line.strip()
    return {name: " ".join(value.split()) for name, value in entries.items()}


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_each_default_is_shown_once_and_only_when_there_is_one(command, capsys):
    text = help_text(command, capsys)
    assert "(default: None)" not in text
    assert "%%" not in text and "%(" not in text
    parser = build_parser()._subparsers._group_actions[0].choices[command]
    entries = option_entries(text)
    for action in parser._actions:
        name = action.option_strings[-1] if action.option_strings else None
        if name is None or name == "--help" or action.help == argparse.SUPPRESS:  # a hidden alias
            continue
        shown = entries[name]
        assert shown.count("default") <= 1, f"{command} {name}: {shown}"
        if (action.required or action.default is None) and "default" not in (action.help or ""):
            assert "(default:" not in shown, f"{command} {name}: {shown}"
        if isinstance(action.default, bool) and action.nargs == 0 and not shown.count("--no-"):
            assert "(default: False)" not in shown, f"{command} {name}: a plain flag needs no default"


def test_the_examples_of_the_issue(capsys):
    assert re.search(r"--out DIR\s+output folder\n", help_text("track", capsys))
    assert re.search(r"--task N\s+task number\n", help_text("tables", capsys))
    track = " ".join(help_text("track", capsys).split())
    assert "points in frame 0 (default: detect corners) --max-features" in track
    batch = " ".join(help_text("batch", capsys).split())
    assert "workers of the local cluster (default: CPU cores) --report" in batch
    consistency = " ".join(help_text("consistency", capsys).split())
    assert "95 % chi-square interval" in consistency
    assert "Task 7 estimator (default: pairs) --runs" in consistency
    scene = " ".join(help_text("scene", capsys).split())
    assert "image size in pixels (default: 320x240)" in scene
