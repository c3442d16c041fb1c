"""Decoder features computed from binned counts, twice from one definition: numpy (training, the
scikit-learn side of the parity tests) and ONNX operators (inside the exported graph).

Every feature is a fixed linear map of the counts or a simple elementwise function of one (the
``spatial`` set's interval histograms: a sort of the spike bins, differences and a kernel), so the
constant matrices and grids built here are the single definition both sides use.

* ``counts``: the flattened input, bins oldest -> newest, classes innermost (force models).
* ``temporal``: Gaussian-smoothed PSTH (sigma 20 ms, truncated at 3 sigma, each row renormalised
  inside the window so the edges are not attenuated), one value per bin.
* ``rate``: rate (Hz), variance of the bin counts, fraction of non-empty bins (the bin-level
  stand-ins for the paper's ISI statistics: a model input of 10 ms counts carries no exact ISI)
  and the mean DFT magnitude of the count sequence per 10 Hz band, (0, 10] ... (40, 50] Hz,
  normalised by the number of bins.
* ``both``: ``temporal`` then ``rate``.
* ``spectral`` (any classes, fine bins): per class its spike count in the window, then the
  magnitude of the Hann-tapered Fourier transform of its count sequence at 4, 5, ... 80 Hz
  (:data:`SPECTRUM_HZ`, evaluated at these frequencies whatever the window), divided by
  ``max(count, 1)``: a count-normalised line spectrum that carries the spike timing (a texture's
  temporal frequency speed / spacing and its harmonics) apart from the rate.
* ``spatial`` (any classes, fine bins, and the scanning speed ``v`` (mm/s) as a second input): per
  class its spikes per mm of scanned surface, ``count / (v * window)``, then the magnitude of the
  Hann-tapered Fourier transform of its count sequence at the temporal frequencies ``f = k * v``
  for the spatial frequencies ``k`` of :data:`SPATIAL_CYCLES_PER_MM` (log-spaced), divided by
  ``max(count, 1)``: each class's phase locking (vector strength) to a surface period ``1 / k``
  mm, the same numbers for one surface at any speed. The phases ``2 pi k v t`` are computed in the
  graph from ``v``. Then per class one histogram of its spike intervals expressed in mm of scanned
  surface, ``(t_{i+o} - t_i) * v``, from each spike to each of its next :data:`INTERVAL_ORDERS`
  spikes (1-4: pooled, so a surface that draws two or three spikes per tooth instead of one keeps
  its peaks at the period and its multiples), on the log-spaced periods of :data:`INTERVAL_MM`
  (triangular kernel one grid step wide on the log axis, so each interval adds 1 split over its two
  nearest periods), divided by ``max(number of intervals, 1)``. An interval measures a period to
  the spike timing (``v * bin``), however few teeth the window holds, where the Fourier magnitude
  resolves only ``1 / (v * window)`` cycles/mm; normalised by the number of intervals, it does not
  scale with the spike count. The spike times are the bins holding at least one spike, the latest
  :meth:`FeatureSpec.max_spikes` of them (``TopK`` in the graph).

A spec with a ``state`` filter (:class:`~touchreal.decoding.state.ExpFilter`, force models at
closed-loop speed) appends the filtered counts carried across steps to ``counts``; its graph has a
second input ``state`` and a second output ``state_out``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .state import STATE_INPUT, STATE_OUTPUT, ExpFilter

FEATURE_SETS = ("counts", "temporal", "rate", "both", "spectral", "spatial")
SMOOTH_SIGMA_MS = 20.0
BANDS_HZ = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0), (40.0, 50.0))
SPECTRUM_HZ = (4.0, 80.0, 1.0)  #: spectral set: first, last, step of the evaluated frequencies (Hz)
#: spatial set: first, last (cycles per mm) and number of its log-spaced spatial frequencies: surface
#: periods 0.25-6.7 mm, so the fundamental and second harmonic of periods of about 0.5-6 mm
SPATIAL_CYCLES_PER_MM = (0.15, 4.0, 70)
#: spatial set, interval histograms: first, last (mm) and number of their log-spaced periods
INTERVAL_MM = (0.2, 8.0, 48)
INTERVAL_ORDERS = (1, 2, 3, 4)  #: spatial set: intervals from each spike to its next 1, 2, 3 and 4 spikes, one histogram
INTERVAL_MAX_RATE_HZ = 400.0  #: spatial set: a window's interval histograms read its latest rate x window spikes per class
SPATIAL_CHUNK = 1024  #: rows per numpy pass of the spatial set
SPEED_INPUT = "speed_mm_s"  #: the spatial set's second input: scanning speed (mm/s), (batch, 1) or (1, 1)


@dataclass(frozen=True)
class FeatureSpec:
    """What turns a ``(batch, n_bins, n_classes)`` counts tensor into a feature matrix."""

    kind: str  #: one of FEATURE_SETS
    n_bins: int
    n_classes: int
    bin_ms: float
    window_ms: float
    state: ExpFilter | None = None  #: filtered counts carried across steps (``counts`` only)

    def __post_init__(self) -> None:
        if self.kind not in FEATURE_SETS:
            raise ValueError(f"unknown feature set {self.kind!r}; expected one of {FEATURE_SETS}")
        if self.kind not in ("counts", "spectral", "spatial") and self.n_classes != 1:
            raise ValueError(f"feature set {self.kind!r} takes one class")
        if self.state is not None and (self.kind != "counts" or self.state.n_bins != self.n_bins
                                       or self.state.n_classes != self.n_classes or self.state.step_ms != self.window_ms):
            raise ValueError("a state filter goes with 'counts' features of its own bins and classes, window = step")

    # ---------------------------------------------------------------- constant matrices
    def smoothing(self) -> np.ndarray:
        """(n_bins, n_bins) row-normalised Gaussian kernel: ``temporal = counts @ S.T``."""
        sigma = SMOOTH_SIGMA_MS / self.bin_ms
        i = np.arange(self.n_bins)
        d = i[:, None] - i[None, :]
        g = np.where(np.abs(d) <= 3 * sigma, np.exp(-0.5 * (d / sigma) ** 2), 0.0)
        return g / g.sum(axis=1, keepdims=True)

    def dft(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cos, sin, band) matrices: ``|X_k| = hypot(c @ cos, c @ sin) / n``, ``bands = |X| @ band``."""
        n = self.n_bins
        k = np.arange(1, n // 2 + 1)
        j = np.arange(n)
        arg = 2 * np.pi * np.outer(j, k) / n
        freq = k * (1000.0 / self.bin_ms) / n
        band = np.zeros((k.size, len(BANDS_HZ)))
        for b, (lo, hi) in enumerate(BANDS_HZ):
            sel = (freq > lo) & (freq <= hi)
            if sel.any():
                band[sel, b] = 1.0 / sel.sum()
        return np.cos(arg) / n, np.sin(arg) / n, band

    def spectrum(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(cos, sin, total, expand) matrices on the flattened counts (bins oldest first, classes
        innermost): ``re = flat @ cos``, ``im = flat @ sin`` ((n_classes * n_freqs) columns, class-major),
        ``count = flat @ total`` (n_classes), ``count @ expand`` repeats each class's count per frequency."""
        lo, hi, df = SPECTRUM_HZ
        freqs = np.arange(lo, hi + df / 2, df)
        nb, nc, nf = self.n_bins, self.n_classes, freqs.size
        t = (np.arange(nb) + 0.5) * self.bin_ms / 1000.0  # bin centres (s)
        taper = np.hanning(nb + 2)[1:-1]
        cos = np.zeros((nb * nc, nc * nf))
        sin = np.zeros((nb * nc, nc * nf))
        for c in range(nc):
            cos[c::nc, c * nf:(c + 1) * nf] = np.cos(2 * np.pi * np.outer(t, freqs)) * taper[:, None]
            sin[c::nc, c * nf:(c + 1) * nf] = np.sin(2 * np.pi * np.outer(t, freqs)) * taper[:, None]
        return (cos, sin, *self.count_matrices(nf))

    @property
    def needs_speed(self) -> bool:
        """True when the features read the scanning speed (:data:`SPEED_INPUT`) beside the counts."""
        return self.kind == "spatial"

    def spatial_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(spatial frequencies k (cycles/mm), bin-centre times x k (s cycles/mm, (n_bins, n_k)), Hann
        taper (n_bins,)): the phase of bin ``b`` at ``k`` for speed ``v`` is ``2 pi v * tk[b, k]``."""
        lo, hi, n = SPATIAL_CYCLES_PER_MM
        k = np.geomspace(lo, hi, n)
        t = (np.arange(self.n_bins) + 0.5) * self.bin_ms / 1000.0
        return k, np.outer(t, k), np.hanning(self.n_bins + 2)[1:-1]

    def interval_grid(self) -> tuple[np.ndarray, float]:
        """(log of the interval histograms' periods (mm), log step between them)."""
        lo, hi, n = INTERVAL_MM
        centres = np.geomspace(lo, hi, n)
        return np.log(centres), float(np.log(centres[1] / centres[0]))

    def max_spikes(self) -> int:
        """Spikes per class (the latest) the interval histograms read: ``ceil(INTERVAL_MAX_RATE_HZ x window)``,
        at most one per bin, at least the highest interval order + 1."""
        k = int(np.ceil(INTERVAL_MAX_RATE_HZ * self.window_ms / 1000.0 - 1e-9))
        return int(min(self.n_bins, max(k, max(INTERVAL_ORDERS) + 1)))

    # ---------------------------------------------------------------------- names
    def names(self) -> list[str]:
        """Feature order of the matrix fed to the estimator."""
        if self.kind == "counts":
            counts = [f"count[bin{b}][c{c}]" for b in range(self.n_bins) for c in range(self.n_classes)]
            return counts + ([] if self.state is None else self.state.names([f"c{c}" for c in range(self.n_classes)]))
        if self.kind == "spectral":
            lo, hi, df = SPECTRUM_HZ
            freqs = np.arange(lo, hi + df / 2, df)
            return [f"count[c{c}]" for c in range(self.n_classes)] + [
                f"spectrum[c{c}][{f:g}Hz]" for c in range(self.n_classes) for f in freqs]
        if self.kind == "spatial":
            k = self.spatial_grid()[0]
            mm = np.exp(self.interval_grid()[0])
            return [f"per_mm[c{c}]" for c in range(self.n_classes)] + [
                f"locking[c{c}][{x:.4g}/mm]" for c in range(self.n_classes) for x in k] + [
                f"intervals[c{c}][{d:.3g}mm]" for c in range(self.n_classes) for d in mm]
        temporal = [f"psth[bin{b}]" for b in range(self.n_bins)]
        rate = ["rate_hz", "count_var", "frac_nonempty"] + [f"dft_{lo:g}_{hi:g}Hz" for lo, hi in BANDS_HZ]
        return {"temporal": temporal, "rate": rate, "both": temporal + rate}[self.kind]

    # ---------------------------------------------------------------------- numpy
    def transform(self, counts: np.ndarray, groups: np.ndarray | None = None, speed: np.ndarray | None = None) -> np.ndarray:
        """Features of a ``(batch, n_bins, n_classes)`` counts tensor, float32 like the graph.

        With a state filter the rows are consecutive steps and ``groups`` (trial of each row) is
        required: the state restarts at zero on each trial (:meth:`ExpFilter.sequence`). The
        ``spatial`` set requires ``speed``: scanning speed (mm/s) per row, ``(batch, 1)``, or ``(1, 1)``."""
        c = np.asarray(counts, dtype=np.float32)
        if c.ndim != 3 or c.shape[1:] != (self.n_bins, self.n_classes):
            raise ValueError(f"counts must be (batch, {self.n_bins}, {self.n_classes}), got {c.shape}")
        x = c.reshape(c.shape[0], -1)
        if self.kind == "counts":
            if self.state is None:
                return x
            if groups is None or len(groups) != x.shape[0]:
                raise ValueError("stateful features need the trial of every row (groups)")
            return np.concatenate([x, self.state.sequence(c, groups)], axis=1)
        if self.kind == "spatial":
            return self._spatial(c, x, speed)
        if self.kind == "spectral":
            cos, sin, total, expand = (m.astype(np.float32) for m in self.spectrum())
            re, im = x @ cos, x @ sin
            n = x @ total
            mag = np.sqrt(re * re + im * im)
            return np.concatenate([n, mag / np.maximum(n @ expand, np.float32(1.0))], axis=1)
        parts = []
        if self.kind in ("temporal", "both"):
            parts.append(x @ self.smoothing().T.astype(np.float32))
        if self.kind in ("rate", "both"):
            cos, sin, band = (m.astype(np.float32) for m in self.dft())
            mean = x @ np.full((self.n_bins, 1), 1.0 / self.n_bins, np.float32)
            mean_sq = (x * x) @ np.full((self.n_bins, 1), 1.0 / self.n_bins, np.float32)
            frac = np.minimum(x, np.float32(1.0)) @ np.full((self.n_bins, 1), 1.0 / self.n_bins, np.float32)
            re, im = x @ cos, x @ sin
            mag = np.sqrt(re * re + im * im)
            rate = mean * np.float32(1000.0 / self.bin_ms)
            parts += [rate, mean_sq - mean * mean, frac, mag @ band.astype(np.float32)]
        return np.concatenate(parts, axis=1)

    def _spatial(self, c: np.ndarray, flat: np.ndarray, speed: np.ndarray | None) -> np.ndarray:
        if speed is None:
            raise ValueError("spatial features need the scanning speed (mm/s) of every row")
        v = np.asarray(speed, np.float32).reshape(-1, 1)
        if v.shape[0] not in (1, c.shape[0]):
            raise ValueError(f"speed must be (batch, 1) or (1, 1), got {np.shape(speed)} for {c.shape[0]} rows")
        _, tk, taper = self.spatial_grid()
        two_pi_tk, tap = (2 * np.pi * tk).astype(np.float32)[None], taper.astype(np.float32)[:, None]
        xt = np.transpose(c, (0, 2, 1))
        mag = np.empty((c.shape[0], self.n_classes * tk.shape[1]), np.float32)
        for a in range(0, c.shape[0], SPATIAL_CHUNK):  # the phases are (rows, n_bins, n_k): bounded memory
            rows = slice(a, a + SPATIAL_CHUNK)
            phase = (v if v.shape[0] == 1 else v[rows])[:, :, None] * two_pi_tk
            re, im = xt[rows] @ (np.cos(phase) * tap), xt[rows] @ (np.sin(phase) * tap)
            mag[rows] = np.sqrt(re * re + im * im).reshape(re.shape[0], -1)
        total, expand = (m.astype(np.float32) for m in self.count_matrices(SPATIAL_CYCLES_PER_MM[2]))
        n = flat @ total
        per_mm = n / (v * np.float32(self.window_ms / 1000.0))
        return np.concatenate([per_mm, mag / np.maximum(n @ expand, np.float32(1.0)), self._intervals(xt, v)], axis=1)

    def _intervals(self, xt: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Interval histograms on the spatial-period axis of ``(batch, n_classes, n_bins)`` counts, float32."""
        nb, k = self.n_bins, self.max_spikes()
        lc, step = self.interval_grid()
        lc, step = lc.astype(np.float32), np.float32(step)
        v3 = v.reshape(-1, 1, 1)
        out = []
        for a in range(0, xt.shape[0], SPATIAL_CHUNK):
            rows = slice(a, a + SPATIAL_CHUNK)
            key = (xt[rows] > 0).astype(np.float32) * np.arange(1, nb + 1, dtype=np.float32)  # bin index + 1, 0 = no spike
            top = -np.sort(-key, axis=2)[:, :, :k]  # latest spikes first
            vr = v3 if v3.shape[0] == 1 else v3[rows]
            h = np.zeros((top.shape[0], self.n_classes, lc.size), np.float32)
            nv = np.zeros((top.shape[0], self.n_classes), np.float32)
            for o in INTERVAL_ORDERS:
                valid = (top[:, :, o:] > 0).astype(np.float32)
                d = (top[:, :, :-o] - top[:, :, o:]) * np.float32(self.bin_ms / 1000.0) * vr
                ld = np.log(np.maximum(d, np.float32(1e-3)))
                w = np.maximum(np.float32(1.0) - np.abs(ld[..., None] - lc) / step, np.float32(0.0)) * valid[..., None]
                h += w.sum(axis=2)
                nv += valid.sum(axis=2)
            out.append((h / np.maximum(nv, np.float32(1.0))[..., None]).reshape(h.shape[0], -1))
        return np.concatenate(out, axis=0).astype(np.float32)

    def _interval_nodes(self, xt: str, v3: str, node, const, nodes: list, inits: list) -> list[str]:
        """Graph of :meth:`_intervals`: the latest spike bins by ``TopK``, the intervals of every order side by
        side, each one's position ``u`` on the log-period grid, and its triangular weights ``1 - frac(u)`` and
        ``frac(u)`` added into bins ``floor(u)`` and ``floor(u) + 1`` (``ScatterElements``, reduction add):
        ``O(intervals)`` per taxel, not ``O(intervals x periods)``. Positions off the grid land in padding bins."""
        k = self.max_spikes()
        lc, step = self.interval_grid()
        n_mm, pad_lo = lc.size, 2

        def ints(name: str, *values: int) -> str:
            inits.append(numpy_helper.from_array(np.array(values, np.int64), name))
            return name

        idx = const("bin_index", np.arange(1, self.n_bins + 1))
        spiking = node("Cast", [node("Greater", [xt, const("zero", np.zeros(1))], "spiking_b")], "spiking", to=TensorProto.FLOAT)
        nodes.append(helper.make_node("TopK", [node("Mul", [spiking, idx], "spike_key"), ints("max_spikes", k)],
                                      ["spike_top", "spike_top_i"], axis=-1, largest=1, sorted=1))
        axis = ints("axis_k", 2)
        gaps, valids = [], []
        for o in INTERVAL_ORDERS:
            later = node("Slice", ["spike_top", ints(f"later{o}_s", 0), ints(f"later{o}_e", k - o), axis], f"later{o}")
            earlier = node("Slice", ["spike_top", ints(f"earlier{o}_s", o), ints(f"earlier{o}_e", k), axis], f"earlier{o}")
            gaps.append(node("Sub", [later, earlier], f"gap{o}"))
            valids.append(node("Cast", [node("Greater", [earlier, "zero"], f"valid{o}_b")], f"valid{o}", to=TensorProto.FLOAT))
        gap = node("Concat", gaps, "gaps", axis=2)
        valid = node("Concat", valids, "valid", axis=2)
        d = node("Mul", [gap, node("Mul", [v3, const("bin_s", np.full(1, self.bin_ms / 1000.0))], "mm_per_bin")], "gaps_mm")
        ld = node("Log", [node("Max", [d, const("gap_floor", np.full(1, 1e-3))], "gaps_floored")], "gaps_log")
        off = node("Sub", [ld, const("interval_log_first", np.full(1, lc[0]))], "gaps_off")
        u = node("Mul", [off, const("interval_inv_step", np.full(1, 1.0 / step))], "grid_pos")
        u = node("Clip", [u, const("grid_lo", np.full((), -pad_lo)), const("grid_hi", np.full((), n_mm + 1))], "grid_pos_c")
        lower = node("Floor", [u], "grid_floor")
        frac = node("Sub", [u, lower], "grid_frac")
        lo_f = node("Add", [lower, const("grid_pad", np.full(1, pad_lo))], "grid_lo_f")
        lo_i = node("Cast", [lo_f], "grid_lo_i", to=TensorProto.INT64)
        hi_i = node("Add", [lo_i, ints("one_i", 1)], "grid_hi_i")
        w_hi = node("Mul", [frac, valid], "w_hi")
        w_lo = node("Sub", [valid, w_hi], "w_lo")  # (1 - frac) * valid
        bc = node("Slice", [node("Shape", ["spike_top"], "top_shape"), ints("sh_s", 0), ints("sh_e", 2)], "bc_shape")
        shape = node("Concat", [bc, ints("grid_size", n_mm + pad_lo + 3)], "hist_shape", axis=0)
        nodes.append(helper.make_node("ConstantOfShape", [shape], ["hist_zero"],
                                      value=numpy_helper.from_array(np.zeros(1, np.float32))))
        index = node("Concat", [lo_i, hi_i], "grid_idx", axis=2)
        weight = node("Concat", [w_lo, w_hi], "grid_w", axis=2)
        nodes.append(helper.make_node("ScatterElements", ["hist_zero", index, weight], ["hist_padded"], axis=2, reduction="add"))
        hist = node("Slice", ["hist_padded", ints("hist_s", pad_lo), ints("hist_e", pad_lo + n_mm), axis], "hist")
        n_floor = node("Max", [node("ReduceSum", [valid, axis], "n_intervals", keepdims=1), const("interval_one", np.ones(1))],
                       "n_intervals_floor")
        return [node("Flatten", [node("Div", [hist, n_floor], "hist_norm")], "intervals", axis=1)]

    def count_matrices(self, n_freqs: int) -> tuple[np.ndarray, np.ndarray]:
        """(total, expand): ``count = flat @ total`` (n_classes) of the flattened counts, ``count @
        expand`` repeats each class's count for each of its ``n_freqs`` spectrum values."""
        total = np.zeros((self.n_bins * self.n_classes, self.n_classes))
        for c in range(self.n_classes):
            total[c::self.n_classes, c] = 1.0
        return total, np.kron(np.eye(self.n_classes), np.ones((1, n_freqs)))

    # ----------------------------------------------------------------------- ONNX
    def graph(self, opset: int, ir_version: int, input_name: str = "counts", output_name: str = "features") -> onnx.ModelProto:
        """The same transform as an ONNX model ``counts -> features`` (default-domain operators; a
        stateful spec also ``state -> state_out``)."""
        nodes: list[onnx.NodeProto] = []
        inits: list[onnx.TensorProto] = []

        def const(name: str, value: np.ndarray) -> str:
            inits.append(numpy_helper.from_array(np.asarray(value, np.float32), name))
            return name

        def node(op: str, inputs: list[str], out: str, **attrs) -> str:
            nodes.append(helper.make_node(op, inputs, [out], **attrs))
            return out

        plain = self.kind == "counts" and self.state is None
        flat = node("Flatten", [input_name], output_name if plain else "flat", axis=1)
        inputs = [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [None, self.n_bins, self.n_classes])]
        outputs = [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, [None, len(self.names())])]
        if self.state is not None:
            state_nodes, state_inits = self.state.nodes(flat)
            nodes += state_nodes
            inits += state_inits
            node("Concat", [flat, STATE_OUTPUT], output_name, axis=1)
            inputs.append(self.state.value_info(STATE_INPUT))
            outputs.append(self.state.value_info(STATE_OUTPUT))
        elif self.kind == "spatial":
            inputs.append(helper.make_tensor_value_info(SPEED_INPUT, TensorProto.FLOAT, [None, 1]))
            _, tk, taper = self.spatial_grid()
            total, expand = self.count_matrices(SPATIAL_CYCLES_PER_MM[2])
            inits.append(numpy_helper.from_array(np.array([-1, 1, 1], np.int64), "speed_shape"))
            v3 = node("Reshape", [SPEED_INPUT, "speed_shape"], "speed3")
            phase = node("Mul", [v3, const("two_pi_tk", 2 * np.pi * tk)], "phase")
            tap = const("taper", taper[:, None])
            cos = node("Mul", [node("Cos", [phase], "cos_raw"), tap], "cos")
            sin = node("Mul", [node("Sin", [phase], "sin_raw"), tap], "sin")
            xt = node("Transpose", [input_name], "counts_t", perm=[0, 2, 1])
            re = node("MatMul", [xt, cos], "re")
            im = node("MatMul", [xt, sin], "im")
            power = node("Add", [node("Mul", [re, re], "re2"), node("Mul", [im, im], "im2")], "power")
            mag = node("Flatten", [node("Sqrt", [power], "mag3")], "mag", axis=1)
            n = node("MatMul", [flat, const("total", total)], "n")
            per = node("Max", [node("MatMul", [n, const("expand", expand)], "n_per_k"), const("one", np.ones(1))], "n_floor")
            scanned = node("Mul", [SPEED_INPUT, const("window_s", np.full(1, self.window_ms / 1000.0))], "scanned_mm")
            hists = self._interval_nodes(xt, v3, node, const, nodes, inits)
            node("Concat", [node("Div", [n, scanned], "per_mm"), node("Div", [mag, per], "locking"), *hists], output_name, axis=1)
        elif self.kind == "spectral":
            cos, sin, total, expand = self.spectrum()
            re = node("MatMul", [flat, const("spec_cos", cos)], "re")
            im = node("MatMul", [flat, const("spec_sin", sin)], "im")
            n = node("MatMul", [flat, const("total", total)], "n")
            power = node("Add", [node("Mul", [re, re], "re2"), node("Mul", [im, im], "im2")], "power")
            mag = node("Sqrt", [power], "mag")
            per = node("Max", [node("MatMul", [n, const("expand", expand)], "n_per_freq"), const("one", np.ones(1))], "n_floor")
            node("Concat", [n, node("Div", [mag, per], "spectrum")], output_name, axis=1)
        elif self.kind != "counts":
            parts = []
            if self.kind in ("temporal", "both"):
                parts.append(node("MatMul", [flat, const("smooth_T", self.smoothing().T)], "psth"))
            if self.kind in ("rate", "both"):
                cos, sin, band = self.dft()
                avg = const("avg", np.full((self.n_bins, 1), 1.0 / self.n_bins))
                mean = node("MatMul", [flat, avg], "mean")
                sq = node("Mul", [flat, flat], "sq")
                mean_sq = node("MatMul", [sq, avg], "mean_sq")
                clip = node("Min", [flat, const("one", np.ones(1))], "occupied")
                frac = node("MatMul", [clip, avg], "frac")
                re = node("MatMul", [flat, const("dft_cos", cos)], "re")
                im = node("MatMul", [flat, const("dft_sin", sin)], "im")
                power = node("Add", [node("Mul", [re, re], "re2"), node("Mul", [im, im], "im2")], "power")
                mag = node("Sqrt", [power], "mag")
                bands = node("MatMul", [mag, const("band", band)], "bands")
                rate = node("Mul", [mean, const("per_s", np.full(1, 1000.0 / self.bin_ms))], "rate")
                var = node("Sub", [mean_sq, node("Mul", [mean, mean], "mean2")], "var")
                parts += [rate, var, frac, bands]
            node("Concat", parts, output_name, axis=1)
        g = helper.make_graph(nodes, f"features_{self.kind}", inputs, outputs, inits)
        return helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)], ir_version=ir_version)
