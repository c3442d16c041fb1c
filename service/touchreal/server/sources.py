"""``--source`` specs -> live sources (:mod:`touchreal.sources.live`, the serial reader), and the
confinement of specs a client sends (:func:`confine_source`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from ..recording import Dataset
from ..sources.live import LiveSource, ReplayLiveSource, SimLiveSource
from .settings import SCRIPT_SCENE_MAX_TAXELS, RuntimeConfig, ServeSettings, parse_source


class SourceRefused(ValueError):
    """A source the service will not open for a client: outside the data roots, a pyserial URL
    while those are off, or any source change while remote source changes are off."""


def real(path: str | Path) -> Path:
    """``path`` absolute with every symlink and ``..`` resolved (whether or not it exists)."""
    return Path(os.path.realpath(path))


def confine_source(spec: str, data_roots: Sequence[Path], serial_urls: bool) -> None:
    """Refuse (:class:`SourceRefused`) a spec a client may not open. ``replay:DIR`` only for a DIR
    under one of ``data_roots``; ``serial:PORT`` only for a device under /dev (or a link to one) and
    pyserial URLs (``spy://``, ``socket://``, ``loop://``...) only with ``serial_urls``. The
    messages are the same whether the path exists or not."""
    kind, arg = parse_source(spec)
    if kind == "replay":
        folder = real(arg.partition(":")[0])
        if not any(folder.is_relative_to(real(r)) for r in data_roots):
            raise SourceRefused("replay: datasets are read only under the data roots "
                                f"({', '.join(str(r) for r in data_roots) or 'none'}; TOUCHREAL_DATA_ROOTS)")
    elif kind == "serial":
        if "://" in arg:
            if not serial_urls:
                raise SourceRefused("serial: takes a device path; pyserial URLs are off (TOUCHREAL_SERIAL_URLS)")
        elif not real(arg).is_relative_to("/dev"):
            raise SourceRefused("serial: takes a device path under /dev (or a link to one)")


def sim_touched(settings: ServeSettings, n_taxels: int) -> float | None:
    """The simulated skin's scene, resolved once: None for the scripted scene, else the large
    scene's touched fraction (``sim_scene`` auto: scripted up to SCRIPT_SCENE_MAX_TAXELS taxels)."""
    scene = settings.sim_scene
    if scene == "auto":
        scene = "script" if n_taxels <= SCRIPT_SCENE_MAX_TAXELS else "large"
    return None if scene == "script" else settings.sim_touched


def open_source(config: RuntimeConfig, settings: ServeSettings, hop_s: float, device_present: bool = False) -> LiveSource:
    """Open the source a config names, handing over samples every ``hop_s`` (raises ValueError/OSError
    with a clear message). A serial device that is absent at start is waited for (it reconnects on
    unplug anyway), unless ``device_present``: then a device that is missing, not a terminal or busy
    is refused at once (a client's source change)."""
    kind, arg = parse_source(config.source)
    if kind == "sim":
        return SimLiveSource(config.taxels, hop_s, seed=settings.seed, t0_s=settings.sim_t0_s, own_process=True,
                             touched=sim_touched(settings, config.taxels))
    if kind == "replay":
        folder, _, ids = arg.partition(":")
        if not Path(folder).is_dir():
            raise ValueError(f"replay dataset folder not found: {folder}")
        trial_ids = [t for t in ids.split(",") if t] or None
        return ReplayLiveSource(Dataset.open(folder), trial_ids, hop_s, config.speed, config.loop)
    from ..device.serial_source import SerialSource, check_device

    if device_present and "://" not in arg:
        check_device(arg)
    return SerialSource(arg, n_taxels=config.taxels, update_s=hop_s, allow_urls=settings.serial_urls)
