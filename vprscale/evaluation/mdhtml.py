"""``report.md`` as HTML, for ``report.html``: the page holds the whole report, not a third of it.

The report's Markdown is vprscale's own and of a small subset: headings, paragraphs, list
items, pipe tables, images of the figures beside it, and inline ``**strong**``, ```code``` and
backslash escapes (:mod:`vprscale.core.plaintext` writes every value that way). This renders
that subset and nothing more: every piece of text is HTML-escaped after its Markdown escapes are
undone, so a label that came from a file is text in the page as it is in the Markdown, and each
figure is embedded as a PNG data URI, so the page stays one file that opens offline.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

_IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)\s]+)\)$")
_CODE = re.compile(r"(`+)(.+?)\1")
_STRONG = re.compile(r"\*\*(.+?)\*\*")
_ESCAPED = re.compile(r"\\([!-/:-@\[-`{-~])")  # a backslash before ASCII punctuation: the character itself
_CELL = re.compile(r"(?<!\\)\|")


def inline(text: str) -> str:
    """One line of Markdown text as HTML: code spans verbatim, ``**strong**``, escapes undone,
    everything else escaped."""
    out, at = [], 0
    for m in _CODE.finditer(text):
        out.append(_strong(text[at : m.start()]))
        out.append(f"<code>{html.escape(m.group(2).strip() if m.group(2).strip() else m.group(2))}</code>")
        at = m.end()
    out.append(_strong(text[at:]))
    return "".join(out)


def _strong(text: str) -> str:
    parts = _STRONG.split(text)  # odd pieces were between ** and **
    return "".join(f"<strong>{_text(p)}</strong>" if i % 2 else _text(p) for i, p in enumerate(parts))


def _text(text: str) -> str:
    return html.escape(_ESCAPED.sub(r"\1", text))


def _cells(line: str) -> list[str]:
    return [c.strip() for c in _CELL.split(line.strip().strip("|"))]


def _figure(alt: str, name: str, folder: Path) -> str:
    path = folder / Path(name).name  # a figure beside the report, never a path out of it
    if path.suffix.lower() != ".png" or not path.is_file():
        return f"<p>{_text(alt)}: figure not found</p>"
    data = base64.b64encode(path.read_bytes()).decode()
    return (f'<figure class="static" data-name="{html.escape(path.stem)}"><img alt="{html.escape(alt)}" '
            f'src="data:image/png;base64,{data}"></figure>')


def render(markdown: str, folder: Path, skip_title: bool = True) -> str:
    """``markdown`` (a report's) as HTML, its images read from ``folder``."""
    out: list[str] = []
    lines = markdown.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        heading = re.match(r"^(#{1,4}) (.*)$", line)
        image = _IMAGE.match(line.strip())
        if heading:
            level = len(heading.group(1))
            if not (skip_title and level == 1):
                out.append(f"<h{level + 1}>{inline(heading.group(2))}</h{level + 1}>")
            i += 1
        elif image:
            out.append(_figure(image.group(1), image.group(2), folder))
            i += 1
        elif line.startswith("|"):
            block = []
            while i < len(lines) and lines[i].startswith("|"):
                block.append(lines[i])
                i += 1
            out.append(_table(block))
        elif line.startswith("- "):
            items = []
            while i < len(lines) and (lines[i].startswith("- ") or lines[i].startswith("  ") and items):
                if lines[i].startswith("- "):
                    items.append(lines[i][2:])
                else:
                    items[-1] += " " + lines[i].strip()
                i += 1
            out.append("<ul>" + "".join(f"<li>{inline(item)}</li>" for item in items) + "</ul>")
        else:
            para = []
            while i < len(lines) and lines[i].strip() and not re.match(r"^(#{1,4} |\||- |!\[)", lines[i]):
                para.append(lines[i].strip())
                i += 1
            out.append(f"<p>{inline(' '.join(para))}</p>")
    return "\n".join(out)


def _table(block: list[str]) -> str:
    head, rows = _cells(block[0]), [_cells(r) for r in block[2:]]
    cells = "".join(f"<th>{inline(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="static"><thead><tr>{cells}</tr></thead><tbody>{body}</tbody></table>'
