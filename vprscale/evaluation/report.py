"""``vprscale report``: the paper's figures and a Markdown report from eval results.

Inputs are evaluation directories (or their ``results.parquet``); the indexes and stores
they name supply storage, occupancy and timing. Figures are written as PNG and PDF.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from vprscale.core.errors import InputError  # noqa: E402
from vprscale.core.localcopy import cache_folder, upload  # noqa: E402
from vprscale.core.manifest import write_manifest  # noqa: E402
from vprscale.core.objects import Remote  # noqa: E402
from vprscale.core.plaintext import markdown, markdown_code  # noqa: E402
from vprscale.core.provenance import provenance  # noqa: E402
from vprscale.core.publish import check_writable, exclusive, keep_beside, refuse_foreign  # noqa: E402
from vprscale.dataset.recipe import known_scales  # noqa: E402
from vprscale.evaluation import stagerecord  # noqa: E402
from vprscale.evaluation.accounting import method_ops, time_cell  # noqa: E402
from vprscale.evaluation.comparison import (  # noqa: E402
    as_run_measured,
    compare_section,
    method_family,
    report_palette,
)
from vprscale.evaluation.htmlreport import write_html
from vprscale.evaluation.ladder import ladder_section, percent
from vprscale.evaluation.metres import load_metres, metres_section  # noqa: E402
from vprscale.evaluation.nnreport import load_nn, nn_section  # noqa: E402
from vprscale.evaluation.operating import operating_section
from vprscale.evaluation.prcurves import pr_section  # noqa: E402
from vprscale.evaluation.results import eval_folder, main_noise, noise_order  # noqa: E402
from vprscale.evaluation.storage import floor_bits, index_parts  # noqa: E402
from vprscale.evaluation.taskreport import task_sections, write_task_html  # noqa: E402
from vprscale.evaluation.tasks import KS  # noqa: E402
from vprscale.method.indexmeta import checked, read_index_meta  # noqa: E402

PAPER = {"nr_L50": {"20K": 74, "1M": 57, "10M": 32}, "storage_mb": {"20K": 0.2, "1M": 8.4, "10M": 80.4},
         "ops_10M": 37_400, "baseline_ratio": 1300, "fas20K": (1, 98, 267)}
STYLE = {1: ":", 50: "--", 100: "-"}
COLOURS = {("coarsehash", "paper"): "tab:blue", ("coarsehash", "aligned"): "tab:green",
           ("coarsehash", None): "tab:blue", ("baseline", None): "tab:red"}


def _label(method: str, mode: str | None) -> str:
    return "baseline (SeqSLAM, d=1)" if method == "baseline" else f"CoarseHash {mode or 'single best'}"


def load_results(paths: list[str | Path]) -> tuple[pd.DataFrame, list[dict], list[dict], pd.DataFrame]:
    """Concatenated results, the eval summaries, the index metadata they refer to, and the rows of
    points more than one run evaluated (every such run's row: the results keep the first)."""
    frames, evals, indexes = [], [], {}
    kinds: dict[bool, Path] = {}  # an evaluation of MSLS's tasks (True) or of the frame grid, by its folder
    for p in paths:
        f = eval_folder(p) / "results.parquet"
        try:
            df = pd.read_parquet(f)
        except (OSError, ValueError) as exc:  # pyarrow's errors for a truncated or foreign file
            raise InputError(f"{f}: not a readable Parquet file ({str(exc).splitlines()[0]})") from None
        task = "task" in df.columns
        kinds.setdefault(task, f.parent)
        if len(kinds) > 1:
            raise InputError(f"{kinds[True]}: an evaluation of MSLS's tasks, reported with {kinds[False]}, one of "
                             "the frame grid: a report draws one or the other; give them to two reports")
        need = {"task", "method", "mode", "part", *(f"recall_at_{k}" for k in KS)} if task else {
            "scale", "noise", "method", "mode", "L", "d", "part", "radius", "recall"}
        missing = need - set(df.columns)
        if missing:
            raise InputError(f"{f}: not a vprscale results file (no column {', '.join(sorted(missing))})")
        frames.append(df.assign(run=str(f.parent.resolve())))
        named = [] if task else [str(x) for x in df["index"].dropna().unique()]
        # each summary tied to the indexes its results name (absolute paths)
        evals.append({**json.loads((f.parent / "eval.json").read_text()),
                      "_indexes": named, "_run": str(f.parent.resolve())})
        for idx in named:
            if (Path(idx) / "index.json").is_file():  # an index moved or removed since is left out
                path = Path(idx)
                indexes[idx] = {**checked(path, read_index_meta(path)), "path": idx}
    res = pd.concat(frames, ignore_index=True)
    if True in kinds:
        return res, evals, [], res.iloc[:0]
    # A d sweep re-evaluates the main index width too, and a scale's evaluations split across parts
    # each evaluate CoarseHash: keep one row per key, and each run's rows of those points apart, for
    # setting times of one run against each other. (Operating points of one method differ in their
    # params: each is kept.)
    key = ["scale", "noise", "method", "mode", "L", "d", "K", "part", "radius",
           *(["params"] if "params" in res.columns else [])]
    twins = res[res.duplicated(subset=key, keep=False)].reset_index(drop=True)
    res = res.drop_duplicates(subset=key, keep="first").reset_index(drop=True)
    return res, evals, list(indexes.values()), twins


def _scale_order(res: pd.DataFrame, indexes: list[dict]) -> list[str]:
    n = {i["store"]["scale"]: i["n_ref"] for i in indexes}
    return sorted(res["scale"].unique(), key=lambda s: n.get(s, math.inf))


def _main_d(res: pd.DataFrame, scale: str, indexes: list[dict]) -> int:
    """The index width of the main grid of a scale: ⌈log2 N_ref⌉ when present, else the most used."""
    sub = res[(res.scale == scale) & (res.method == "coarsehash")]
    ds = sub["d"].value_counts()
    n = next((i["n_ref"] for i in indexes if i["store"]["scale"] == scale), None)
    default = math.ceil(math.log2(n)) if n else None
    return default if default in ds.index else int(ds.index[0])


def _save(fig, out: Path, name: str, figures: list[str]) -> None:
    for ext, meta in (("png", {}), ("pdf", {"CreationDate": None})):  # no timestamp: same data, same file
        fig.savefig(out / f"{name}.{ext}", dpi=130, bbox_inches="tight", metadata=meta)
        figures.append(str(out / f"{name}.{ext}"))
    plt.close(fig)


def _main_rows(res: pd.DataFrame, scale: str, d: int) -> pd.DataFrame:
    sub = res[(res.scale == scale) & (res.part == "all")]
    return sub[(sub.method == "baseline") | (sub.d == d)]


def fig_recall(res, scales, mains, out, figures) -> None:
    noises = noise_order(res.noise)
    fig, axes = plt.subplots(len(noises), len(scales), figsize=(4.2 * len(scales), 3.4 * len(noises)),
                             squeeze=False, sharey=True, layout="constrained")
    for r, noise in enumerate(noises):
        for c, scale in enumerate(scales):
            ax = axes[r][c]
            sub = _main_rows(res, scale, mains[scale])
            sub = sub[sub.noise == noise]
            for (method, mode, L), g in sub.groupby(["method", "mode", "L"], dropna=False):
                mode = None if pd.isna(mode) else mode
                g = g.sort_values("radius")
                ax.plot(g.radius, 100 * g.recall, STYLE.get(L, "-."), color=COLOURS[(method, mode)],
                        label=f"{_label(method, mode)}, L={L}")
            ax.set_title(f"{scale}, {noise.upper()} (d={mains[scale]})")
            ax.set_xlabel("localisation radius (frames)")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            if c == 0:
                ax.set_ylabel("recall (%)")
            ax.set_ylim(0, 100)
            ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle("Recall vs radius: CoarseHash vs baseline (paper Fig. 3)")
    _save(fig, out, "fig3_recall", figures)


def fig_dsweep(res, out, figures) -> bool:
    sub = res[(res.method == "coarsehash") & (res.part == "all") & (res.radius == 20) & (res.noise == main_noise(res))]
    swept = [s for s, g in sub.groupby("scale") if g["d"].nunique() > 1]
    if not swept:
        return False
    scale = swept[0]
    sub = sub[sub.scale == scale]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6), layout="constrained")
    for (mode, L), g in sub.groupby(["mode", "L"], dropna=False):
        mode = None if pd.isna(mode) else mode
        g = g.sort_values("d")
        a1.plot(g.d, 100 * g.recall, STYLE.get(L, "-.") + "o", color=COLOURS[("coarsehash", mode)],
                label=f"{_label('coarsehash', mode)}, L={L}")
        a2.plot(g.d, g.nr_mean, STYLE.get(L, "-.") + "o", color=COLOURS[("coarsehash", mode)],
                label=f"{_label('coarsehash', mode)}, L={L}")
    base = res[(res.method == "baseline") & (res.scale == scale) & (res.part == "all") & (res.radius == 20)
               & (res.noise == main_noise(res))]
    for L, g in base.groupby("L"):
        a1.axhline(100 * g.recall.mean(), color="tab:red", ls=STYLE.get(L, "-."), label=f"baseline, L={L}")
    a1.set(xlabel="hash length d (bits)", ylabel="recall within 20 frames (%)",
           title=f"{scale}, {main_noise(res).upper()}: recall vs d")
    a2.set(xlabel="hash length d (bits)", ylabel="mean candidates N_r", yscale="log", title="N_r vs d")
    for a in (a1, a2):
        a.grid(alpha=0.3)
    a1.legend(fontsize=7)
    fig.suptitle("Shorter codes → longer lists, still good recall (paper Fig. 4a)")
    _save(fig, out, "fig4a_dsweep", figures)
    return True


