"""Small pieces of the report's HTML: escaped text, embedded images, numbers, tables, cards and warnings."""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Iterable, Sequence
from typing import Any

__all__ = ["Html", "cards", "esc", "figure", "frames_warning", "img", "is_number", "number", "percent", "table"]

esc = html.escape


def data_uri(image: bytes, media_type: str = "image/png") -> str:
    """``image`` (PNG unless said otherwise) as a data URI for an ``<img src>``."""
    return f"data:{media_type};base64," + base64.b64encode(image).decode("ascii")


def img(png: bytes, alt: str, *, css_class: str = "", width: int | None = None) -> str:
    attrs = f' class="{css_class}"' if css_class else ""
    if width:
        attrs += f' width="{width}"'
    return f'<img src="{data_uri(png)}" alt="{esc(alt)}"{attrs}>'


def figure(png: bytes, caption: str, alt: str | None = None) -> str:
    return f"<figure>{img(png, alt or caption)}<figcaption>{caption}</figcaption></figure>"


def number(value: Any, digits: int = 4) -> str:
    """A value for a table cell: None → an em dash, floats to ``digits`` significant digits."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "—"
        return f"{value:.{digits}g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(number(v, digits) for v in value)
    if isinstance(value, dict):
        return esc(json.dumps(value))
    return esc(str(value))


def percent(value: Any) -> str:
    return "—" if not isinstance(value, (int, float)) or isinstance(value, bool) else f"{100 * value:.1f} %"


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class Html(str):
    """Markup that a table cell inserts as it is (already escaped)."""


def is_empty(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def table(
    header: Sequence[str],
    rows: Iterable[Sequence[Any]],
    *,
    sortable: bool = False,
    numeric: Sequence[bool] = (),
    fold: int | None = None,
    drop_empty: bool = False,
) -> str:
    """An HTML table of ``rows`` under ``header``.

    With ``fold`` a table longer than that shows its first ``fold`` rows and a button for
    the rest (the page script folds it; without script every row shows).  With
    ``drop_empty`` a column empty in every row (an em dash throughout) is left out.
    """
    rows = [list(row) for row in rows]
    if drop_empty and rows:
        keep = [k for k in range(len(header)) if not all(is_empty(row[k]) for row in rows)]
        header = [header[k] for k in keep]
        numeric = [numeric[k] for k in keep if k < len(numeric)]
        rows = [[row[k] for k in keep] for row in rows]
    folded = fold is not None and len(rows) > fold
    classes = [name for name, on in (("sortable", sortable), ("folded", folded)) if on]
    css = f' class="{" ".join(classes)}"' if classes else ""
    fold_attr = f' data-fold="{fold}"' if folded else ""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for row in rows:
        cells = []
        for k, value in enumerate(row):
            is_num = numeric[k] if k < len(numeric) else is_number(value)
            sort_key = f' data-sort="{value}"' if is_number(value) else ""
            css_cell = ' class="num"' if is_num else ""
            cells.append(f"<td{css_cell}{sort_key}>{value if isinstance(value, Html) else number(value)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    table = f"<table{css}{fold_attr}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"
    if fold_attr:
        table += (f'<p class="note"><button type="button" class="fold-toggle">show all {len(rows)} rows</button> '
                  f"(the first {fold} are shown; sorting sorts all)</p>")
    return table


def cards(items: Sequence[tuple[str, str]]) -> str:
    cards = "".join(
        f'<div class="card"><div class="value">{value}</div><div class="label">{esc(label)}</div></div>'
        for label, value in items
    )
    return f'<div class="cards">{cards}</div>'



def frames_warning(label: str, frames: Sequence[int], shown: int) -> str:
    """A warning paragraph listing the first ``shown`` frame numbers (an ellipsis when there are more)."""
    listed = ", ".join(str(f) for f in frames[:shown])
    more = " …" if len(frames) > shown else ""
    return f'<p class="warn">{esc(label)}: {esc(listed)}{more}</p>'
