"""``--source`` specs -> live sources (:mod:`touchreal.sensing.live`, the serial reader)."""

from __future__ import annotations

from pathlib import Path

from ..recording import Dataset
from ..sensing.live import LiveSource, ReplayLiveSource, SimLiveSource
from .settings import RuntimeConfig, ServeSettings


def parse_source(spec: str) -> tuple[str, str]:
    """``sim`` | ``replay:DIR[:ID,...]`` | ``serial:PORT`` -> (kind, argument); ValueError otherwise."""
    kind, _, arg = spec.partition(":")
    if kind == "sim" and not arg:
        return kind, ""
    if kind in ("replay", "serial") and arg:
        return kind, arg
    raise ValueError(f"source must be 'sim', 'replay:DATASET_DIR[:TRIAL_ID,...]' or 'serial:PORT', got {spec!r}")


def open_source(config: RuntimeConfig, settings: ServeSettings, hop_s: float) -> LiveSource:
    """Open the source a config names, handing over samples every ``hop_s`` (raises ValueError/OSError
    with a clear message)."""
    kind, arg = parse_source(config.source)
    if kind == "sim":
        return SimLiveSource(config.taxels, hop_s, seed=settings.seed, t0_s=settings.sim_t0_s)
    if kind == "replay":
        folder, _, ids = arg.partition(":")
        if not Path(folder).is_dir():
            raise ValueError(f"replay dataset folder not found: {folder}")
        trial_ids = [t for t in ids.split(",") if t] or None
        return ReplayLiveSource(Dataset.open(folder), trial_ids, hop_s, config.speed, config.loop)
    from ..sensing.serial_source import SerialSource

    return SerialSource(arg, n_taxels=config.taxels, update_s=hop_s)
