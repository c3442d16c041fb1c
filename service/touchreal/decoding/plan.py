"""Which decoders ``touchreal decoders train`` makes, and the metric keys each one reports under.

Product models (top folder, installed and served): ``force`` (SA1 + RA, 128 ms), ``force_sa1``,
``force_ra``, ``force_fast`` (SA1 + RA, 32 ms window and step, with filtered counts carried across
steps), ``texture`` (temporal features, 500 ms), ``texture_rate``, ``texture_both``,
``texture_spectral`` (SA1 + RA + PC spectra in 1 ms bins, 200 ms), ``texture_spatial`` (SA1 + RA + PC
phase locking on a spatial-frequency axis and interval histograms on a spatial-period axis, with the
scanning speed as a second input, 1 ms bins, 200 ms).
Sweep models (``sweep/``): force SA1 + RA per other decoding window, the stateful force model per
other step, the spectral texture model per other window, the spatial texture model per other window, texture per feature set and
other inference window (the product models are the sweeps' 128 ms and 500 ms points), and texture (temporal, 500 ms) per PC causal preprocessing window (the paper's
Fig. 16: the spikes are re-encoded with that causal PVDF window).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from touchreal_client import features as F

FORCE_CONFIGS: dict[str, tuple[str, ...]] = {"SA1": ("SA1",), "RA": ("RA",), "SA1+RA": ("SA1", "RA")}
FORCE_WINDOW_MS = 128.0
FORCE_SWEEP_MS = (4.0, 8.0, 16.0, 32.0, 64.0, 96.0, 128.0, 256.0)
FAST_WINDOW_MS = 32.0  #: the stateful force model: window = step = the service's update interval
FAST_SWEEP_MS = (8.0, 16.0, 32.0)
FAST_TAUS_MS = (32.0, 64.0, 128.0, 256.0, 512.0, 1024.0)  #: time constants of its filtered counts
TEXTURE_SETS = ("rate", "temporal", "both")
#: the spike-timing texture decoder: SA1, RA and PC in 1 ms bins, spectra inside the graph, MLP
SPECTRAL_CLASSES = ("SA1", "RA", "PC")
SPECTRAL_BIN_MS = 1.0
SPECTRAL_WINDOW_MS = 200.0
SPECTRAL_SWEEP_MS = (100.0, 200.0, 500.0)
#: the scanning texture decoder: the same classes and bins, features on a spatial-frequency axis (speed input)
SPATIAL_WINDOW_MS = 200.0
SPATIAL_SWEEP_MS = (100.0, 200.0, 500.0)
TEXTURE_WINDOW_MS = 500.0
TEXTURE_SWEEP_MS = (100.0, 200.0, 300.0, 400.0, 500.0, 750.0)
PRE_WINDOW_SWEEP_MS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0)
TASKS = ("force", "texture")
STEP_MS = F.STEP_US / 1000
BIN_MS = F.BIN_US / 1000


@dataclass(frozen=True)
class ModelSpec:
    """One decoder to train: what it reads and where its metrics go."""

    name: str
    task: str  #: force | texture
    classes: tuple[str, ...]
    window_ms: float
    features: str  #: counts (force) or a texture feature set
    folder: str = ""  #: "" (product) or "sweep"
    pvdf_window_ms: float | None = None  #: spikes re-encoded with this causal PVDF window (Fig. 16)
    state_taus_ms: tuple[float, ...] = ()  #: force: filtered counts carried across steps (window = step)
    bin_ms: float = BIN_MS  #: count bin width

    @property
    def step_ms(self) -> float:
        """Decoding step (ms): the window for a stateful model, else the service's 32 ms."""
        return self.window_ms if self.state_taus_ms else STEP_MS

    def metric_keys(self, metrics: dict) -> dict:
        """This model's metrics under their METRICS.json keys (e.g. ``force.SA1+RA.r2``,
        ``force.window.64ms.SA1+RA.r2``, ``texture.temporal.acc_500ms``)."""
        out: dict = {}
        if self.task == "force":
            config = "+".join(self.classes)
            if self.state_taus_ms:
                if self.window_ms == FAST_WINDOW_MS:
                    out.update({f"force.fast.{config}.{k}": v for k, v in metrics.items()})
                out.update({f"force.fast.window.{self.window_ms:g}ms.{config}.{k}": v for k, v in metrics.items() if not isinstance(v, list)})
                return out
            if self.window_ms == FORCE_WINDOW_MS:
                out.update({f"force.{config}.{k}": v for k, v in metrics.items()})
            # the sweep's entry: scalars only (the per-trial list is under force.<config> once)
            out.update({f"force.window.{self.window_ms:g}ms.{config}.{k}": v for k, v in metrics.items() if not isinstance(v, list)})
            return out
        pre = f"texture.prewindow.{self.pvdf_window_ms:g}ms." if self.pvdf_window_ms is not None else "texture."
        head = f"{pre}{self.features}.acc_{self.window_ms:g}ms"
        return {head: metrics["acc"], f"{head}_fold_mean": metrics["acc_fold_mean"], f"{head}_fold_std": metrics["acc_fold_std"],
                f"{head}_folds": metrics["acc_folds"], f"{head}_windows": metrics["n_windows"],
                f"{head}_trials_without_window": metrics["n_trials_without_window"],
                f"{head}_chance_majority": metrics["chance_majority"],
                **({f"{head}_by_speed_mm_s": metrics["acc_by_speed_mm_s"]} if "acc_by_speed_mm_s" in metrics else {})}


