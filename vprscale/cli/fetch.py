"""``vprscale fetch``: downloads the real sources, or the rows a scale reads."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vprscale.cli.common import bounded_int, write_summary

SOURCES = ("deep1b", "deep1b-queries", "fas100k", "bigann", "text2image", "turing", "spacev")  # dataset.fetch's


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("fetch", parents=[summary],
                       help="download Deep1B or another corpus (the first rows a scale reads), Deep1B's queries or "
                            "FAS100K, by ranges, resumable, checked, with a manifest")
    p.add_argument("source", choices=SOURCES, help="deep1b (base.1B.fbin), deep1b-queries (query.public.10K.fbin), "
                                                   "fas100k (the NetVLAD .npz), or another corpus's base file for "
                                                   "build --base: bigann (base.1B.u8bin), text2image, turing (.fbin), "
                                                   "spacev (.i8bin, with --url)")
    p.add_argument("--out", required=True, help="the folder to write into")
    p.add_argument("--rows", help="a corpus's base file: the first rows only, e.g. 10M (what the 10M scale reads), "
                                  "1B, 20000 (default: all 1B; Deep1B's is 384 GB)")
    p.add_argument("--format", choices=["fbin", "fvecs"], default="fbin",
                   help="a float32 base file: write the rows as .fbin (big-ann-benchmarks' layout) or fvecs")
    p.add_argument("--url", help="the source's URL, for a mirror (default: VPRSCALE_<SOURCE>_URL if set, e.g. "
                                 "VPRSCALE_DEEP1B_URL, VPRSCALE_BIGANN_URL, else docs/dataset.md's)")
    p.add_argument("--connections", type=bounded_int(32, "parallel requests to one server"), default=4,
                   help="byte ranges fetched at once")
    p.add_argument("--force", action="store_true",
                   help="fetch again a file already in --out; the old one is kept beside, as <file>.previous")
    p.set_defaults(func=run, out_is_dir=True)


def run(args: argparse.Namespace) -> int:
    from vprscale.core.throughput import throughput
    from vprscale.dataset.fetch import FetchRequest, fetch, parse_rows

    t0 = time.perf_counter()
    summary = fetch(FetchRequest(source=args.source, out=Path(args.out),
                                 rows=parse_rows(args.rows) if args.rows else None, format=args.format,
                                 url=args.url, connections=args.connections, force=args.force))
    print(f"{summary['file']}: {summary['bytes']:,} bytes" + (f", {summary['rows']:,} rows" if summary["rows"] else "")
          + f", CRC32C {summary['crc32c']}, from {summary['source']}")
    summary["wall_s"] = time.perf_counter() - t0  # a resumed fetch counts from where it resumed
    print("  fetched " + throughput(summary["rows"] or 0, summary["bytes"], summary["wall_s"], args.connections,
                                    per="connection"))
    write_summary(args, summary)
    return 0