def fig_single(res, scales, mains, out, figures) -> None:
    fig, ax = plt.subplots(figsize=(5.5, 3.8), layout="constrained")
    for i, scale in enumerate(scales):
        g = res[(res.scale == scale) & (res.method == "coarsehash") & (res.L == 1) & (res.d == mains[scale])
                & (res.part == "all") & (res.noise == main_noise(res))].sort_values("radius")
        colour = f"C{i}"
        ax.plot(g.radius, 100 * g.recall, "-", color=colour, label=f"{scale}: selected best")
        ax.plot(g.radius, 100 * g.recall_in_list, "--", color=colour, label=f"{scale}: anywhere in list")
    ax.set(xlabel="localisation radius (frames)", ylabel="recall (%)",
           title=f"Single frame: best match vs in-list bound, {main_noise(res).upper()} (paper Fig. 4b)")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, out, "fig4b_single_frame", figures)


def fig_storage(indexes, out, figures) -> bool:
    """Fig. 4c, where an index of K = 2 was evaluated; whether it was drawn."""
    rows = sorted({(i["n_ref"], i["d"]): i for i in indexes if i["k"] == 2}.values(), key=lambda i: i["n_ref"])
    if not rows:
        return False
    fig, ax = plt.subplots(figsize=(5.5, 3.8), layout="constrained")
    names = {"P1": "P1 ref→address map", "P2": "P2 centres", "P3": "P3 PCA matrix", "P4": "P4 mean"}
    by_n: dict[int, dict] = {}
    for i in rows:  # one point per N_ref: its default-width index
        if i["n_ref"] not in by_n or i["d"] == math.ceil(math.log2(i["n_ref"])):
            by_n[i["n_ref"]] = i
    n = np.array(sorted(by_n))
    for k, (part, label) in enumerate(names.items()):
        ax.plot(n, [by_n[x]["storage"][part]["paper"] for x in n], "o-", color=f"C{k}", label=f"{label} (8 B)")
        ax.plot(n, [by_n[x]["storage"][part]["disk"] for x in n], "s:", color=f"C{k}", label=f"{label} on disk")
    lists = [x for x in n if "lists" in by_n[x]]  # the paper leaves the inverted lists out; they cost the most
    if lists:
        ax.plot(lists, [by_n[x]["lists"]["bytes"] for x in lists], "D-", color="C4",
                label="inverted lists (ids, buckets) on disk")
        tables = [(x, _sql_table_bytes(by_n[x])) for x in lists]
        tables = [(x, b) for x, b in tables if b]
        if tables:
            ax.plot(*zip(*tables, strict=True), "D:", color="C5", label="SQL tables of the lists on disk")
    whole = [x for x in n if "parts" in by_n[x]]
    if whole:  # every file of the index, measured, against the floor of d + ⌈log2 N⌉ bits a place
        ax.plot(whole, [sum(by_n[x]["parts"].values()) for x in whole], "^-", color="C6", label="whole index on disk")
        ax.plot(whole, [x * floor_bits(x, by_n[x]["d"], by_n[x]["k"]) / 8 for x in whole], "_--", color="C7", ms=12,
                label="floor: d + ⌈log2 N⌉ bits a place")
    ax.set(xscale="log", yscale="log", xlabel="reference places N_ref", ylabel="bytes",
           title="Storage growth (paper Fig. 4c, with the lists)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))  # beside the data, not over it
    _save(fig, out, "fig4c_storage", figures)
    return True


def _sql_table_bytes(index: dict) -> int:
    """Bytes of the tables an index keeps for the SQL console beside its lists: none from format 4
    on (its lists are Parquet tables), measured when it was written (format 3), else from its
    folder (format 2's Parquet copies; 0 when the folder is gone)."""
    if index.get("format", 0) >= 4:
        return 0
    if "parts" in index:
        return index["parts"]["SQL tables"]
    path = Path(index.get("path", ""))
    return sum((path / f).stat().st_size for f in ("lists.parquet", "buckets.parquet") if (path / f).is_file())


def fig_balance(indexes, out, figures) -> bool:
    smallest = min((i["n_ref"] for i in indexes), default=None)
    pair = [i for i in indexes if i["n_ref"] == smallest and i["k"] == 2]
    if not pair:
        return False
    fig, ax = plt.subplots(figsize=(5.5, 4.5), layout="constrained")
    for i in sorted(pair, key=lambda i: not i["store"].get("rescale", True)):
        comp = pd.read_parquet(Path(i["path"]) / "components.parquet")
        c0 = comp[comp.cluster == 0].sort_values("component")
        rescaled = i["store"].get("rescale", True)
        ax.barh(c0.component + (-0.2 if rescaled else 0.2), c0.share - 0.5, left=0.5, height=0.4,
                color="tab:blue" if rescaled else "tab:orange",
                label=f"{'with' if rescaled else 'without'} variance rescaling (d={i['d']})")
    ax.axvline(0.5, color="k", ls="--", lw=0.8)
    ax.invert_yaxis()
    ax.set(xlabel="share of references in cluster 1 (left of 0.5) vs cluster 2", ylabel="principal component",
           xlim=(0, 1), title=f"Cluster balance per component, {pair[0]['store']['scale']} (paper Fig. 4d)")
    ax.legend(fontsize=8)
    _save(fig, out, "fig4d_balance", figures)
    return True


def _family(rows: pd.DataFrame, method: str) -> str:
    """The family the rows of one method carry (derived from its name for results older than the column)."""
    return str(rows.family.iloc[0]) if "family" in rows.columns else method_family(method)


def _ratio(x: float) -> str:
    return f"{x:,.0f}×" if x >= 10 else f"{x:.2f}×"


def _num(x: Any, fmt: str) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _whole_index_bytes(meta: dict) -> int | None:
    """Every file of the index directory, measured as ``vprscale index`` measures it (its
    metadata included); the parts recorded at indexing time where the directory is gone."""
    path = Path(meta.get("path", ""))
    if (path / "index.json").is_file() and not (path / KEPT_SIZES).is_file():
        return sum(index_parts(path).values())
    return sum(meta["parts"].values()) if "parts" in meta else _kept_bytes(path)


def _provenance_block(evals: list[dict], record: dict[str, Any] | None = None) -> list[str]:
    """Who made this report and the results in it: commits, machines, commands; mixed commits said so,
    or, for a pipeline's report, the code state stage by stage (:mod:`vprscale.evaluation.stagerecord`)."""
    me = provenance()
    if record is None:
        drawn = (f"- report: vprscale {me['vprscale']}, commit {_commit(me)}, {me['time']}, on {me['cpu']} "
                 f"({me['cores']} cores), {markdown_code(_here(me['command']))}")
    else:  # drawn from a pipeline's results, as its parts kept them: the same bytes wherever it is drawn
        drawn = (f"- report: vprscale {me['vprscale']}, drawn from the stages of pipeline "
                 f"{markdown(record['pipeline'])} below (when, where and at which commit it was drawn: the "
                 "pipeline's run summary)")
    lines = ["## Provenance", "", drawn]
    commits = set()
    for e in evals:
        rec = e.get("provenance")
        if not rec:
            lines.append(f"- results {markdown(_here(e['_run']))}: no provenance recorded (written by a vprscale "
                         "before 0.3)")
            commits.add("unknown")
            continue
        commits.add(_commit(rec))
        lines.append(f"- results {markdown(_here(e['_run']))}: vprscale {rec['vprscale']}, commit {_commit(rec)}, "
                     f"{rec['time']}, {rec['cpu']} ({rec['cores']} cores, "
                     f"load {', '.join(map(str, rec['load_average']))} at start), "
                     f"{markdown_code(_here(rec['command']))}")
    if record is not None:  # what makes a pipeline's results one state is each stage's code, not one commit
        return [*lines, *stagerecord.provenance_lines(record, _md_table)]
    if len(commits) > 1:
        lines.append(f"- **These results come from {len(commits)} different commits** "
                     f"({', '.join(sorted(commits))}); figures from different commits are not one run.")
    return [*lines, ""]


def _here(text: str) -> str:
    """``text`` (a command, a path) with this working directory's and home's absolute paths shown
    relative (``data/…``, ``~/…``): a report is read, and committed, on other machines. The
    evaluations' own records keep the absolute paths."""
    text = str(text)
    for folder, shown in ((Path.cwd(), ""), (Path.home(), "~/")):
        text = text.replace(f"{folder}/", shown)
    return text


def _commit(rec: dict) -> str:
    if not rec.get("commit"):
        return "unknown (not a git checkout)"
    return rec["commit"][:12] + (" (dirty tree)" if rec.get("dirty") else "")


def _md_table(header: list[str], rows: list[list[Any]]) -> str:
    """A Markdown table; every cell is text (a method's name is never markup: core/plaintext)."""
    lines = ["| " + " | ".join(map(markdown, header)) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(map(markdown, r)) + " |" for r in rows]
    return "\n".join(lines)


def _store_label(store: dict[str, Any]) -> str:
    """A store's scale, and "(no rescale)" for a recipe's store built without the variance
    rescaling (your own data is never rescaled, and says nothing of it)."""
    return store["scale"] + (" (no rescale)" if store.get("rescale") is False else "")


REPORT_TITLE = "# vprscale report"


def _check_replaceable(out: Path, force: bool) -> None:
    """A folder with files may be replaced only when it holds a report vprscale wrote, and only with
    ``force``: a report is a product people link to, and one command must not silently redraw it."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, not a directory")
    if not out.is_dir() or not any(p.name != stagerecord.PARTS for p in out.iterdir()):  # or only what parts kept
        return
    md = out / "report.md"
    try:
        ours = md.is_file() and md.read_text(errors="replace").startswith(REPORT_TITLE)
    except OSError:
        ours = False
    if not ours:
        raise InputError(f"--out {out}: holds files that are not a vprscale report; give an empty or new folder")
    if not force:
        raise InputError(f"--out {out}: already holds a report; --force replaces it and keeps it beside, in "
                         f"{out.name}.previous/")


def write_report(results: list[str | Path], out: Path | Remote, extra_indexes: list[str] | None = None,
                 force: bool = False, stages: str | Path | None = None) -> dict[str, Any]:
    """Write the figures and ``report.md`` into ``out``; returns their paths. ``stages``: the stage
    record of the pipeline the results come from (its code state and time table, kept as ``stages.json``).

    The report is drawn in a hidden folder beside ``out`` and renamed into place when whole, so
    ``out`` never holds half a report; an existing report is replaced only with ``force``, and is
    then kept beside as ``<out>.previous``. On object storage it is drawn in the cache and
    uploaded with a manifest, written last, as every output there is.
    """
    record = None if stages is None else stagerecord.read_record(stages)  # before any work: a bad one is refused
    if isinstance(out, Remote):
        return _write_remote(results, out, extra_indexes, force, record)
    return _write_local(results, Path(out), extra_indexes, force, record)


def _write_local(results: list[str | Path], out: Path, extra_indexes: list[str] | None, force: bool,
                 record: dict[str, Any] | None) -> dict[str, Any]:
    check_writable(out.parent)  # before any work: the report is drawn beside out and renamed into place
    with exclusive(out):
        _check_replaceable(out, force)
        work = out.with_name(f".{out.name}.partial")
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        try:
            rep = _draw(results, work, extra_indexes, record)
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            raise
        if (out / stagerecord.PARTS).is_dir():  # what a pipeline's parts kept stays with its report
            (out / stagerecord.PARTS).rename(work / stagerecord.PARTS)
        if out.exists() and any(out.iterdir()):
            keep_beside(out)
        elif out.exists():
            out.rmdir()
        work.rename(out)
    return {"report": str(out / "report.md"), "figures": [str(out / Path(f).name) for f in rep["figures"]]}


def _write_remote(results: list[str | Path], out: Remote, extra_indexes: list[str] | None,
                  force: bool, record: dict[str, Any] | None) -> dict[str, Any]:
    check_writable(out.parent)
    refuse_foreign(out)  # before the drawing: what is there is replaced only if vprscale wrote it
    if (out / "report.md").exists() and not force:
        raise InputError(f"--out {out}: holds a report; --force replaces it (the old one is kept beside, as "
                         f"{out.name}.previous)")
    local = cache_folder(out, fresh=True)
    rep = _write_local(results, local, extra_indexes, False, record)
    write_manifest(local)
    upload(local, out, keep=True)
    return {"report": str(out / "report.md"), "figures": [str(out / Path(f).name) for f in rep["figures"]]}


def _draw(results: list[str | Path], out: Path, extra_indexes: list[str] | None,
          record: dict[str, Any] | None) -> dict[str, Any]:
    res, evals, indexes, twins = load_results(results)
    if "task" in res.columns:
        return _draw_tasks(res, evals, out, record)
    for p in extra_indexes or []:
        from vprscale.method.indexfile import load_index_meta

        meta = load_index_meta(p)
        if not any(i["path"] == str(p) for i in indexes):
            indexes.append({**meta, "path": str(p)})
    out.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    scales = _scale_order(res, indexes)
    mains = {s: _main_d(res, s, indexes) for s in scales}
    fig_recall(res, scales, mains, out, figures)
    has_sweep = fig_dsweep(res, out, figures)
    fig_single(res, scales, mains, out, figures)
    has_storage = fig_storage([i for i in indexes if i["store"].get("rescale") is not False], out, figures)
    has_balance = fig_balance(indexes, out, figures)
    save = lambda fig, o, name: _save(fig, o, name, figures)  # noqa: E731
    runs = list(dict.fromkeys(res.run))
    nn = load_nn(runs)
    # one colour per method for every figure of the report, whichever of them each draws
    palette = report_palette([*res.method, *(nn.method if len(nn) else [])])
    compared = compare_section(res, scales, out, save, _md_table, palette, twins)
    compared += operating_section(res, scales, _md_table)
    compared += pr_section(res, runs, scales, out, save, _md_table, palette)
    metres = load_metres(runs)
    compared += metres_section(metres, scales, _md_table)
    compared += nn_section(nn, scales, out, save, _md_table, palette)
    text = _markdown(res, evals, indexes, scales, mains, has_sweep, has_storage, has_balance, compared, record,
                     twins)
    (out / "report.md").write_text(text)
    write_html(res, metres, _provenance_block(evals, record), REPORT_TITLE.removeprefix("# "), out, text,
               palette)
    if record is not None:
        stagerecord.write_record(out / stagerecord.FILE, record["pipeline"], record["stages"],
                                 record.get("one_code_state"), record.get("parts"))
    small = res[res.radius.isin([0, 5, 10, 20])].drop(columns=["store", "index"], errors="ignore")
    if "run" in small.columns:  # as the provenance block shows them: relative to here
        small = small.assign(run=small["run"].map(_here))
    small.to_csv(out / "recall_table.csv", index=False)
    return {"report": str(out / "report.md"), "figures": figures}


def _draw_tasks(res: pd.DataFrame, evals: list[dict], out: Path, record: dict[str, Any] | None) -> dict[str, Any]:
    """The report of MSLS's tasks (:mod:`vprscale.evaluation.taskreport`): its figure, ``report.md``,
    ``report.html`` and the table of every row it shows, ``task_table.csv``."""
    out.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    save = lambda fig, o, name: _save(fig, o, name, figures)  # noqa: E731
    palette = report_palette(res.method)
    md = [REPORT_TITLE, "", "Generated by `vprscale report` from evaluations of MSLS's tasks.", "",
          *_provenance_block(evals, record), *task_sections(res, out, save, _md_table, palette)]
    text = "\n".join(md)
    (out / "report.md").write_text(text)
    write_task_html(res, _provenance_block(evals, record), REPORT_TITLE.removeprefix("# "), out, text, palette)
    if record is not None:
        stagerecord.write_record(out / stagerecord.FILE, record["pipeline"], record["stages"],
                                 record.get("one_code_state"), record.get("parts"))
    shown = res.drop(columns=["store"], errors="ignore").assign(run=res["run"].map(_here))
    shown.to_csv(out / "task_table.csv", index=False)
    return {"report": str(out / "report.md"), "figures": figures}


def _markdown(res, evals, indexes, scales, mains, has_sweep, has_storage, has_balance, compared: list[str],
              record: dict[str, Any] | None, twins: pd.DataFrame | None = None) -> str:
    md = [REPORT_TITLE, "",
          "Generated by `vprscale report` from evaluation results. Scales: " + ", ".join(
              f"{s} (d = {mains[s]})" for s in scales) + ".", "", *_provenance_block(evals, record)]
    md += ladder_section(res, indexes, scales, mains, _whole_index_bytes, _md_table)
    md += ["## Figures", "", "![Fig. 3](fig3_recall.png)", ""]
    if has_sweep:
        md += ["![Fig. 4a](fig4a_dsweep.png)", ""]
    md += ["![Fig. 4b](fig4b_single_frame.png)", ""] + (["![Fig. 4c](fig4c_storage.png)", ""] if has_storage else [])
    if has_balance:
        md += ["![Fig. 4d](fig4d_balance.png)", ""]
    rows = []
    for scale in scales:
        sub = _main_rows(res, scale, mains[scale])
        for (noise, method, mode, L), g in sub.groupby(["noise", "method", "mode", "L"], dropna=False):
            r = g.set_index("radius")["recall"]
            mode = None if pd.isna(mode) else mode
            rows.append([scale, noise.upper(), L, _label(method, mode), _family(g, method), int(g.n_queries.iloc[0]),
                         *(percent(r.get(x)) for x in (0, 5, 10, 20))])
    md += ["## Recall (%) at radii 0 / 5 / 10 / 20 frames (all queries)", "",
           _md_table(["scale", "noise", "L", "method", "family", "queries", "≤0 frames", "≤5 frames", "≤10 frames",
                      "≤20 frames"], rows), ""]
    md += _stratification_note(res, scales)
    rows = []
    named = {"deep1b": "Deep1B", "fas": "FAS"}
    shown = [p for p in ("deep1b", "fas") if p in set(res.part)] + sorted(set(res.part) - {"all", "deep1b", "fas"})
    for scale in scales:
        sub = res[(res.scale == scale) & (res.radius == 20) & (res.L > 1) & (res.d == mains[scale])
                  & (res.method == "coarsehash")]
        for (noise, mode, L), g in sub.groupby(["noise", "mode", "L"]):
            parts = g.set_index("part")
            rows.append([scale, noise.upper(), L, mode, *(percent(parts.recall.get(p)) for p in ("all", *shown)),
                         f"{parts.nr_mean.get('all'):.1f}", f"{parts.nr_median.get('all'):.0f}",
                         f"{parts.nr_p95.get('all'):.0f}"])
    title = "Per part, and candidate counts N_r" if shown else "Candidate counts N_r"
    md += [f"## {title} (recall within 20 frames, %)", "",
           _md_table(["scale", "noise", "L", "mode", "all", *(named.get(p, p) for p in shown), "N_r mean",
                      "N_r median", "N_r p95"], rows), ""]
    rows = []
    for scale in scales:
        sub = _main_rows(res, scale, mains[scale])
        sub = sub[(sub.radius == 0) & (sub.noise == main_noise(res))]
        for L, g in sub.groupby("L"):
            m = g[(g.method == "coarsehash") & (g["mode"].isna() | (g["mode"] == "paper"))]
            b = g[g.method == "baseline"]
            if m.empty or b.empty:
                continue
            b = b.iloc[0]
            m = as_run_measured(m.iloc[0], b.get("run"), twins, radius=0)  # the baseline's run's time, if it has one
            frame = m.get("us_per_frame")
            same_run = m.get("run") == b.get("run")
            rows.append([scale, L, f"{m.ops_per_query:,.0f}", f"{b.ops_per_query:,.0f}",
                         _ratio(b.ops_per_query / m.ops_per_query), time_cell(m),
                         "" if frame is None or frame != frame else f"{frame:.2f}", time_cell(b),
                         _ratio(b.us_per_query / max(m.us_per_query, 1e-9)) if same_run else "(different runs)"])
    if rows:  # an evaluation without the baseline (--no-baseline) has nothing to set CoarseHash against here
        md += [f"## Compute per query: CoarseHash (paper mode) vs baseline, {main_noise(res).upper()}", "",
               "Operations by the formulas of docs/accounting.md. Times are µs per query per core: the CPU time of "
               "one thread running the method, the median of the repeats with their range, including the per-frame "
               "work of one new frame (hash, nearest occupied address, list retrieval) as in online use; the column "
               "beside gives that per-frame part. Ratios are of medians measured in the same run.", "",
               _md_table(["scale", "L", "ops method", "ops baseline", "ops ratio", "µs method", "of which per frame",
                          "µs baseline", "time ratio"], rows), ""]
    rows = []
    for i in sorted(indexes, key=lambda i: (i["n_ref"], i["d"])):
        st = i["storage"]
        lists = i.get("lists", {}).get("bytes_per_place")
        whole = _whole_index_bytes(i)
        whole = whole / i["n_ref"] if whole else None
        floor = floor_bits(i["n_ref"], i["d"], i["k"]) / 8
        rows.append([_store_label(i["store"]), i["d"],
                     f"{i['n_ref']:,}", *(f"{st[p]['paper'] / 1e6:.3f}" for p in ("P1", "P2", "P3", "P4", "total")),
                     f"{st['total']['packed'] / 1e6:.3f}", f"{st['total']['disk'] / 1e6:.3f}", _num(lists, ".2f"),
                     _num(_sql_table_bytes(i) / i["n_ref"] or None, ".2f"), _num(whole, ".2f"), f"{floor:.2f}",
                     _num(whole and whole / floor, ".2f"), i["store"].get("layout", "full")])
    md += ["## Storage (MB)", "",
           "P1–P4 counted the paper's way (8 bytes a number), packed (⌈d·log2 K⌉ bits an address, float32 "
           "model) and as the index directory holds them; the inverted lists (`lists.parquet` and "
           "`buckets.parquet`) are counted apart, in bytes per place (indexes of formats 2 and 3 kept separate "
           "copies for the SQL console, counted in their own column); the whole index "
           "(every file, measured) is set against the floor of d + ⌈log2 N⌉ bits a place (docs/method.md, "
           "\"Storage\"; indexes of format 2 have no whole-index figure). A compact store "
           "keeps 12 bytes per place (address, quantisation error, baseline value) and the evaluated query "
           "windows; a full one 1.15 KB per place.", "",
           _md_table(["scale", "d", "N_ref", "P1", "P2", "P3", "P4", "total (8 B)", "total packed", "on disk",
                      "lists B/place", "SQL tables B/place", "whole index B/place", "floor B/place", "× floor",
                      "store layout"], rows),
           ""]
    rows = []
    for i in sorted(indexes, key=lambda i: (i["n_ref"], i["d"])):
        built = i["store"].get("built", {})
        ev = next((e for e in evals if i["path"] in e["_indexes"]), {})
        gib = 2**30
        rows.append([_store_label(i["store"]), i["d"],
                     _num(built.get("wall_s"), ".1f"), _num(built.get("peak_rss_bytes", math.nan) / gib, ".2f"),
                     _num(i["wall_s"], ".1f"), _num(i["peak_rss_bytes"] / gib, ".2f"), _num(ev.get("wall_s"), ".1f"),
                     _num(ev.get("peak_rss_bytes", math.nan) / gib, ".2f"),
                     _num(_disk(i["store"].get("path", "")) / gib, ".2f"), _num(_disk(i.get("path", "")) / gib, ".2f")])
    md += compared
    if record is not None:  # the pipeline's own record: every stage, its time over every call it took
        md += stagerecord.time_table(record, _md_table)
    else:
        md += ["## Time (s), peak memory (GiB) and disk (GiB) per stage", "",
               _md_table(["scale", "d", "build s", "build GiB", "index s", "index GiB", "eval s", "eval GiB",
                          "store on disk", "index on disk"], rows), ""]
    if set(scales) & set(known_scales()):  # a store of your own data has no paper figure to stand beside
        md += ["## The paper's text figures beside ours", "", *_paper_comparison(res, indexes, scales, mains), ""]
    return "\n".join(md)


def _disk(path: str | Path) -> float:
    """Bytes under a directory (NaN where it is not on this machine): of a kept copy of an index
    (what a pipeline's part keeps), the bytes its files had."""
    p = Path(path)
    if not path or not p.is_dir():
        return math.nan
    kept = _kept_bytes(p)
    return float(kept if kept is not None else sum(f.stat().st_size for f in p.rglob("*") if f.is_file()))


KEPT_SIZES = "files.json"  # in a kept copy of an index: the bytes of each of its files (vprscale.jobs.parts)


def _kept_bytes(path: Path) -> int | None:
    """The bytes a kept copy of an index records for its files (None: not a kept copy)."""
    try:
        return int(sum(json.loads((path / KEPT_SIZES).read_text()).values()))
    except (OSError, ValueError, TypeError, AttributeError):
        return None


def _stratification_note(res: pd.DataFrame, scales: list[str]) -> list[str]:
    """Which scales sampled the FAS part with a stride of its own, and what "all" then means."""
    if "fas_stride" not in res.columns:
        return []
    strided = res[res.fas_stride.notna() & (res.part == "fas") & (res.radius == 0) & (res.method == "coarsehash")]
    if strided.empty:
        return []
    said = []
    for scale in scales:
        g = strided[strided.scale == scale]
        if not g.empty:
            said.append(f"{scale} (a FAS stride of {int(g.fas_stride.iloc[0]):,} frames, "
                        f"{int(g.n_queries.min()):,}–{int(g.n_queries.max()):,} FAS queries)")
    base = res[(res.method == "baseline") & (res.part == "all") & (res.radius == 0)]
    note = ["Stratified centres: at " + ", ".join(said) + " the common stride leaves fewer than 200 FAS "
            "centres, so the FAS part is sampled with its own stride; the overall (\"all\") recall of those "
            "scales weights each part's recall by its share of the query rows, while the queries column counts "
            "both parts."]
    for scale in scales:
        m = res[(res.scale == scale) & (res.method == "coarsehash") & (res.part == "all") & (res.radius == 0)]
        b = base[base.scale == scale]
        if not b.empty and not m.empty and b.n_queries.max() < m.n_queries.min():
            note.append(f"At {scale} the baseline localises an evenly spaced sample of {int(b.n_queries.max())} "
                        "centres per run (each of its queries scans every place).")
    return [" ".join(note), ""]


def _paper_comparison(res, indexes, scales, mains) -> list[str]:
    lines = ["| figure | paper | ours | note |", "|---|---|---|---|"]
    for scale in scales:
        g = res[(res.scale == scale) & (res.method == "coarsehash") & (res["mode"] == "paper") & (res.L == 50)
                & (res.d == mains[scale]) & (res.part == "all") & (res.radius == 0) & (res.noise == main_noise(res))]
        if not g.empty:
            lines.append(f"| N_r, L = 50, {scale} | {PAPER['nr_L50'].get(scale, '–')} | {g.nr_mean.iloc[0]:.1f} | "
                         f"paper mode, {main_noise(res).upper()} |")
    formula = method_ops(96, 24, 2, 50, 32, 1, 0.0)["sequence_matching"]
    lines.append(f"| sequence-matching operations, d = 24, L = 50, N_r = 32 | {PAPER['ops_10M']:,} | "
                 f"{formula:,.0f} | by the formula L·N_r·(d/64 + d − 1) |")
    for scale in scales:
        g = res[(res.scale == scale) & (res.L == 100) & (res.d == mains[scale]) & (res.part == "all")
                & (res.radius == 20) & (res.method == "coarsehash") & (res["mode"] == "paper")]
        if scale == "10M" and not g.empty:
            lines.append("| recall, L = 100, 10M | over 50 % | "
                         + ", ".join(f"{n.upper()} {100 * r:.1f} %" for n, r in zip(g.noise, g.recall, strict=True))
                         + " | within 20 frames, paper mode |")
    for scale in scales:
        sub = _main_rows(res, scale, mains[scale])
        sub = sub[(sub.radius == 0) & (sub.noise == main_noise(res)) & (sub.L == 50)]
        m = sub[(sub.method == "coarsehash") & (sub["mode"] == "paper")]
        b = sub[sub.method == "baseline"]
        if not m.empty and not b.empty:
            lines.append(f"| baseline / method operations, {scale}, L = 50 | ≈ {PAPER['baseline_ratio']}× (10M) | "
                         f"{_ratio(b.ops_per_query.iloc[0] / m.ops_per_query.iloc[0])} | docs/accounting.md formulas |")
    if "20K" in scales:
        sub = res[(res.scale == "20K") & (res.part == "fas") & (res.radius == 20) & (res.noise == main_noise(res))
                  & (res.L == 50)]
        m = sub[(sub.method == "coarsehash") & (sub["mode"] == "paper") & (sub.d == mains["20K"])]
        b = sub[sub.method == "baseline"]
        if not m.empty and not b.empty:
            n = int(m.n_queries.iloc[0])
            lines.append(f"| FAS part of 20K within 100 m: baseline / method | 1 / 98 of 267 | "
                         f"{round(b.recall.iloc[0] * n)} / {round(m.recall.iloc[0] * n)} of {n} | "
                         f"L = 50, {main_noise(res).upper()}, paper mode |")
    for i in indexes:
        s = i["store"]["scale"]
        if s in PAPER["storage_mb"] and i["d"] == mains.get(s) and i["store"].get("rescale", True):
            total = i["storage"]["total"]
            lines.append(f"| storage, {s} | {PAPER['storage_mb'][s]} MB | {total['paper'] / 1e6:.1f} MB "
                         f"(packed {total['packed'] / 1e6:.2f} MB) | counted the paper's way |")
    lines += ["", _sources_note(indexes) + " The operation counts and the paper-way storage follow from d, L, "
              "N_r and N_ref alone and agree where those agree."]
    return lines


def _sources_note(indexes) -> str:
    """What the evaluated stores were built from, as their build records say, and what that means
    for the comparison with the paper's figures."""
    kinds = set()
    for i in indexes:
        sources = (((i["store"].get("built") or {}).get("provenance") or {}).get("inputs") or {}).get("sources")
        if not isinstance(sources, dict):
            kinds.add("unrecorded")
        elif "deep1b" not in sources:
            kinds.add("own")
        else:
            kinds.add("synthetic" if "synthetic" in json.dumps(sources) else "real")
    if kinds == {"real"}:
        return ("These datasets are built from the Deep1B and FAS100K files their stores' build records name; "
                "where the recipe, d and the sources are the paper's, recall and N_r are comparable.")
    if kinds == {"synthetic"}:
        return ("These datasets are built from the synthetic stand-ins of Deep1B and FAS100K (the default; "
                "`vprscale fetch` downloads the real sets, docs/dataset.md), so recall and N_r differ from the "
                "paper's.")
    return ("These results are not all of the paper's datasets (own descriptors, synthetic stand-ins or unrecorded "
            "sources), so recall and N_r are not the paper's to compare.")
