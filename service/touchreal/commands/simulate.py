"""``touchreal simulate``: write a simulated e-skin dataset in the recording format."""

from __future__ import annotations

import argparse
import sys
import time

from ..simulator.simulate import PROTOCOL_GROUPS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a simulated e-skin dataset (no hardware needed)",
        description="Simulate rig protocols with the e-skin physics model and write a dataset "
        "(manifest.json + trials/*.npz) with TouchSim reference spike trains.",
    )
    p.add_argument("protocols", nargs="+", choices=sorted(PROTOCOL_GROUPS) + ["all"], metavar="PROTOCOL",
                   help="ramp, sine, texture, spatial (spatial_ramp + spatial_sine), all (the paper's four), or "
                   "texture-fine (eight close combs at three close speeds, for the texture decoder), texture-hard (ten close "
                   "combs at 20-60 mm/s, press depth and sensor build drawn per trial)")
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--trials", type=_trial_counts, default=4,
                   help="trials per protocol, spread over its conditions: N for every protocol, or "
                   "PROTOCOL=N,... (e.g. ramp=896,sine=100; default 4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--speeds", type=_speeds, default=None, metavar="V,...",
                   help="texture-hard: its scanning speeds in mm/s (default 20,30,40,50,60), e.g. to hold a speed out")
    p.add_argument("--same-build", action="store_true",
                   help="texture-hard: every trial on the dataset's build (default: a build drawn per trial around it)")
    p.add_argument("--no-reference", action="store_true", help="skip the TouchSim reference spike trains")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    g = p.add_argument_group("sensor build (docs/simulator.md; ratios to the nominal rig-v1 build)")
    g.add_argument("--build", default=None, metavar="NAME|FILE",
                   help="a shipped build (nominal, weak-film-60hz, noisy-amplifier, stiff-film-slow-rig) or a JSON file; "
                   "the options below override its fields")
    for name, kind, text in BUILD_OPTIONS:
        g.add_argument("--" + name.replace("_", "-"), dest=f"build_{name}", type=kind, default=None, help=text)
    p.set_defaults(func=run)


BUILD_OPTIONS = (
    ("pvdf_coupling", float, "film sensitivity x this (real builds 0.5-1.5)"),
    ("st_gain", float, "SingleTact sensitivity x this (0.8-1.2)"),
    ("st_noise", float, "SingleTact noise x this (0.5-3)"),
    ("pvdf_noise", float, "PVDF noise x this (0.5-3)"),
    ("mains_hz", float, "mains frequency, 50 or 60 Hz"),
    ("mains_level", float, "mains pickup x this (0.5-3)"),
    ("mains_harmonics", int, "highest mains harmonic, 1-9 (nominal 8)"),
    ("harmonic_gain", float, "mains harmonics 2 and up x this (0.5-3)"),
    ("rig_lag_ms", float, "physical stimulus behind its command, ms (nominal 6.5; real rigs up to 120)"),
)


def build_from_args(args: argparse.Namespace):
    """The build the options name (None: nominal, nothing asked)."""
    import dataclasses

    from ..simulator.build import SensorBuild, load_build

    over = {name: getattr(args, f"build_{name}") for name, _, _ in BUILD_OPTIONS if getattr(args, f"build_{name}") is not None}
    if args.build is None and not over:
        return None
    base = load_build(args.build) if args.build else SensorBuild()
    return dataclasses.replace(base, **over, name=base.name if not over else f"{base.name}+custom")


def _speeds(text: str) -> tuple[float, ...]:
    try:
        speeds = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected speeds in mm/s like 20,30,50; got {text!r}") from None
    if not speeds or min(speeds) <= 0:
        raise argparse.ArgumentTypeError("speeds must be > 0 mm/s")
    return speeds


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
    from ..simulator.simulate import simulate_dataset

    if isinstance(args.trials, dict):
        unknown = (set(args.trials) - set(args.protocols) - set(PROTOCOL_GROUPS["spatial"]) - set(PROTOCOL_GROUPS["texture-fine"])
                   - set(PROTOCOL_GROUPS["texture-hard"]))
        if unknown:
            raise ValueError(f"--trials names protocols not being simulated: {sorted(unknown)}")
    protocols = [g for g in PROTOCOL_GROUPS if not g.startswith("texture-")] if "all" in args.protocols else args.protocols
    if (args.speeds is not None or args.same_build) and "texture-hard" not in protocols:
        raise ValueError("--speeds and --same-build apply to texture-hard only")
    t0 = time.perf_counter()
    progress = None if args.quiet else (lambda tid: print(f"  {tid}", file=sys.stderr))
    build = build_from_args(args)
    ds = simulate_dataset(protocols, args.out, args.trials, args.seed, reference=not args.no_reference, build=build,
                          speeds_mm_s=args.speeds, vary_build=not args.same_build, progress=progress)
    counts = ", ".join(f"{k} {v}" for k, v in ds.manifest["counts"].items())
    print(f"wrote {len(ds.trials)} trials ({counts}) to {ds.root} in {time.perf_counter() - t0:.1f} s")
    return 0
