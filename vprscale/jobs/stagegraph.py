"""A pipeline's stage graph with each stage's state, as Mermaid or Graphviz dot
(``vprscale run PIPELINE --dag``): what reads what, and what is done, stale and why, or pending."""

from __future__ import annotations

FORMATS = ("mermaid", "dot")
_FILL = {"done": "#d9ead3", "stale": "#fce5cd", "pending": "#eeeeee"}


def render(stages: list[tuple[str, str, str, str]], edges: list[tuple[str, str]], form: str) -> str:
    """The graph of ``stages`` (name, kind, state, why) and ``edges`` (from the stage read to the
    stage reading it) in ``form`` (:data:`FORMATS`); every label is text (quotes and brackets escaped)."""
    ids = {name: f"s{i}" for i, (name, *_) in enumerate(stages)}
    nodes = [(ids[name], [f"{name} ({kind})", state + (f": {why}" if why else "")], state)
             for name, kind, state, why in stages]
    pairs = [(ids[a], ids[b]) for a, b in edges if a in ids and b in ids]
    return _mermaid(nodes, pairs) if form == "mermaid" else _dot(nodes, pairs)


def _mermaid(nodes: list[tuple[str, list[str], str]], pairs: list[tuple[str, str]]) -> str:
    def text(s: str) -> str:  # Mermaid's entity codes: a label never closes its quotes or opens markup
        for raw, code in (("#", "#35;"), ('"', "#quot;"), ("<", "#lt;"), (">", "#gt;"), ("`", "#96;")):
            s = s.replace(raw, code)
        return s

    lines = ["flowchart TD"]
    lines += [f'  {i}["{"<br/>".join(text(x) for x in label)}"]:::{state}' for i, label, state in nodes]
    lines += [f"  {a} --> {b}" for a, b in pairs]
    lines += [f"  classDef {state} fill:{fill},stroke:#555" for state, fill in _FILL.items()]
    return "\n".join(lines) + "\n"


def _dot(nodes: list[tuple[str, list[str], str]], pairs: list[tuple[str, str]]) -> str:
    def text(s: str) -> str:  # a dot string: backslashes and quotes escaped, one line
        return s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ")

    newline = "\\n"  # dot's line break inside a label
    lines = ["digraph pipeline {", "  rankdir=TB;", '  node [shape=box, style="rounded,filled"];']
    lines += [f'  {i} [label="{newline.join(text(x) for x in label)}", fillcolor="{_FILL[state]}"];'
              for i, label, state in nodes]
    lines += [f"  {a} -> {b};" for a, b in pairs]
    return "\n".join(lines + ["}"]) + "\n"
