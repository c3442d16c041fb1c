"""TouchSim-compatible reference model of a single round probe (Saal, Delhaye et al., PNAS 2017).

Re-implemented from the published equations and TouchSim's constants: Sneddon mechanics and
surface-wave propagation (:mod:`.mechanics`), the 17 single-unit integrate-and-fire models
(:mod:`.model`, constants in :mod:`.constants`), and the ``touchreal reference`` command
(:mod:`.command`). Reproduces TouchSim 0.1.1's noiseless conformance spikes exactly; see
docs/reference-model.md.
"""

from .constants import TouchSimConstants, load_constants
from .model import ReferenceModel, SpikeResponse, reference_trains

__all__ = ["ReferenceModel", "SpikeResponse", "TouchSimConstants", "load_constants", "reference_trains"]
