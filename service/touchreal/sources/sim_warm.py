"""Loaded by the fork server of the simulated e-skin's processes (:class:`~.live.SimHopsProcess`): one
hop of a one-taxel skin, so that the skin's compiled kernels are loaded once, in the fork server,
and every simulation process forked from it starts warm (each would otherwise spend about 0.5 s
loading them before its first hop)."""

from .live import SimHops

SimHops(1, 0.005).read_hop()
