"""Self-contained HTML reports: sections of text, tables and figures, images embedded as base64.

A report opens in any browser with no other file beside it. It always ends with the exact command
that made it, the commit of the code (and whether it was clean) and the versions of the packages
involved.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import importlib.metadata
import platform
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.provenance import provenance_line

__all__ = ["Report", "Section", "versions"]

PACKAGES = ("bayesdrive", "jax", "jaxlib", "numpyro", "arviz", "numpy", "pandas", "scipy", "emcee")

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 70em; margin: 2em auto; padding: 0 1em;
       color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #444; } h2 { margin-top: 2em; border-bottom: 1px solid #bbb; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
.note { background: #fff8e0; border-left: 4px solid #e0b000; padding: 0.5em 1em; }
pre { background: #f6f6f6; padding: 0.7em; overflow-x: auto; }
nav ul { columns: 2; }
"""


def versions() -> dict[str, str]:
    """Installed versions of the packages a result depends on, plus Python's."""
    found = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            found[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            found[name] = "not installed"
    return found


@dataclass
class Section:
    """One titled part of a report: paragraphs, notes, tables and figures in the order added."""

    title: str
    parts: list[str] = field(default_factory=list)

    def text(self, paragraph: str) -> Section:
        self.parts.append(f"<p>{html.escape(paragraph)}</p>")
        return self

    def note(self, paragraph: str) -> Section:
        """A highlighted paragraph: where we differ from the paper, caveats, artefacts."""
        self.parts.append(f'<p class="note">{html.escape(paragraph)}</p>')
        return self

    def code(self, text: str) -> Section:
        self.parts.append(f"<pre>{html.escape(text)}</pre>")
        return self

    def table(
        self, frame: pd.DataFrame, caption: str = "", float_format: str = "{:.3g}"
    ) -> Section:
        body = frame.to_html(
            index=False,
            escape=True,
            border=0,
            float_format=lambda x: float_format.format(x),
            na_rep="-",
        )
        if caption:
            body = f"<p><b>{html.escape(caption)}</b></p>{body}"
        self.parts.append(body)
        return self

    def figure(self, png: Path, caption: str) -> Section:
        data = base64.b64encode(Path(png).read_bytes()).decode("ascii")
        self.parts.append(
            f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )
        return self


@dataclass
class Report:
    """A titled list of sections, rendered to one HTML file."""

    title: str
    intro: str = ""
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str) -> Section:
        new = Section(title)
        self.sections.append(new)
        return new

    def render(self, command: Sequence[str] | None = None) -> str:
        command_line = " ".join(command if command is not None else sys.argv)
        anchors = [f"s{i}" for i in range(len(self.sections))]
        toc = "".join(
            f'<li><a href="#{a}">{html.escape(s.title)}</a></li>'
            for a, s in zip(anchors, self.sections, strict=True)
        )
        body = "".join(
            f'<h2 id="{a}">{html.escape(s.title)}</h2>' + "".join(s.parts)
            for a, s in zip(anchors, self.sections, strict=True)
        )
        version_rows = "".join(
            f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>"
            for k, v in versions().items()
        )
        stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
        return (
            "<!DOCTYPE html><html><head><meta charset='utf-8'>"
            f"<title>{html.escape(self.title)}</title><style>{STYLE}</style></head><body>"
            f"<h1>{html.escape(self.title)}</h1><p>{html.escape(self.intro)}</p>"
            f"<nav><ul>{toc}</ul></nav>{body}"
            "<h2>How this report was made</h2>"
            f"<p>Command:</p><pre>{html.escape(command_line)}</pre>"
            f"<p>Code: {html.escape(provenance_line())}.</p>"
            f"<p>Generated {stamp}.</p><table><tr><th>package</th><th>version</th></tr>"
            f"{version_rows}</table></body></html>"
        )

    def write(self, path: Path, command: Sequence[str] | None = None) -> Path:
        write_text_atomic(Path(path), self.render(command))
        return Path(path)
