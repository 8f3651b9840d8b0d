"""Values as text, wherever they are shown: the one escaping path for each medium.

A method's name, a parameter, a noise level, a path or a command comes from a file, a flag or a
plug-in, and none of it is ever markup, code or a terminal command: in Markdown it is escaped
text, inside an HTML ``<script>`` it is JSON that cannot close the element, in a terminal its
control characters are made visible. (In the HTML page's own script, values reach the page
through ``textContent`` and an escaping function: ``report_page.js``.)
"""

from __future__ import annotations

import json
import re
from typing import Any

_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")  # C0 (but tab and newline), DEL, C1
_MARKDOWN = str.maketrans({"|": "\\|", "`": "\\`", "\n": " ", "\r": " "})
_MARKUP = re.compile(r"<(?=[A-Za-z/!?])|&(?=#?[A-Za-z0-9]+;)")  # what would start a tag or an entity
_SCRIPT = str.maketrans({"<": "\\u003c", ">": "\\u003e", "&": "\\u0026", "\u2028": "\\u2028", "\u2029": "\\u2029"})


def terminal(value: Any) -> str:
    """``value`` for a terminal: escape sequences and other control characters shown as ``\\x1b``."""
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", str(value))


def markdown(value: Any) -> str:
    """``value`` as one Markdown table cell or inline text: no HTML, no cell break, no code span.
    A ``<`` or ``&`` that would start a tag or an entity is backslash-escaped, so the text reads
    as itself in the raw Markdown too (``Babenko & Lempitsky``, not ``Babenko &amp; Lempitsky``)."""
    return _MARKUP.sub(lambda m: "\\" + m.group(), terminal(value).translate(_MARKDOWN))


def markdown_code(value: Any) -> str:
    """``value`` as a Markdown code span (shown verbatim), whatever backticks it holds."""
    text = terminal(value).replace("\n", " ")
    fence = "`" * (max((len(run) for run in re.findall(r"`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def script_json(value: Any, **dumps: Any) -> str:
    """``value`` as JSON that is safe inside an HTML ``<script>`` element, whatever its strings hold."""
    return json.dumps(value, **dumps).translate(_SCRIPT)
