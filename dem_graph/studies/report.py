"""A report page: a title, paragraphs, one table and captioned PNG figures, written as Markdown
(figures linked by relative path) and as one self-contained HTML file (figures embedded as base64
data URIs; no script, no stylesheet or image from elsewhere).
"""

from __future__ import annotations

import base64
import html
import os
from dataclasses import dataclass
from pathlib import Path

from dem_graph.errors import DatasetError


@dataclass(frozen=True)
class Figure:
    path: Path  # a PNG file
    caption: str


@dataclass(frozen=True)
class ReportPage:
    """One table (its first and last columns are text, the others numbers) between paragraphs and figures."""

    title: str
    paragraphs: list[str]
    headers: list[str]
    rows: list[list[str]]
    figures: list[Figure]
    notes: list[str]  # after the table: failed runs, what a column means

    def markdown(self, relative_to: Path) -> str:
        """The page as Markdown; figure paths relative to the folder ``relative_to``."""

        def cell(text: str) -> str:
            return str(text).replace("|", "\\|").replace("\n", " ")

        lines = [f"# {self.title}", ""]
        for p in self.paragraphs:
            lines += [p, ""]
        lines.append("| " + " | ".join(cell(h) for h in self.headers) + " |")
        last = len(self.headers) - 1
        lines.append("|" + "|".join("---" if i in (0, last) else "---:" for i in range(len(self.headers))) + "|")
        lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in self.rows]
        lines.append("")
        lines += [f"- {n}" for n in self.notes]
        if self.notes:
            lines.append("")
        for f in self.figures:
            link = Path(os.path.relpath(f.path, relative_to)).as_posix()
            lines += [f"![{f.caption}]({link})", "", f"*{f.caption}*", ""]
        return "\n".join(lines)

    def html(self) -> str:
        """The page as one HTML document with every figure inside it."""
        e = html.escape
        parts = [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{e(self.title)}</title>",
            "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em}"
            "table{border-collapse:collapse;font-size:0.9em}th,td{border:1px solid #bbb;padding:4px 8px}"
            "td{text-align:right}td:first-child,th:first-child,td:last-child{text-align:left}th{background:#eee}"
            "figure{margin:2em 0}img{max-width:100%}figcaption{font-style:italic}</style>",
            "</head><body>",
            f"<h1>{e(self.title)}</h1>",
        ]
        parts += [f"<p>{e(p)}</p>" for p in self.paragraphs]
        parts.append("<table><thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in self.headers) + "</tr></thead><tbody>")
        parts += ["<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in row) + "</tr>" for row in self.rows]
        parts.append("</tbody></table>")
        if self.notes:
            parts.append("<ul>" + "".join(f"<li>{e(n)}</li>" for n in self.notes) + "</ul>")
        for f in self.figures:
            data = base64.b64encode(_read_bytes(f.path)).decode("ascii")
            parts.append(f'<figure><img alt="{e(f.caption)}" src="data:image/png;base64,{data}"><figcaption>{e(f.caption)}</figcaption></figure>')
        parts.append("</body></html>")
        return "\n".join(parts) + "\n"

    def write(self, md_path: str | Path, html_path: str | Path) -> tuple[Path, Path]:
        md_path, html_path = Path(md_path), Path(html_path)
        _write_text(md_path, self.markdown(md_path.parent))
        _write_text(html_path, self.html())
        return md_path, html_path


def _read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None


def _write_text(path: Path, text: str) -> None:
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None


__all__ = ["Figure", "ReportPage"]
