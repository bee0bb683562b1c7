"""Reporting: figures, tables and the HTML report. It draws and formats what it is given; it computes no estimates."""

from .html import build_report, render_report

__all__ = ["build_report", "render_report"]
