"""Causal frame-based STFT -> spectral gate -> inverse STFT with overlap-add (PVDF, 2 kHz).

Frames of N samples (the causal window) advance by H = N / 4 samples; each frame is Hann-windowed
(periodic Hann, which sums to a constant 2 at 75 % overlap), transformed with a real FFT, every
bin whose magnitude is below its threshold is multiplied by ``attenuation``, and the inverse FFT is
overlap-added. Output sample n is final once every frame covering it is processed, i.e. once input
sample n + N - H - 1 + (H - 1 - n mod H) has arrived: the stage's latency is about one window. Frame boundaries are fixed by the
absolute sample index, so the output does not depend on how the input is chunked. The stream is
preceded by N - H virtual zeros so the output starts at input sample 0.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.fft
from numpy.lib.stride_tricks import as_strided
from scipy import signal

from .parallel import split_run


def frame_length(window_ms: float, fs_hz: float) -> int:
    """Frame length (samples) for a window: rounded to a multiple of 4, at least 8."""
    return max(8, 4 * int(round(window_ms * fs_hz / 1000.0 / 4.0)))


@lru_cache(maxsize=32)
def hann_window(n: int, dtype: str) -> np.ndarray:
    """Periodic Hann window of ``n`` samples in ``dtype`` (read-only: gates built per woken taxel share it)."""
    w = signal.get_window("hann", n, fftbins=True).astype(dtype)
    w.flags.writeable = False
    return w


class StftGate:
    """Stateful spectral gate over (n, n_taxels) chunks.

    ``thresholds`` (n_bins,) are magnitude thresholds on the rfft of a Hann-windowed frame (V);
    ``None`` keeps every bin (the stage is then an exact delay-free identity on the clock).
    All arithmetic is in ``dtype``: float64, or float32 with the spectrum in complex64 (scipy.fft
    keeps single precision; the thresholds are rounded to float32).
    """

    def __init__(
        self, n: int, n_taxels: int = 1, thresholds: np.ndarray | None = None, attenuation: float = 0.05, dtype: type = np.float64
    ):
        if n < 8 or n % 4:
            raise ValueError("frame length must be a multiple of 4, >= 8")
        self.n, self.hop = n, n // 4
        self.n_taxels = n_taxels
        self.dtype = np.dtype(dtype)
        self.window = hann_window(n, self.dtype.str)
        self.norm = self.window.sum() / self.dtype.type(self.hop)  # constant overlap-add gain (2.0 for Hann at N/4)
        self.thresholds = None if thresholds is None else np.asarray(thresholds, dtype=np.float64).astype(self.dtype)
        if self.thresholds is not None and self.thresholds.shape != (n // 2 + 1,):
            raise ValueError(f"thresholds must have {n // 2 + 1} bins")
        self.attenuation = float(attenuation)
        # state in taxel-major layout, (n_taxels, samples): each taxel's frames are contiguous, so the
        # FFTs of all taxels run as one batch along the last axis (a strided axis costs ~6x)
        self._buf = np.zeros((n_taxels, n - self.hop), self.dtype)  # input not yet consumed by a full frame
        self._acc = np.zeros((n_taxels, n - self.hop), self.dtype)  # overlap-add tail of frames already done
        self._skip = n - self.hop  # leading outputs that belong to the virtual zeros
        self.frames = 0

    @staticmethod
    def gather(parts: "list[tuple[StftGate, np.ndarray]]") -> "StftGate":
        """One gate over the taxels ``idx`` of each part, in order (same frame, thresholds and
        position in the stream; state copied bit for bit)."""
        first = parts[0][0]
        if any((g.n, g._buf.shape[1], g._acc.shape[1], g._skip) != (first.n, first._buf.shape[1], first._acc.shape[1], first._skip)
               for g, _ in parts):
            raise ValueError("gates gathered into one must be at the same position of the stream")
        out = StftGate(first.n, sum(len(idx) for _, idx in parts), None, first.attenuation, first.dtype)
        out.thresholds, out._skip, out.frames = first.thresholds, first._skip, max(g.frames for g, _ in parts)
        out._buf = np.concatenate([g._buf[idx] for g, idx in parts])
        out._acc = np.concatenate([g._acc[idx] for g, idx in parts])
        return out

    @property
    def to_next_frame(self) -> int:
        """Input samples still needed before the next frame is complete."""
        return self.n - self._buf.shape[1]

    def process(self, x: np.ndarray) -> np.ndarray:
        """Consume input samples (n, n_taxels), return the newly finalised output samples (m, n_taxels),
        same units (a transposed view of the taxel-major result)."""
        x = np.asarray(x, dtype=self.dtype)
        buf = np.concatenate((self._buf, x.T), axis=1)
        n_frames = (buf.shape[1] - self.n) // self.hop + 1 if buf.shape[1] >= self.n else 0
        if n_frames <= 0:
            self._buf = buf
            return np.zeros((0, self.n_taxels), self.dtype)
        total = (n_frames - 1) * self.hop + self.n
        done = n_frames * self.hop
        drop = min(self._skip, done)  # outputs of the virtual zeros
        out = np.empty((self.n_taxels, done - drop), self.dtype)
        tail = np.empty((self.n_taxels, total - done), self.dtype)

        def rows(a: int, b: int) -> None:  # taxels a ... b - 1 (scipy's FFT and numpy's ufuncs release the GIL)
            rows = buf[a:b]  # frames as a strided view (sliding_window_view's checks cost ~20 us a call)
            frames = as_strided(rows, (b - a, n_frames, self.n), (rows.strides[0], self.hop * rows.strides[1], rows.strides[1]),
                                writeable=False) * self.window  # (taxels, F, N)
            spec = scipy.fft.rfft(frames, axis=-1, overwrite_x=True)
            if self.thresholds is not None:
                np.multiply(spec, self.attenuation, out=spec, where=np.abs(spec) < self.thresholds)
            y = scipy.fft.irfft(spec, n=self.n, axis=-1, overwrite_x=True)
            # overlap-add: frame f contributes to output positions f*H ... f*H + N - 1, i.e. its quarter q
            # (N = 4 H) to hop f + q: one vectorised add per quarter, whatever the number of frames; the
            # last quarters first, so that every hop sums its frames in stream order (chunk invariance, bit for bit)
            acc = np.zeros((b - a, n_frames + 3, self.hop), self.dtype)
            acc.reshape(b - a, total)[:, : self._acc.shape[1]] += self._acc[a:b]
            quarters = y.reshape(b - a, n_frames, 4, self.hop)
            for q in (3, 2, 1, 0):
                acc[:, q : q + n_frames] += quarters[:, :, q]
            acc = acc.reshape(b - a, total)
            np.divide(acc[:, drop:done], self.norm, out=out[a:b])
            tail[a:b] = acc[:, done:]

        split_run(rows, self.n_taxels, self.n_taxels * n_frames * self.n, min_work=100_000)
        self._skip -= drop
        self._acc = tail
        self._buf = buf[:, done:]
        self.frames += n_frames
        return out.T

    @property
    def state_norm(self) -> float:
        return float(max(np.max(np.abs(self._buf), initial=0.0), np.max(np.abs(self._acc), initial=0.0)))
