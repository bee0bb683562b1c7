"""Reporting: tables, plots and the HTML report."""

from .html import build_report, render_report
from .run_folder import RunFolder, load_run, read_summary

__all__ = ["RunFolder", "build_report", "load_run", "read_summary", "render_report"]
