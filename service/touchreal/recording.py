"""Rig recording format: a dataset folder with ``manifest.json`` and ``trials/<id>.npz``.

The format is documented in docs/recording-format.md. All arrays of a trial share one recording
clock (s, t = 0 at recording start): SingleTact (N, 100 Hz) and PVDF (V, 2 kHz) carry explicit
sample times; the commanded indentation (mm) is on a regular grid ``cmd_t0 + arange(n) / cmd_fs``.
Reference spike trains are stored flat per class with an offsets table of shape
(repeats, n_models + 1).

Reading validates everything a consumer relies on and raises :class:`RecordingError` with the
file and key named; writing validates the same way before touching the disk.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .settings import CLASSES, PVDF_FS_HZ, ST_FS_HZ

FORMAT_VERSION = "1.0"
PROTOCOLS = ("ramp", "sine", "texture", "spatial_ramp", "spatial_sine")
_RATE_TOLERANCE = 0.01  # relative tolerance on the median sample rate


class RecordingError(ValueError):
    """A recording or dataset is malformed or inconsistent."""


@dataclass
class ReferenceTrains:
    """Spike trains of one class: ``train(r, m) = t[off[r, m]:off[r, m + 1]]`` (s)."""

    t: np.ndarray  # float, flat spike times (s)
    off: np.ndarray  # int, (repeats, n_models + 1)

    @property
    def repeats(self) -> int:
        return self.off.shape[0]

    @property
    def n_models(self) -> int:
        return self.off.shape[1] - 1

    def train(self, repeat: int, model: int) -> np.ndarray:
        return self.t[self.off[repeat, model] : self.off[repeat, model + 1]]

    def trains(self) -> list[np.ndarray]:
        """All trains, repeat-major: [(r0, m0), (r0, m1), ..., (r1, m0), ...]."""
        return [self.train(r, m) for r in range(self.repeats) for m in range(self.n_models)]

    @classmethod
    def from_trains(cls, trains: list[list[np.ndarray]]) -> "ReferenceTrains":
        """Pack ``trains[repeat][model]`` into the flat layout."""
        if not trains or not trains[0]:
            raise RecordingError("reference trains need at least one repeat and one model")
        n_models = len(trains[0])
        off = np.zeros((len(trains), n_models + 1), dtype=np.int32)
        flat: list[np.ndarray] = []
        pos = 0
        for r, rep in enumerate(trains):
            if len(rep) != n_models:
                raise RecordingError("every repeat must have the same number of models")
            off[r, 0] = pos
            for m, tr in enumerate(rep):
                pos += len(tr)
                off[r, m + 1] = pos
                flat.append(np.asarray(tr, dtype=np.float32))
        t = np.concatenate(flat) if flat else np.zeros(0, np.float32)
        return cls(t=t, off=off)


@dataclass
class Trial:
    """One recording: raw sensor channels, commanded stimulus and optional reference spikes."""

    st_t: np.ndarray  # float64 (s), SingleTact sample times
    st: np.ndarray  # float32 (N)
    pvdf_t: np.ndarray  # float64 (s), PVDF sample times
    pvdf: np.ndarray  # float32 (V)
    cmd_depth: np.ndarray  # float32 (mm), commanded indentation at cmd_fs
    cmd_t0: float = 0.0  # s
    cmd_fs: float = 5000.0  # Hz
    cmd_x: np.ndarray | None = None  # float32 (mm), texture trials only
    reference: dict[str, ReferenceTrains] = field(default_factory=dict)

    @property
    def cmd_t(self) -> np.ndarray:
        return self.cmd_t0 + np.arange(self.cmd_depth.size) / self.cmd_fs

    @property
    def duration_s(self) -> float:
        return float(max(self.st_t[-1] if self.st_t.size else 0.0, self.pvdf_t[-1] if self.pvdf_t.size else 0.0))

    def validate(self, where: str = "trial") -> None:
        """Raise :class:`RecordingError` unless the arrays are consistent."""
        _check_channel(where, "st", self.st_t, self.st, ST_FS_HZ)
        _check_channel(where, "pvdf", self.pvdf_t, self.pvdf, PVDF_FS_HZ)
        if self.cmd_depth.ndim != 1:
            raise RecordingError(f"{where}: cmd_depth must be 1-D")
        if not (np.isfinite(self.cmd_fs) and self.cmd_fs > 0 and np.isfinite(self.cmd_t0)):
            raise RecordingError(f"{where}: cmd_fs must be positive and cmd_t0 finite")
        if self.cmd_x is not None and self.cmd_x.shape != self.cmd_depth.shape:
            raise RecordingError(f"{where}: cmd_x must have the shape of cmd_depth")
        for cls, ref in self.reference.items():
            if cls not in CLASSES:
                raise RecordingError(f"{where}: unknown reference class {cls!r}")
            off = ref.off
            if off.ndim != 2 or off.shape[1] < 2:
                raise RecordingError(f"{where}: ref_{cls}_off must be (repeats, n_models + 1)")
            flat = off.ravel()
            if np.any(np.diff(flat) < 0) or flat[0] != 0 or flat[-1] != ref.t.size:
                # rows are contiguous: row r ends where row r+1 starts
                raise RecordingError(f"{where}: ref_{cls}_off does not index ref_{cls}_t consistently")

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        d: dict[str, np.ndarray] = {
            "st_t": np.asarray(self.st_t, np.float64),
            "st": np.asarray(self.st, np.float32),
            "pvdf_t": np.asarray(self.pvdf_t, np.float64),
            "pvdf": np.asarray(self.pvdf, np.float32),
            "cmd_t0": np.float64(self.cmd_t0),
            "cmd_fs": np.float64(self.cmd_fs),
            "cmd_depth": np.asarray(self.cmd_depth, np.float32),
        }
        if self.cmd_x is not None:
            d["cmd_x"] = np.asarray(self.cmd_x, np.float32)
        for cls, ref in self.reference.items():
            d[f"ref_{cls}_t"] = np.asarray(ref.t, np.float32)
            d[f"ref_{cls}_off"] = np.asarray(ref.off, np.int32)
        return d


def _check_channel(where: str, name: str, t: np.ndarray, x: np.ndarray, fs: float) -> None:
    if t.ndim != 1 or x.ndim != 1 or t.shape != x.shape:
        raise RecordingError(f"{where}: {name}_t and {name} must be 1-D of equal length")
    if t.size < 2:
        raise RecordingError(f"{where}: {name} has fewer than 2 samples")
    if not np.all(np.isfinite(t)):
        raise RecordingError(f"{where}: {name}_t has non-finite times")
    dt = np.diff(t)
    if np.any(dt <= 0):
        bad = int(np.argmax(dt <= 0))
        raise RecordingError(f"{where}: {name}_t is not strictly increasing (sample {bad + 1})")
    rate = 1.0 / float(np.median(dt))
    if abs(rate - fs) > _RATE_TOLERANCE * fs:
        raise RecordingError(f"{where}: {name} is sampled at {rate:.3f} Hz, expected {fs:g} Hz")


def load_trial(path: str | Path) -> Trial:
    """Read and validate one trial ``.npz``."""
    path = Path(path)
    try:
        with np.load(path) as d:
            keys = set(d.files)
            missing = {"st_t", "st", "pvdf_t", "pvdf", "cmd_t0", "cmd_fs", "cmd_depth"} - keys
            if missing:
                raise RecordingError(f"{path}: missing keys {sorted(missing)}")
            ref: dict[str, ReferenceTrains] = {}
            for cls in CLASSES:
                has_t, has_off = f"ref_{cls}_t" in keys, f"ref_{cls}_off" in keys
                if has_t != has_off:
                    raise RecordingError(f"{path}: ref_{cls}_t and ref_{cls}_off must come together")
                if has_t:
                    ref[cls] = ReferenceTrains(d[f"ref_{cls}_t"].astype(np.float64), d[f"ref_{cls}_off"].astype(np.int64))
            trial = Trial(
                st_t=d["st_t"].astype(np.float64),
                st=d["st"],
                pvdf_t=d["pvdf_t"].astype(np.float64),
                pvdf=d["pvdf"],
                cmd_depth=d["cmd_depth"],
                cmd_t0=float(d["cmd_t0"]),
                cmd_fs=float(d["cmd_fs"]),
                cmd_x=d["cmd_x"] if "cmd_x" in keys else None,
                reference=ref,
            )
    except (OSError, ValueError) as exc:
        if isinstance(exc, RecordingError):
            raise
        raise RecordingError(f"{path}: not a readable trial file ({exc})") from exc
    trial.validate(str(path))
    return trial


def save_trial(path: str | Path, trial: Trial) -> None:
    """Validate and write one trial ``.npz`` (compressed)."""
    trial.validate(str(path))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **trial.to_npz_dict())


_ENTRY_KEYS = ("id", "file", "protocol", "condition", "repeat", "params", "onset_s", "stim_end_s")


@dataclass
class Dataset:
    """A dataset folder: the manifest plus lazy access to its trials."""

    root: Path
    manifest: dict[str, Any]

    @classmethod
    def open(cls, root: str | Path) -> "Dataset":
        root = Path(root)
        mpath = root / "manifest.json"
        if not mpath.is_file():
            raise RecordingError(f"{root}: no manifest.json (is this a dataset folder?)")
        try:
            manifest = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{mpath}: invalid JSON ({exc})") from exc
        if not isinstance(manifest, dict) or not isinstance(manifest.get("trials"), list):
            raise RecordingError(f"{mpath}: manifest must be an object with a 'trials' list")
        seen: set[str] = set()
        for i, e in enumerate(manifest["trials"]):
            missing = [k for k in _ENTRY_KEYS if k not in e]
            if missing:
                raise RecordingError(f"{mpath}: trial {i} lacks {missing}")
            if e["protocol"] not in PROTOCOLS:
                raise RecordingError(f"{mpath}: trial {e['id']} has unknown protocol {e['protocol']!r}")
            if e["id"] in seen:
                raise RecordingError(f"{mpath}: duplicate trial id {e['id']!r}")
            seen.add(e["id"])
        return cls(root=root, manifest=manifest)

    @property
    def trials(self) -> list[dict[str, Any]]:
        return self.manifest["trials"]

    def entries(self, protocol: str | None = None) -> list[dict[str, Any]]:
        return [e for e in self.trials if protocol is None or e["protocol"] == protocol]

    def entry(self, trial_id: str) -> dict[str, Any]:
        for e in self.trials:
            if e["id"] == trial_id:
                return e
        raise KeyError(trial_id)

    def load(self, entry: dict[str, Any] | str) -> Trial:
        if isinstance(entry, str):
            entry = self.entry(entry)
        return load_trial(self.root / entry["file"])

    def __iter__(self) -> Iterator[tuple[dict[str, Any], Trial]]:
        for e in self.trials:
            yield e, self.load(e)


def write_dataset(root: str | Path, manifest: dict[str, Any], trials: dict[str, Trial]) -> Dataset:
    """Write ``trials`` (keyed by trial id) and a manifest whose entries name them.

    Entries get ``file`` = ``trials/<id>.npz`` and the sample counts filled in.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    manifest = dict(manifest)
    manifest.setdefault("format_version", FORMAT_VERSION)
    for e in manifest["trials"]:
        trial = trials[e["id"]]
        e["file"] = f"trials/{e['id']}.npz"
        e["n_st"], e["n_pvdf"], e["n_cmd"] = int(trial.st.size), int(trial.pvdf.size), int(trial.cmd_depth.size)
        save_trial(root / e["file"], trial)
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return Dataset.open(root)
