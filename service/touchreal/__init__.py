"""TouchReal: raw SingleTact + PVDF signals -> biomimetic SA1/RA/PC spike trains, online.

Data flow: ``raw`` (the sample block) <- ``simulator`` (the e-skin physics), ``device`` (the serial
microcontroller) and ``sources`` (live and replayed) -> ``preprocess`` (causal chunk-wise stages to
four 5 kHz channels) -> ``encoding`` (LIF per afferent class) -> ``stream`` -> ``decoding``, the
network ``server`` and its ``bridge``; ``analysis`` and ``fitting`` read recordings offline;
``reference`` holds the TouchSim-compatible ground-truth model; ``commands`` is the command line.
"""

__version__ = "0.1.0"
