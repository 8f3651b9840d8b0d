"""One or two worked examples per command, shown at the end of its ``--help``: the paths are the
ones the README's quickstart leaves behind (``data/quickstart``)."""

from __future__ import annotations

from pathlib import Path

Q = "data/quickstart"
INDEX = f"{Q}/20K-d15-k2.index"

EXAMPLES: dict[str, list[tuple[str, str]]] = {
    "fetch": [("vprscale fetch deep1b --rows 10M --out sources",
               "the first 10M rows of Deep1B's base.1B.fbin (3.8 GB), by ranges, resumable: base.10M.fbin"),
              ("vprscale fetch fas100k --url URL --out sources", "FAS100K's NetVLAD .npz (its link: docs/dataset.md)"),
              ("vprscale fetch bigann --rows 10M --out sources",
               "another corpus: the first 10M rows of BIGANN's base.1B.u8bin (1.28 GB): bigann.base.10M.u8bin")],
    "synth": [("vprscale synth --out sources --deep1b-rows 100000 --fas-dim 512",
               "synthetic Deep1B (fvecs, fbin) and FAS100K (npz) files in the real layouts")],
    "build": [("vprscale build --scale 20K --out data", "the 20K dataset from the embedded synthetic sources"),
              ("vprscale build --scale 10M --deep1b base.1B.fbin --fas FAS_uniSam5_all.npz --dry-run",
               "what a 10M build from the real files would read, write and take"),
              ("vprscale build --ref ref.npy --query live=q.npy --gt gt.npy --out data",
               "your own descriptors (docs/bring-your-own.md)"),
              ("vprscale build --scale 10M --deep1b https://host/base.1B.fbin --out s3://bucket/vpr",
               "read Deep1B by ranges, write the store to object storage (docs/storage.md)"),
              ("vprscale build --scale 10M --base bigann:sources/bigann.base.10M.u8bin --out data",
               "the recipe on another corpus, projected to 96 dimensions (docs/dataset.md)")],
    "index": [("vprscale index data/20K.zarr --out data/20K.index", "fit CoarseHash at d = ⌈log2 N⌉"),
              ("vprscale index data/20K.zarr --d 12 --out data/20K-d12.index", "a coarser hash: longer lists")],
    "encode": [("vprscale encode data/100M.zarr --compare IVF4096,PQ3",
                "encode once, resumably, for every later eval --compare")],
    "eval": [(f"vprscale eval {Q}/20K.zarr {INDEX} --L 1,50,100 --out runs/20K",
              "the paper's grid: both noise levels, paper and aligned modes, the baseline"),
             (f"vprscale eval {Q}/20K.zarr {INDEX} --compare PQ2 --compare IVF256,PQ2 --no-baseline --out runs/codes",
              "CoarseHash beside FAISS compact codes of its size"),
             (f"vprscale eval {Q}/20K.zarr {INDEX} --compare RaBitQ --compare HNSW32 --no-baseline --out runs/sota",
              "beside RaBitQ and an HNSW graph (the speed reference)"),
             (f"vprscale eval {Q}/20K.zarr {INDEX} --L 50 --compare seq:PQ2 --compare seq:PQ2+rerank --no-baseline "
              "--out runs/pooled", "beside pooled sequence descriptors, alone and re-ranked by CoarseHash"),
             (f"vprscale eval {Q}/20K.zarr {INDEX} --L 1 --compare IVF256,PQ2 --nn --no-baseline --out runs/nn",
              "also 1-NN recall at 1, 10, 100 against exact neighbours (nn.parquet)")],
    "report": [(f"vprscale report {INDEX}/eval --out my-report", "figures and report.md of an evaluation"),
               (f"vprscale report {INDEX}/eval --out my-report --force", "draw again; the old report is kept beside")],
    "results": [(f"vprscale results {INDEX}", "method, parameters and recall of every row"),
                (f"vprscale results {INDEX} --where \"radius = 20 AND L = 100\" --csv", "a filtered CSV"),
                (f"vprscale results {INDEX} --best-bytes 4", "each method's best recall within 4 bytes a place")],
    "methods": [("vprscale methods", "what --compare and --method accept")],
    "verify": [(f"vprscale verify {INDEX}", "every file's size and CRC32C against the manifest"),
               ("vprscale verify s3://bucket/vpr/10M.zarr", "a store on object storage, object by object")],
    "run": [("vprscale run quickstart", "the shipped quickstart pipeline (or pipelines/quickstart.toml)"),
            ("vprscale run paper --dry-run", "which stages would run, and why"),
            ("vprscale run paper --budget 2h", "stages until 2 hours are spent; exit 75 if more is left"),
            ("vprscale run paper eval-1M --set eval-1M.L=[1,50]", "one stage, a parameter overridden"),
            ("vprscale run paper --dag", "the stage graph with each stage's state (Mermaid)")],
    "bench": [(f"vprscale bench online {Q}/20K.zarr --index {INDEX} --L 50", "online matching's cost per frame"),
              (f"vprscale bench startup {INDEX}", "the one-shot commands' CPU time, start to exit")],
    "sql": [(f"vprscale sql {INDEX} \"SELECT size, count(*) AS buckets FROM buckets GROUP BY size ORDER BY size\"",
             "the bucket-size histogram"),
            (f"vprscale sql {INDEX}", "an interactive shell (history, line editing; .help lists its commands)")],
    "localise": [(f"vprscale localise {INDEX} {Q}/20K.zarr/query_qm1 --L 50 --out matches.csv",
                  "match a traverse frame by frame; one row per frame, with its score"),
                 (f"vprscale localise {INDEX} {Q}/20K.zarr/query_qm1 --L 50 | head", "the same as CSV on stdout")],
    "occupancy": [(f"vprscale occupancy {INDEX}", "bucket sizes, occupied share, per-component balance")],
}


def epilog(command: str) -> str:
    lines = ["examples:"]
    for cmd, what in EXAMPLES.get(command, []):
        lines += [f"  {cmd}", f"      {what}"]
    return "\n".join(lines) + f"\n\ndocs: {docs_index()}"


def docs_index() -> str:
    """Where the documentation's index is on this machine: in the installed package (a wheel's
    ``vprscale/docs``), else in the checkout vprscale is imported from."""
    from importlib.resources import files

    try:
        return str(files("vprscale.docs") / "README.md")
    except ModuleNotFoundError:
        return str(Path(__file__).resolve().parents[2] / "docs" / "README.md")
