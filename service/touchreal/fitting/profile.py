"""A build's profile: what the fit measures of a dataset, once, before it resolves its plan
(:mod:`.policy`'s rules read it and nothing else)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..params import PreprocessParams
from ..recording import Dataset, Trial
from .calibration import contact_snr, singletact_noise
from .trials import baseline_segments


@dataclass(frozen=True)
class BuildProfile:
    """The measures of a build the fit's policy reads (None: not measured, e.g. a dataset without
    ramps; no rule applies on a measure that is None)."""

    #: the PVDF contact signal over the calibrated noise (ratio): the 99th percentile of |PVDF| after
    #: the training ramps' contact onsets over the noise RMS (:func:`~.calibration.contact_snr`)
    contact_snr: float | None = None
    #: the SingleTact's sample noise (N RMS) on the contact-free baselines (:func:`~.calibration.singletact_noise`)
    st_noise_n: float | None = None

    def as_dict(self) -> dict[str, float | None]:
        """The measures as the provenance records them (SNR to 0.01, noise to 1 uN)."""
        return {k: None if v is None else round(v, DIGITS[k]) for k, v in asdict(self).items()}


#: per measure: its label and how it is shown (scale from its unit, unit shown)
MEASURES: Mapping[str, tuple[str, float, str]] = {
    "contact_snr": ("contact SNR", 1.0, ""),
    "st_noise_n": ("SingleTact noise", 1000.0, " mN"),
}
DIGITS = {"contact_snr": 2, "st_noise_n": 6}  #: decimals a measure is recorded with (in its own unit)


def shown(measure: str, value: float | None, digits: int = 1) -> str:
    """A measure's value in its display unit (``"5.0 mN"``; ``"-"`` when not measured)."""
    _, scale, unit = MEASURES[measure]
    return "-" if value is None else f"{value * scale:.{digits}f}{unit}"


def measure_profile(ds: Dataset, entries: Sequence[dict[str, Any]], loaded: Mapping[str, Trial], pre: PreprocessParams) -> BuildProfile:
    """The profile of a dataset's training ``entries`` (their trials in ``loaded``, by id), on the PVDF
    stage ``pre`` calibrated on their baselines: the contact SNR of the ramps, the SingleTact noise
    of the contact-free baselines."""
    ramps = [(loaded[e["id"]], float(e["onset_s"])) for e in entries if e["protocol"] == "ramp"]
    snr = contact_snr([r.pvdf for r, _ in ramps], [int(np.searchsorted(r.pvdf_t, onset)) for r, onset in ramps], pre)
    noise = singletact_noise(baseline_segments(ds, entries, loaded=dict(loaded), channel="st"))
    return BuildProfile(contact_snr=snr, st_noise_n=noise)
