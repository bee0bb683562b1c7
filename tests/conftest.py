"""Shared test set-up.

The report's fake run folder (``tests/unit/report/fake_run.py``) and its HTML checks
(``report_checks.py``) are used by unit, CLI and browser tests alike; their folder
goes on the import path once, so every test imports them as the same modules.  The
NumPy references of the compiled kernels (``tests/reference``) are imported as
``reference.<name>``.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "unit" / "report"))
sys.path.insert(0, str(Path(__file__).parent))
