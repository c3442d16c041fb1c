"""Reconnect delays: exponential backoff with full jitter (sans-I/O, seeded for tests)."""

from __future__ import annotations

import random
from dataclasses import dataclass, field


@dataclass
class Backoff:
    """Delay before reconnect attempt n (0-based): uniform in ``[0, min(max_s, initial_s * factor**n)]``
    ("full jitter", so many clients of a restarted server do not reconnect in lockstep).
    ``max_attempts`` None = try for ever; :meth:`reset` after a connection that delivered a hello."""

    initial_s: float = 0.2
    factor: float = 2.0
    max_s: float = 10.0
    max_attempts: int | None = None
    seed: int | None = None
    attempt: int = 0
    _rng: random.Random = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.initial_s <= 0 or self.factor < 1 or self.max_s < self.initial_s:
            raise ValueError("backoff needs initial_s > 0, factor >= 1 and max_s >= initial_s")
        self._rng = random.Random(self.seed)

    @property
    def exhausted(self) -> bool:
        return self.max_attempts is not None and self.attempt >= self.max_attempts

    def next_delay(self) -> float:
        """Seconds to wait before the next attempt; counts the attempt."""
        cap = min(self.max_s, self.initial_s * self.factor**self.attempt)
        self.attempt += 1
        return self._rng.uniform(0.0, cap)

    def reset(self) -> None:
        self.attempt = 0
