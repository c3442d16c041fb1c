"""Matplotlib figures of the evaluation report (Agg backend, PNG). Each function takes plain
arrays/dicts computed by :mod:`touchreal.analysis.metrics` and writes one file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

TS_COLOR = "#1f77b4"  # TouchSim (blue, as in the paper)
TR_COLOR = "#ff7f0e"  # TouchReal (orange)
DPI = 110


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def fig7_time_courses(path: Path, d: dict[str, Any]) -> Path:
    """Mean firing-rate time courses per class, TouchReal (left) beside TouchSim (right), with the
    measured force and the commanded indentation on top. ``d``: t (s), force, depth, and
    rates[source][cls] = (mean, lo, hi), title."""
    classes = list(d["rates"]["TouchReal"])
    fig, axes = plt.subplots(len(classes) + 1, 2, figsize=(10, 2.0 * (len(classes) + 1)), sharex=True, squeeze=False)
    for col, source in enumerate(("TouchReal", "TouchSim")):
        ax = axes[0, col]
        ax.plot(d["t_stim"], d["force"], color="k", lw=1.2, label="force (ST) [N]")
        ax.set_ylabel("force [N]")
        ax2 = ax.twinx()
        ax2.plot(d["t_stim"], d["depth"], color="0.5", lw=1.0, ls="--", label="commanded depth [mm]")
        ax2.set_ylabel("depth [mm]")
        ax.set_title(f"{source}")
        color = TR_COLOR if source == "TouchReal" else TS_COLOR
        for row, cls in enumerate(classes, start=1):
            mean, lo, hi = d["rates"][source][cls]
            a = axes[row, col]
            a.plot(d["t"], mean, color=color, lw=1.2)
            a.fill_between(d["t"], lo, hi, color=color, alpha=0.25, lw=0)
            a.set_ylabel(f"{cls} [Hz]")
    for col in range(2):
        axes[-1, col].set_xlabel("time from commanded onset [s]")
    fig.suptitle(d.get("title", ""), fontsize=10)
    fig.subplots_adjust(wspace=0.45)
    return _save(fig, path)


def fig8_vr_boxes(path: Path, d: dict[str, dict[str, np.ndarray]], ratios: dict[str, float], tau_ms: float) -> Path:
    """Box plots of per-condition mean VR distances (TS-TS, TR-TR, TS-TR) per class."""
    classes = list(d)
    fig, axes = plt.subplots(1, len(classes), figsize=(3.6 * len(classes), 3.6), squeeze=False)
    labels = (("ts_ts", "TouchSim-\nTouchSim"), ("tr_tr", "TouchReal-\nTouchReal"), ("ts_tr", "TouchSim-\nTouchReal"))
    for ax, cls in zip(axes[0], classes):
        data = [np.asarray(d[cls][k], float) for k, _ in labels]
        data = [x[np.isfinite(x)] for x in data]
        bp = ax.boxplot(data, whis=1.5, showfliers=True, patch_artist=True, flierprops={"markersize": 2})
        for patch, c in zip(bp["boxes"], (TS_COLOR, TR_COLOR, "#2ca02c")):
            patch.set_facecolor(c)
            patch.set_alpha(0.5)
        ax.set_xticks([1, 2, 3], [lab for _, lab in labels], fontsize=8)
        ax.set_title(f"{cls}  (inter/intra = {ratios.get(cls, float('nan')):.2f})", fontsize=10)
        ax.set_ylabel(f"VR distance (tau = {tau_ms:g} ms)")
    fig.tight_layout()
    return _save(fig, path)


def fig9_frequency(path: Path, freqs: np.ndarray, d: dict[str, dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]]) -> Path:
    """Firing rate against sine frequency with 95 % CIs, TouchSim and TouchReal, per class."""
    classes = list(d)
    fig, axes = plt.subplots(1, len(classes), figsize=(4.2 * len(classes), 3.4), squeeze=False)
    for ax, cls, letter in zip(axes[0], classes, "ABCDEF"):
        for source, color in (("TouchSim", TS_COLOR), ("TouchReal", TR_COLOR)):
            m, lo, hi = (np.asarray(v, float) for v in d[cls][source])
            ax.errorbar(freqs, m, yerr=[m - lo, hi - m], color=color, marker="o", capsize=3, label=source)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("firing rate [Hz]")
        ax.set_title(f"({letter}) {cls}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def fig10_maps(path: Path, maps: list[dict[str, Any]]) -> Path:
    """Interpolated spatial maps; ``maps`` items: title, map (SpatialMap), x, y (samples)."""
    n = len(maps)
    cols = min(3, n) or 1
    rows = int(np.ceil(n / cols)) or 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, item in zip(axes.ravel(), maps):
        m = item["map"]
        im = ax.imshow(m.values, origin="lower", extent=(m.x_mm[0], m.x_mm[-1], m.y_mm[0], m.y_mm[-1]), cmap="viridis")
        ax.scatter(item["x"], item["y"], s=4, c="white")
        ax.set_title(item["title"], fontsize=9)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        fig.colorbar(im, ax=ax, fraction=0.046, label="mean spikes / trial")
    fig.tight_layout()
    return _save(fig, path)


def fig10_radial(path: Path, d: dict[str, list[dict[str, Any]]]) -> Path:
    """Radial profiles per class: items have label, radii, TouchReal mean, TouchSim mean."""
    classes = list(d)
    fig, axes = plt.subplots(1, len(classes), figsize=(4.0 * len(classes), 3.2), squeeze=False)
    for ax, cls in zip(axes[0], classes):
        for i, item in enumerate(d[cls]):
            c = plt.cm.viridis(i / max(1, len(d[cls]) - 1))
            ax.plot(item["radii"], item["tr"], color=c, marker="o", ms=3, label=f"{item['label']} TR")
            ax.plot(item["radii"], item["ts"], color=c, ls=":", label=f"{item['label']} TS")
        ax.set_xlabel("radial offset [mm]")
        ax.set_ylabel("mean spikes / trial")
        ax.set_title(cls)
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return _save(fig, path)


def fig10_area(path: Path, d: dict[str, dict[str, Any]], threshold: float) -> Path:
    """Response area at the threshold against depth / frequency, per class (TR and TS)."""
    classes = list(d)
    fig, axes = plt.subplots(1, len(classes), figsize=(3.6 * len(classes), 3.0), squeeze=False)
    for ax, cls in zip(axes[0], classes):
        x = d[cls]["levels"]
        ax.plot(x, d[cls]["tr"], marker="o", color=TR_COLOR, label="TouchReal")
        ax.plot(x, d[cls]["ts"], marker="s", color=TS_COLOR, label="TouchSim")
        ax.set_xlabel(d[cls]["xlabel"])
        ax.set_ylabel(f"area >= {threshold:g} spikes [mm^2]")
        ax.set_title(cls)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def fig10_sweep(path: Path, d: dict[str, dict[str, Any]]) -> Path:
    """Threshold-sweep heat maps: area (mm^2) by level (rows) x threshold (columns), TouchReal."""
    classes = list(d)
    fig, axes = plt.subplots(1, len(classes), figsize=(4.2 * len(classes), 3.0), squeeze=False)
    for ax, cls in zip(axes[0], classes):
        a = np.asarray(d[cls]["area"], float)
        th = np.asarray(d[cls]["thresholds"])
        im = ax.imshow(a, aspect="auto", origin="lower", cmap="magma", extent=(th[0] - 0.5, th[-1] + 0.5, -0.5, a.shape[0] - 0.5))
        ax.set_yticks(range(a.shape[0]), [str(v) for v in d[cls]["levels"]])
        ax.set_xlabel("spike-count threshold")
        ax.set_ylabel(d[cls]["xlabel"])
        ax.set_title(f"{cls} (TouchReal)")
        fig.colorbar(im, ax=ax, label="area [mm^2]")
    fig.tight_layout()
    return _save(fig, path)


def fig11_anisotropy(path: Path, d: dict[str, dict[str, Any]]) -> Path:
    """Top: normalised angular profiles (polar); bottom: AI_2 against depth / frequency."""
    classes = list(d)
    fig = plt.figure(figsize=(3.8 * len(classes), 6.4))
    for i, cls in enumerate(classes):
        ax = fig.add_subplot(2, len(classes), i + 1, projection="polar")
        ang = np.deg2rad(np.asarray(d[cls]["angles"], float))
        for source, color in (("tr", TR_COLOR), ("ts", TS_COLOR)):
            m = np.asarray(d[cls][f"profile_{source}"], float)
            s = np.asarray(d[cls][f"profile_{source}_std"], float)
            if ang.size and np.all(np.isfinite(m)):
                a = np.concatenate((ang, ang[:1]))
                ax.plot(a, np.concatenate((m, m[:1])), color=color, label="TouchReal" if source == "tr" else "TouchSim")
                ax.fill_between(a, np.concatenate((m - s, m[:1] - s[:1])), np.concatenate((m + s, m[:1] + s[:1])), color=color, alpha=0.2)
        axis = d[cls].get("axis_tr", float("nan"))
        if np.isfinite(axis):
            r = np.nanmax(np.asarray(d[cls]["profile_tr"], float)) if ang.size else 1.0
            for a0 in (axis, axis + 180.0):
                ax.plot([np.deg2rad(a0)] * 2, [0, r], "k--", lw=0.8)
        ax.set_title(cls, fontsize=10)
        if i == 0:
            ax.legend(fontsize=7, loc="lower left")
        bx = fig.add_subplot(2, len(classes), len(classes) + i + 1)
        bx.plot(d[cls]["levels"], d[cls]["ai2_tr"], marker="o", color=TR_COLOR, label="TouchReal")
        bx.plot(d[cls]["levels"], d[cls]["ai2_ts"], marker="s", color=TS_COLOR, label="TouchSim")
        bx.set_xlabel(d[cls]["xlabel"])
        bx.set_ylabel("AI_2")
        bx.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def fig12_window(path: Path, d: dict[str, Any]) -> Path:
    """(A) mean TS-TR VR distance vs causal window, TS-TS dashed; (B) mean spike-count error."""
    w = np.asarray(d["windows_ms"], float)
    classes = list(d["vr"])
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    for i, cls in enumerate(classes):
        c = f"C{i}"
        a.plot(w, d["vr"][cls], marker="o", color=c, label=cls)
        a.axhline(d["ts_ts"][cls], color=c, ls="--", lw=0.8)
        b.plot(w, 100.0 * np.asarray(d["count_error"][cls], float), marker="o", color=c, label=cls)
    for ax in (a, b):
        ax.set_xscale("log", base=2)
        ax.set_xticks(w, [f"{v:g}" for v in w])
        ax.set_xlabel("causal window [ms]")
        ax.legend(fontsize=8)
    a.set_ylabel("mean VR distance TS-TR")
    a.set_title("(A) VR distance (dashed: TouchSim-TouchSim)")
    b.set_ylabel("mean spike-count error [%]")
    b.set_title("(B) spike-count error")
    fig.tight_layout()
    return _save(fig, path)
