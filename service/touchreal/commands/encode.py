"""``touchreal encode DATASET_DIR --params PARAMS.json --out OUT_DIR``.

Spike times are written on the dataset's reference clock by default: each stamp minus the parameter
file's ``alignment.lag_ms`` (the rig's lag behind the commanded stimulus its reference spikes follow),
so they compare directly with the dataset's reference trains. ``--clock sensor`` writes the stamps
themselves (the sensor clock, as the online stream emits them).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tqdm import tqdm

from ..params import EncoderParams, default_params
from ..recording import Dataset
from ..stream import encode_trial


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("encode", help="encode every trial of a dataset into SA1/RA/PC spike times")
    p.add_argument("dataset", type=Path, help="dataset folder (manifest.json + trials/)")
    p.add_argument("--params", type=Path, default=None, help="parameter file (default: the shipped set)")
    p.add_argument("--out", type=Path, required=True, help="output folder for <trial_id>.json")
    p.add_argument("--protocol", default=None, help="only trials of this protocol")
    p.add_argument("--clock", choices=("reference", "sensor"), default="reference",
                   help="reference (default): stamp - the parameter file's alignment lag, comparable with the dataset's "
                   "reference spike trains; sensor: the stamps as the online stream emits them")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    params = EncoderParams.load(args.params) if args.params else default_params()
    ds = Dataset.open(args.dataset)
    entries = ds.entries(args.protocol)
    args.out.mkdir(parents=True, exist_ok=True)
    total = {c: 0 for c in params.classes}
    for e in tqdm(entries, desc="encode", unit="trial"):
        trains = encode_trial(ds.load(e), params)
        if args.clock == "reference":
            trains = {c: params.reference_times(v) for c, v in trains.items()}
        (args.out / f"{e['id']}.json").write_text(json.dumps({c: [round(float(t), 6) for t in v] for c, v in trains.items()}))
        for c, v in trains.items():
            total[c] += v.size
    clock = f"reference clock (stamp - {params.alignment.lag_ms:g} ms)" if args.clock == "reference" else "sensor clock"
    print(f"encoded {len(entries)} trials -> {args.out} ({clock}); spikes: " + ", ".join(f"{c} {n}" for c, n in total.items()))
    return 0
