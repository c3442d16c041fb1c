"""``touchreal simulate``: write a simulated e-skin dataset in the recording format."""

from __future__ import annotations

import argparse
import sys
import time

from .simulate import PROTOCOL_GROUPS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a simulated e-skin dataset (no hardware needed)",
        description="Simulate rig protocols with the e-skin physics model and write a dataset "
        "(manifest.json + trials/*.npz) with TouchSim reference spike trains.",
    )
    p.add_argument("protocols", nargs="+", choices=sorted(PROTOCOL_GROUPS) + ["all"], metavar="PROTOCOL",
                   help="ramp, sine, texture, spatial (spatial_ramp + spatial_sine) or all")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--trials", type=_trial_counts, default=4,
                   help="trials per protocol, spread over its conditions: N for every protocol, or "
                   "PROTOCOL=N,... (e.g. ramp=896,sine=100; default 4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-reference", action="store_true", help="skip the TouchSim reference spike trains")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _trial_counts(text: str) -> int | dict[str, int]:
    try:
        if "=" not in text:
            counts: int | dict[str, int] = int(text)
            values = [counts]
        else:
            counts = {k.strip(): int(v) for k, v in (part.split("=", 1) for part in text.split(","))}
            values = list(counts.values())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or PROTOCOL=N,...; got {text!r}") from None
    if min(values) < 1:
        raise argparse.ArgumentTypeError("trial counts must be >= 1")
    return counts


def run(args: argparse.Namespace) -> int:
    from .simulate import simulate_dataset

    if isinstance(args.trials, dict):
        unknown = set(args.trials) - set(args.protocols) - set(PROTOCOL_GROUPS.get("spatial", ()))
        if unknown:
            raise ValueError(f"--trials names protocols not being simulated: {sorted(unknown)}")
    protocols = list(PROTOCOL_GROUPS) if "all" in args.protocols else args.protocols
    t0 = time.perf_counter()
    progress = None if args.quiet else (lambda tid: print(f"  {tid}", file=sys.stderr))
    ds = simulate_dataset(protocols, args.out, args.trials, args.seed, reference=not args.no_reference, progress=progress)
    counts = ", ".join(f"{k} {v}" for k, v in ds.manifest["counts"].items())
    print(f"wrote {len(ds.trials)} trials ({counts}) to {ds.root} in {time.perf_counter() - t0:.1f} s")
    return 0
