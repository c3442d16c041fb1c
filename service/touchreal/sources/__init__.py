"""The live sources the service reads: the simulated e-skin in real time, replays of recordings, and
the warm-up that keeps the simulator's first hop from stalling; each hands over
:class:`~touchreal.raw.RawChunk` blocks at the hop (the serial source is :mod:`touchreal.device`).
"""
