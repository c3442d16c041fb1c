"""Sans-I/O rate budgets: how long a connection must wait before its next message is read."""

from __future__ import annotations

import time
from collections.abc import Callable

from touchreal_client import protocol as P


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up; a charge may overdraw, and the
    overdraft is the wait (s) before the next charge is due. Times from ``clock`` (monotonic s)."""

    def __init__(self, rate: float, burst: float, clock: Callable[[], float] = time.monotonic):
        if rate <= 0 or burst <= 0:
            raise ValueError("rate and burst must be positive")
        self.rate, self.burst, self.clock = rate, burst, clock
        self.tokens, self._at = float(burst), clock()

    def charge(self, amount: float) -> float:
        """Spend ``amount`` tokens; returns how long (s) to wait until the balance is back to zero."""
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self._at) * self.rate) - amount
        self._at = now
        return max(0.0, -self.tokens / self.rate)


class ControlBudget:
    """One connection's budget for client messages: :data:`~touchreal_client.protocol.CONTROL_RATE_PER_S`
    messages and :data:`~touchreal_client.protocol.CONTROL_BYTES_PER_S` bytes per second, with their
    bursts (the hello's ``limits`` state them)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.messages = TokenBucket(P.CONTROL_RATE_PER_S, P.CONTROL_BURST, clock)
        self.bytes = TokenBucket(P.CONTROL_BYTES_PER_S, P.CONTROL_BURST_BYTES, clock)

    def charge(self, n_bytes: int) -> float:
        """Account one message of ``n_bytes``; the wait (s) before the connection's next message is read."""
        return max(self.messages.charge(1), self.bytes.charge(n_bytes))
