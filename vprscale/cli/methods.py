"""``vprscale methods``: what an evaluation can compare, and the flag that asks for each."""

from __future__ import annotations

import argparse

BUILT_IN = (
    ("coarsehash", "always", "CoarseHash, the paper's method, in paper and aligned modes (docs/method.md)"),
    ("baseline", "--baseline (on) / --no-baseline", "the paper's modified SeqSLAM under the same storage"),
    ("faiss:FACTORY", "--compare FACTORY", "any FAISS index_factory string, e.g. --compare PQ3, OPQ3,PQ3, "
                                           "ITQ24,LSH, IVF4096,PQ3, PQ6x4fs, RaBitQ, IVF4096,RaBitQfs, "
                                           "RQ3x8_Nqint8, IVF4096,RQ4x4fsr_Nrq2x4, LSQ3x8, HNSW32 "
                                           "(docs/protocol.md)"),
    ("seq:FACTORY", "--compare seq:FACTORY", "a pooled sequence descriptor: each window of L frames pooled into "
                                             "one row (mean; seq-gem3: GeM) held in a FAISS code, e.g. --compare "
                                             "seq:PQ3, seq:IVF4096,PQ3, seq-gem3:Flat; +rerank: CoarseHash's window "
                                             "score ranks its 20 best (docs/protocol.md)"),
    ("CLASS", "--method package.module:Class", "your own class of the small contract (docs/bring-your-own.md)"),
)


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("methods", help="what eval can compare, and the flag (--compare, --method) that asks for each")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.algorithms.registry import BUILTIN, registered

    rows = list(BUILT_IN)
    for name, (target, kind) in registered().items():
        if name in BUILTIN:
            continue
        if kind == "method":
            rows.append((name, f"--method {name}", f"installed method {target}"))
        else:
            rows.append((name, "always", f"installed factory {target} (joins every evaluation)"))
    width = max(len(r[0]) for r in rows)
    how = max(len(r[1]) for r in rows)
    print(f"{'method':<{width}}  {'asked for by':<{how}}  what it is")
    for name, flag, what in rows:
        print(f"{name:<{width}}  {flag:<{how}}  {what}")
    return 0
