"""``touchreal bench TARGET``: run a benchmark and print its figures."""

from __future__ import annotations

import argparse
import importlib

from ..bench import TARGETS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print figures")
    targets = p.add_subparsers(dest="target", required=True, metavar="TARGET")
    for name in TARGETS:
        module = importlib.import_module(f"touchreal.bench.{name}")
        tp = targets.add_parser(name, help=(module.__doc__ or name).splitlines()[0])
        module.add_arguments(tp)
        tp.set_defaults(func=module.run)