def _ms(x: float) -> str:
    return f"{x:g}ms"


def plan(tasks: Sequence[str] = TASKS, sweeps: bool = True) -> list[ModelSpec]:
    """The models to train for ``tasks``; ``sweeps`` adds the window sweeps."""
    specs: list[ModelSpec] = []
    if "force" in tasks:
        for config, classes in FORCE_CONFIGS.items():
            name = "force" if config == "SA1+RA" else f"force_{config.lower()}"
            specs.append(ModelSpec(name, "force", classes, FORCE_WINDOW_MS, "counts"))
        specs.append(ModelSpec("force_fast", "force", FORCE_CONFIGS["SA1+RA"], FAST_WINDOW_MS, "counts", state_taus_ms=FAST_TAUS_MS))
        if sweeps:
            for w in (w for w in FORCE_SWEEP_MS if w != FORCE_WINDOW_MS):
                specs.append(ModelSpec(f"force_w{_ms(w)}", "force", FORCE_CONFIGS["SA1+RA"], w, "counts", "sweep"))
            for w in (w for w in FAST_SWEEP_MS if w != FAST_WINDOW_MS):
                specs.append(ModelSpec(f"force_fast_w{_ms(w)}", "force", FORCE_CONFIGS["SA1+RA"], w, "counts", "sweep",
                                       state_taus_ms=FAST_TAUS_MS))
    if "texture" in tasks:
        for fs in TEXTURE_SETS:
            name = "texture" if fs == "temporal" else f"texture_{fs}"
            specs.append(ModelSpec(name, "texture", ("PC",), TEXTURE_WINDOW_MS, fs))
        if sweeps:
            for fs in TEXTURE_SETS:
                for w in (w for w in TEXTURE_SWEEP_MS if w != TEXTURE_WINDOW_MS):
                    specs.append(ModelSpec(f"texture_{fs}_w{_ms(w)}", "texture", ("PC",), w, fs, "sweep"))
        specs.append(ModelSpec("texture_spectral", "texture", SPECTRAL_CLASSES, SPECTRAL_WINDOW_MS, "spectral", bin_ms=SPECTRAL_BIN_MS))
        if sweeps:
            for w in (w for w in SPECTRAL_SWEEP_MS if w != SPECTRAL_WINDOW_MS):
                specs.append(ModelSpec(f"texture_spectral_w{_ms(w)}", "texture", SPECTRAL_CLASSES, w, "spectral", "sweep",
                                       bin_ms=SPECTRAL_BIN_MS))
        specs.append(ModelSpec("texture_spatial", "texture", SPECTRAL_CLASSES, SPATIAL_WINDOW_MS, "spatial", bin_ms=SPECTRAL_BIN_MS))
        if sweeps:
            for w in (w for w in SPATIAL_SWEEP_MS if w != SPATIAL_WINDOW_MS):
                specs.append(ModelSpec(f"texture_spatial_w{_ms(w)}", "texture", SPECTRAL_CLASSES, w, "spatial", "sweep",
                                       bin_ms=SPECTRAL_BIN_MS))
            for pw in PRE_WINDOW_SWEEP_MS:
                specs.append(ModelSpec(f"texture_temporal_w{_ms(TEXTURE_WINDOW_MS)}_pre{_ms(pw)}", "texture", ("PC",),
                                       TEXTURE_WINDOW_MS, "temporal", "sweep", pw))
    return specs


def spec_from_meta(meta: dict) -> ModelSpec:
    """The spec a model was trained from (its metadata records it)."""
    state = meta.get("state") or {}
    return ModelSpec(meta["name"], meta["task"], tuple(meta["classes"]), float(meta["window_ms"]), meta["features"]["set"],
                     meta["training"].get("folder", ""), meta["params"].get("pvdf_window_ms"),
                     tuple(float(t) for t in state.get("taus_ms", ())), float(meta["bin_ms"]))
