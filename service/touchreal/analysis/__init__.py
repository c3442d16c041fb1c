"""Evaluation of TouchReal against TouchSim (paper section 2.5 / 3): spike-train distances
(:mod:`.spiketrains`), receptive-field-like spatial measures (:mod:`.spatial`), statistics
(:mod:`.stats`), figures (:mod:`.figures`) and the ``touchreal evaluate`` report (:mod:`.report`).
See docs/evaluation.md."""
