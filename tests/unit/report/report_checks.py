"""Plain-HTML checks of a report, shared by the unit, CLI and browser tests."""

from __future__ import annotations

import base64
import re
from dataclasses import dataclass, field
from html.parser import HTMLParser

import cv2
import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass
class ParsedReport:
    images: list[str] = field(default_factory=list)  # src of every <img>
    ids: set[str] = field(default_factory=set)
    anchors: list[str] = field(default_factory=list)  # href of every <a>
    script_sources: list[str] = field(default_factory=list)
    stylesheet_links: list[str] = field(default_factory=list)
    section_ids: list[str] = field(default_factory=list)
    tags: dict[str, int] = field(default_factory=dict)


class _Collector(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.report = ParsedReport()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.report.tags[tag] = self.report.tags.get(tag, 0) + 1
        if "id" in a:
            self.report.ids.add(a["id"])
        if tag == "img":
            self.report.images.append(a.get("src") or "")
        elif tag == "a" and "href" in a:
            self.report.anchors.append(a["href"])
        elif tag == "script" and "src" in a:
            self.report.script_sources.append(a["src"])
        elif tag == "link":
            self.report.stylesheet_links.append(a.get("href") or "")
        elif tag == "section":
            self.report.section_ids.append(a.get("id") or "")


def parse_report(document: str) -> ParsedReport:
    collector = _Collector()
    collector.feed(document)
    collector.close()
    return collector.report


def decode_png_data_uri(src: str) -> np.ndarray:
    """The image of a ``data:image/png;base64,`` URI; fails the test if it is anything else."""
    prefix = "data:image/png;base64,"
    assert src.startswith(prefix), f"image is not an embedded PNG: {src[:60]!r}"
    data = base64.b64decode(src[len(prefix) :], validate=True)
    assert data.startswith(PNG_SIGNATURE), "embedded image does not carry the PNG signature"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.size > 0, "embedded PNG does not decode"
    return image


def decode_image_data_uri(src: str) -> np.ndarray:
    """The image of an embedded PNG (plots, strips) or JPEG (the player's frames) data URI."""
    prefix = "data:image/jpeg;base64,"
    if not src.startswith(prefix):
        return decode_png_data_uri(src)
    data = base64.b64decode(src[len(prefix):], validate=True)
    assert data.startswith(b"\xff\xd8"), "embedded image does not carry the JPEG signature"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.size > 0, "embedded JPEG does not decode"
    return image


def assert_self_contained(document: str) -> ParsedReport:
    """Parse the report and check it needs nothing outside the file; return what was parsed."""
    parsed = parse_report(document)
    assert parsed.tags.get("html") == 1 and parsed.tags.get("body") == 1
    assert not parsed.script_sources, f"external scripts: {parsed.script_sources}"
    assert not parsed.stylesheet_links, f"<link> elements: {parsed.stylesheet_links}"
    external = re.findall(r"(?:https?:)?//[\w.-]+\.[a-z]{2,}[^\s\"'<>)]*", document)
    assert not external, f"references to external resources: {external[:5]}"
    assert "url(" not in document.replace("url(#", ""), "CSS url() reference"
    for src in parsed.images:
        decode_image_data_uri(src)
    # every in-page link points at an element that exists
    for href in parsed.anchors:
        if href.startswith("#"):
            assert href[1:] in parsed.ids, f"link {href} has no target"
    return parsed
