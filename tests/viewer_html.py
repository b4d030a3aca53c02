"""The plotly figure of an HTML viewer (`jsphere.animate(..., "x.html")`), read from the file
without a browser: `viewer_figure(path)` returns its `data`, `layout` and `frames` as plotly
gives them to `Plotly.newPlot` and `Plotly.addFrames`.

Importable from any test folder as `from viewer_html import viewer_figure` (pytest puts
`tests/`, the folder of the root `conftest.py`, on the import path)."""

from __future__ import annotations

import json
import re
from pathlib import Path

_DECODER = json.JSONDecoder()


def _arguments(html: str, call: str, count: int) -> list:
    """The first `count` arguments of the page's last `call(` (JSON values, or a quoted id)."""
    text = html[html.rindex(call) + len(call) :]
    out = []
    for _ in range(count):
        text = text.lstrip()
        quoted = re.match(r"'([^']*)'", text)
        if quoted:
            out.append(quoted.group(1))
            end = quoted.end()
        else:
            value, end = _DECODER.raw_decode(text)
            out.append(value)
        text = text[end:].lstrip()[1:]  # past the comma
    return out


def viewer_figure(path) -> tuple[list, dict, list]:
    """`(data, layout, frames)` of the viewer at `path`."""
    html = Path(path).read_text()
    _, data, layout = _arguments(html, "Plotly.newPlot(", 3)
    _, frames = _arguments(html, "Plotly.addFrames(", 2)
    return data, layout, frames


def frame_time(frame: dict) -> str:
    """The run time a frame's on-screen status shows (`"0.07"` of `"t =  0.07 s   speed ..."`)."""
    return re.match(r"t =\s*(\S+) s", frame["layout"]["annotations"][1]["text"]).group(1)
