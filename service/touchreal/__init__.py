"""TouchReal: raw SingleTact + PVDF signals -> biomimetic SA1/RA/PC spike trains, online.

Data flow: ``sensing`` (sources: simulated e-skin, replay, serial) -> ``preprocess`` (causal
chunk-wise stages to four 5 kHz channels) -> ``encoding`` (LIF per afferent class) -> analysis,
fitting, and the network service. ``reference`` holds the TouchSim-compatible ground-truth model.
"""

__version__ = "0.1.0"
