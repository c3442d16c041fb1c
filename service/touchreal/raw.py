"""The raw sample block every sensor source produces (simulated e-skin, replay, serial), and the
taxel grid they place their taxels on."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass
class RawChunk:
    """Raw samples of N taxels on the recording clock.

    ``st_t`` (n,) s and ``st`` (n, n_taxels) N for the SingleTact (100 Hz); ``pvdf_t`` (m,) s and
    ``pvdf`` (m, n_taxels) V for the PVDF film (2 kHz). Either part may be empty.
    """

    st_t: np.ndarray
    st: np.ndarray
    pvdf_t: np.ndarray
    pvdf: np.ndarray

    @property
    def n_taxels(self) -> int:
        return self.st.shape[1] if self.st.ndim == 2 else 1

    @classmethod
    def empty(cls, n_taxels: int = 1) -> "RawChunk":
        z = np.zeros(0)
        return cls(z, np.zeros((0, n_taxels)), z.copy(), np.zeros((0, n_taxels)))

    def taxel(self, i: int) -> "RawChunk":
        """The streams of taxel ``i`` as 1-D arrays (``st`` (n,) N, ``pvdf`` (m,) V)."""
        return RawChunk(self.st_t, self.st[:, i], self.pvdf_t, self.pvdf[:, i])

    @staticmethod
    def concat(chunks: Sequence["RawChunk"]) -> "RawChunk":
        """Join consecutive chunks of one source into one."""
        return RawChunk(*(np.concatenate([getattr(c, f) for c in chunks]) for f in ("st_t", "st", "pvdf_t", "pvdf")))


def spatial_order(positions_mm: np.ndarray) -> np.ndarray:
    """A permutation of the taxels (int64) that keeps neighbours on the skin near each other: the Z
    (Morton) order of their ranks along x and along y. Cut into runs of consecutive positions it
    gives compact patches of the skin for any layout: on a grid of 2^k x 2^k taxels, runs of 4^j
    are exactly square tiles, where runs of ids are strips along the rows."""
    p = np.asarray(positions_mm, np.float64).reshape(-1, 2)
    ix = np.unique(p[:, 0], return_inverse=True)[1].astype(np.uint64)
    iy = np.unique(p[:, 1], return_inverse=True)[1].astype(np.uint64)
    return np.argsort(_spread_bits(ix) | (_spread_bits(iy) << np.uint64(1)), kind="stable")


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Each of the low 32 bits of ``v`` (uint64) moved to twice its position (bit i -> bit 2i)."""
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                        (2, 0x3333333333333333), (1, 0x5555555555555555)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def taxel_grid(n: int, pitch_mm: float = 10.0) -> np.ndarray:
    """(n, 2) taxel centres (mm): a near-square grid of pitch ``pitch_mm`` centred on (0, 0)."""
    if n < 1:
        raise ValueError("n must be >= 1")
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    ij = np.array([(i % cols, i // cols) for i in range(n)], float)
    return (ij - [(cols - 1) / 2, (rows - 1) / 2]) * pitch_mm
