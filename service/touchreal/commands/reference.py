"""``touchreal reference DATASET_DIR --out OUT_DIR``: TouchSim reference spike trains for a dataset.

For every trial the commanded indentation (``cmd_depth``, float32 -> float64, 5 kHz from
``cmd_t0``) drives the reference model with the probe and afferent positions of the manifest entry
(``reference.probe_xy_mm`` / ``reference.afferent_xy_mm``). Output: ``OUT_DIR/<trial_id>.npz`` with
``ref_<class>_t`` (float32, s on the recording clock) and ``ref_<class>_off`` (int32,
(repeats, n_models + 1)), the keys of the dataset's own trial files, plus ``OUT_DIR/reference.json``
describing the run.

Trials whose entry has ``reference: null`` (the texture trials of rig-v1) are skipped with a
printed note: a single round probe does not model a comb sliding across the skin. With
``--include-unreferenced`` they are computed anyway, with the probe at the entry's offset
``(r cos theta, r sin theta)`` and the afferent at the origin (a ramp-hold-release of a 1 mm probe,
not a texture response).

Noise: every trial gets its own generator seeded from ``(--seed, crc32(trial id))``, so a trial's
trains do not depend on which other trials are processed or in which order.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..recording import Dataset, RecordingError
from ..settings import CLASSES
from ..reference.model import ReferenceModel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reference",
        help="compute TouchSim reference spike trains for every trial of a dataset",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET_DIR", type=Path, help="dataset folder with manifest.json")
    p.add_argument("--out", required=True, type=Path, metavar="OUT_DIR", help="output folder (<trial_id>.npz)")
    p.add_argument("--repeats", type=int, default=None,
                   help="noisy repeats per trial (default: the manifest's reference repeats, else 1)")
    p.add_argument("--seed", type=int, default=0, help="base seed of the noise (default 0)")
    p.add_argument("--noiseless", action="store_true", help="TouchSim with noisy=False (repeats are identical)")
    p.add_argument("--delays", action="store_true", help="add the models' conduction delays")
    p.add_argument("--protocol", action="append", default=None, metavar="NAME",
                   help="only trials of this protocol (repeatable)")
    p.add_argument("--include-unreferenced", action="store_true",
                   help="also compute trials whose entry has reference null (probe at the entry offset)")
    p.add_argument("--pin-radius", type=float, default=0.5, help="probe radius in mm (default 0.5)")
    p.set_defaults(func=run)


def trial_seed(base_seed: int, trial_id: str) -> np.random.SeedSequence:
    """Per-trial noise seed, independent of processing order."""
    return np.random.SeedSequence([int(base_seed) & 0xFFFFFFFF, zlib.crc32(trial_id.encode())])


def trial_geometry(entry: dict[str, Any]) -> tuple[tuple[float, float], tuple[float, float], bool]:
    """(probe_xy_mm, afferent_xy_mm, from_manifest) of one manifest entry."""
    ref = entry.get("reference")
    if ref:
        probe = tuple(float(v) for v in ref["probe_xy_mm"])
        aff = tuple(float(v) for v in ref["afferent_xy_mm"])
        return probe, aff, True  # type: ignore[return-value]
    r = float(entry.get("offset_r_mm") or 0.0)
    th = math.radians(float(entry.get("offset_theta_deg") or 0.0))
    return (r * math.cos(th), r * math.sin(th)), (0.0, 0.0), False


def _repeats(args: argparse.Namespace, manifest: dict[str, Any], entry: dict[str, Any]) -> int:
    if args.repeats is not None:
        return args.repeats
    ref = entry.get("reference") or {}
    if ref.get("repeats"):
        return int(ref["repeats"])
    per_protocol = (manifest.get("reference") or {}).get("repeats") or {}
    return max(1, int(per_protocol.get(entry["protocol"], 1) or 1))


def run(args: argparse.Namespace) -> int:
    if args.repeats is not None and args.repeats < 1:
        raise ValueError("--repeats must be >= 1")
    dataset = Dataset.open(args.dataset)
    out = Path(args.out)
    trial_dirs = {(dataset.root / e["file"]).resolve().parent for e in dataset.trials}
    if out.resolve() in trial_dirs or out.resolve() == dataset.root.resolve():
        raise ValueError(f"--out {out} is a folder of the dataset itself; choose a separate folder")
    entries = dataset.entries()
    if args.protocol:
        unknown = set(args.protocol) - {e["protocol"] for e in entries}
        if unknown:
            print(f"note: no trials of protocol(s) {sorted(unknown)} in {dataset.root}")
        entries = [e for e in entries if e["protocol"] in args.protocol]
    out.mkdir(parents=True, exist_ok=True)
    model = ReferenceModel(pin_radius_mm=args.pin_radius)

    done: list[dict[str, Any]] = []
    skipped: list[dict[str, str]] = []
    unreferenced = [e["id"] for e in entries if not e.get("reference")]
    if unreferenced and not args.include_unreferenced:
        print(f"note: skipping {len(unreferenced)} trial(s) with reference null (e.g. {unreferenced[0]}): a single "
              "round probe does not model them; --include-unreferenced computes them with the probe at the "
              "entry offset and the afferent at the origin")
    t_start = time.perf_counter()
    for entry in tqdm(entries, desc="reference", unit="trial"):
        tid = entry["id"]
        probe, aff, from_manifest = trial_geometry(entry)
        if not from_manifest and not args.include_unreferenced:
            skipped.append({"id": tid, "reason": "reference null"})
            continue
        try:
            trial = dataset.load(entry)
        except RecordingError as exc:
            tqdm.write(f"note: skipping {tid}: {exc}")
            skipped.append({"id": tid, "reason": str(exc)})
            continue
        if trial.cmd_depth.size == 0:
            tqdm.write(f"note: skipping {tid}: empty cmd_depth")
            skipped.append({"id": tid, "reason": "empty cmd_depth"})
            continue
        repeats = _repeats(args, dataset.manifest, entry)
        resp = model.simulate(
            trial.cmd_depth.astype(np.float64), fs_hz=trial.cmd_fs, probe_xy_mm=probe, afferent_xy_mm=[aff],
            repeats=repeats, noisy=not args.noiseless, delays=args.delays,
            rng=np.random.default_rng(trial_seed(args.seed, tid)),
        )
        trains = resp.class_trains(0)
        arrays: dict[str, np.ndarray] = {}
        for cls in CLASSES:
            ref = trains[cls]
            arrays[f"ref_{cls}_t"] = (np.asarray(ref.t, np.float64) + trial.cmd_t0).astype(np.float32)
            arrays[f"ref_{cls}_off"] = np.asarray(ref.off, np.int32)
        np.savez_compressed(out / f"{tid}.npz", **arrays)
        done.append({
            "id": tid, "protocol": entry["protocol"], "probe_xy_mm": list(probe), "afferent_xy_mm": list(aff),
            "from_manifest": from_manifest, "repeats": repeats,
            "n_spikes": {cls: int(trains[cls].t.size) for cls in CLASSES},
        })
    elapsed = time.perf_counter() - t_start
    summary = {
        "dataset": str(dataset.root.resolve()),
        "model": "touchreal.reference (TouchSim 0.1.1-compatible single round probe)",
        "pin_radius_mm": args.pin_radius, "noisy": not args.noiseless, "delays": args.delays,
        "seed": args.seed, "seeding": "numpy SeedSequence([seed, crc32(trial_id)]) per trial",
        "time": "s on the recording clock (cmd_t0 + spike time from cmd sample 0)",
        "trials": done, "skipped": skipped, "elapsed_s": round(elapsed, 3),
    }
    (out / "reference.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {len(done)} trial(s) to {out} in {elapsed:.1f} s; skipped {len(skipped)}")
    return 0
