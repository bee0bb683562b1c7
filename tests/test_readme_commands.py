"""The two commands of the README are the ones CI runs, to the letter."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ci_runs_exactly_the_readme_commands():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Two commands"):readme.index("## A five-minute tour")]
    commands = re.findall(r"```bash\n(.+?)\n```", section)
    assert len(commands) == 2 and commands[0].startswith("pip install . ") and "pytest" in commands[1]
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
    assert [line for line in ci_lines if line in commands] == commands  # both, in this order
