"""``vprscale methods``: lists the evaluated methods' registry."""

from __future__ import annotations

import argparse


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("methods", help="the evaluated methods' registry: built-in and installed (entry points)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.algorithms.registry import registered

    notes = {"built-in": "", "factory": "  (entry point vprscale.algorithms: joins every evaluation)",
             "method": "  (entry point vprscale.algorithms: eval --method NAME)"}
    for name, (target, kind) in registered().items():
        print(f"{name:<12} {target}{notes[kind]}")
    print("any class of the contract in docs/bring-your-own.md: eval --method package.module:Class")
    return 0
