"""The ``touchreal`` command line: one sub-command per job, each a module of :mod:`touchreal.commands`.

Each command module exposes ``register(subparsers)``, which adds its parser and sets
``func(args) -> int`` as the handler; the heavy imports happen inside the handlers, so
``touchreal --help`` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Command modules, in the order they appear in ``touchreal --help``.
COMMAND_MODULES = (
    "touchreal.commands.demo",
    "touchreal.commands.encode",
    "touchreal.commands.mcu_emulate",
    "touchreal.commands.reference",
    "touchreal.commands.simulate",
    "touchreal.commands.fit",
    "touchreal.commands.evaluate",
    "touchreal.commands.bench",
    "touchreal.commands.decoders",
    "touchreal.commands.serve",
    "touchreal.commands.gateway",
    "touchreal.commands.record",
    "touchreal.commands.export",
    "touchreal.commands.bridge",
    "touchreal.commands.population",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchreal", description="TouchReal: tactile sensor signals -> SA1/RA/PC afferent spike trains."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def one_line(exc: BaseException) -> str:
    """An expected error as one line (a pydantic ValidationError lists each field: its problem)."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(map(str, e['loc'])) or exc.title}: {e['msg']}" for e in exc.errors())
    return " ".join(str(exc).split()) or type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, ImportError) as exc:  # clear message, no traceback: bad input, a missing extra
        print(f"touchreal {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
