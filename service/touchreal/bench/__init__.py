"""Benchmarks: ``touchreal bench TARGET`` prints figures (never asserted in tests).

A target is a module ``touchreal.bench.<name>`` with ``add_arguments(parser)`` and ``run(args)``.
"""

TARGETS = ("encoder", "reference", "simulator", "serve", "decoders", "builds", "population")
