"""Train a texture classifier on binned afferent spikes through Tonic: a TouchReal encode folder as a
``touchreal_client.tonic.TouchRealDataset``, ``tonic.transforms.ToFrame`` into 100 ms frames of SA1,
RA and PC counts, flattened, into scikit-learn's logistic regression (no torch).

By default it makes its data in a few seconds: ``touchreal simulate texture`` (three combs, 0.5, 2
and 4 mm tooth spacing, slid for 2 s in 3 s recordings), then ``touchreal encode --clock sensor``.
``--dataset DIR`` takes a dataset with texture trials instead (e.g. the rig recordings, rig-v1).
Trials are split into training and held-out ones, stratified by texture.

    python texture_tonic.py [--trials 30] [--seed 0] [--dataset DIR] [--work DIR]

Needs ``touchreal-client[tonic]``, scikit-learn and the ``touchreal`` service package (its CLI
simulates and encodes).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import tonic.transforms as T
from sklearn.linear_model import LogisticRegression
from sklearn.model_selection import train_test_split
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from touchreal_client.tonic import TouchRealDataset

FRAME_US = 100_000  #: frame length (µs)


def touchreal(*args: str | Path) -> None:
    """Run a ``touchreal`` command (the service's CLI, in this interpreter); exit on failure."""
    run = subprocess.run([sys.executable, "-m", "touchreal", *map(str, args)], capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"touchreal {args[0]} failed:\n{run.stderr}")


def frames_dataset(encoded: Path, dataset: Path) -> TouchRealDataset:
    """One sample per trial: its frames (counts per frame, class and taxel) flattened to a vector."""
    ds = TouchRealDataset(encoded, dataset=dataset)
    duration_us = max(s.stop_us - s.start_us for s in ds.samples)
    to_frame = T.ToFrame(sensor_size=ds.sensor_size, time_window=FRAME_US, start_time=0, end_time=duration_us)
    ds.transform = T.Compose([to_frame, lambda f: f.reshape(-1)])
    return ds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=30, help="simulated texture trials (default 30)")
    ap.add_argument("--seed", type=int, default=0, help="simulation and split seed")
    ap.add_argument("--dataset", type=Path, default=None, help="a dataset with texture trials instead of simulating")
    ap.add_argument("--work", type=Path, default=None, help="keep the simulated and encoded folders here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        dataset = args.dataset or work / "textures"
        if args.dataset is None:
            touchreal("simulate", "texture", "--trials", args.trials, "--seed", args.seed, "--out", dataset)
        touchreal("encode", dataset, "--protocol", "texture", "--clock", "sensor", "--out", work / "encoded")
        ds = frames_dataset(work / "encoded", dataset)
        x = np.stack([ds[i][0] for i in range(len(ds))]).astype(np.float64)
    y = np.array(ds.targets)
    print(f"{len(ds)} trials, {ds.classes}, sensor_size {ds.sensor_size}, ordering {ds.ordering}, "
          f"{x.shape[1]} features per trial")
    x_fit, x_test, y_fit, y_test = train_test_split(x, y, test_size=1 / 3, stratify=y, random_state=args.seed)
    model = make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000)).fit(x_fit, y_fit)
    accuracy = float(np.mean(model.predict(x_test) == y_test))
    print(f"accuracy {accuracy:.3f} on {len(y_test)} held-out trials (chance {1 / len(ds.classes):.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
