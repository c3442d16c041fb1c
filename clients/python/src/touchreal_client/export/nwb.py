"""A recorded :class:`~touchreal_client.session.Session` -> an NWB file (pynwb; extra ``[nwb]``).

* ``units``: one unit per (taxel, class) with ``spike_times`` (s), ``taxel``, ``afferent_class``,
  ``position_mm`` ([x, y]) and ``obs_intervals`` (the class's coverage: every spike in it was
  received); ``resolution`` 1 us.
* ``processing/misc``: the preprocessed channels as TimeSeries ``ST`` [N], ``dST`` [N/s], ``PVDF`` [V],
  ``dPVDF`` [V/s] (``data[sample, taxel]``), each decoder's outputs as ``decoded_<name>``
  (``data[step, taxel, output]``), and the tables ``parameter_revisions`` (``rev``, ``sha256``,
  ``source``) and ``clock`` (the stream's clock points); each full parameter set (JSON) in
  ``scratch/parameters_rev<N>``.
* ``subject``: the modelled afferents (no living subject; nwbinspector requires one).
* ``trials`` when the session has trials (a ``touchreal encode`` folder).

Times: ``(stamp - origin_us) / 1e6`` s, where stamps are the wire clock (us) and ``origin_us`` the
session's origin (the earliest recorded stamp of an MCAP recording, 0 for an encode folder); the
file's ``session_start_time`` is the origin's server wall time by the clock model when there is one.
"""

from __future__ import annotations

import json
import uuid
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from hdmf.common import DynamicTable
from pynwb import NWBHDF5IO, NWBFile, TimeSeries
from pynwb.file import Subject
from pynwb.misc import Units

from .. import protocol as P
from ..session import Session

#: ``units.resolution``: stamps are integer microseconds.
RESOLUTION_S = 1e-6


def to_nwb(session: Session, out: str | Path, description: str | None = None) -> Path:
    """Write ``session`` as the NWB file ``out`` (overwritten); returns its path. ValueError for a
    recording that spans several server sessions (their wire clocks overlap)."""
    if len(session.sessions) > 1:
        raise ValueError(f"{session.source} spans {len(session.sessions)} server sessions (the server restarted and "
                         "its clock with it); NWB export takes a recording of one session")
    out = Path(out)
    origin = session.origin_us()
    wall = session.wall_us_of(origin)
    start = datetime.fromtimestamp((wall if wall is not None else session.created_wall_us) / 1e6, timezone.utc)
    nwb = NWBFile(
        session_description=description or f"TouchReal SA1/RA/PC afferent spike trains from {session.source}",
        identifier=str(uuid.uuid4()), session_start_time=start, timestamps_reference_time=start,
        source_script=f"touchreal_client.export.nwb (times: wire-clock stamp - {origin} us, in s)",
        source_script_file_name="touchreal_client/export/nwb.py",
        experiment_description="online biomimetic SA1/RA/PC afferent spike trains from a tactile sensor (SingleTact force "
        "+ PVDF film) by TouchReal's TouchSim-style encoder",
        keywords=["touch", "tactile afferents", "SA1", "RA", "PC", "TouchSim", "TouchReal"],
    )
    nwb.subject = Subject(
        subject_id=str((session.hello or {}).get("session") or "touchreal-encode"), species="Homo sapiens", sex="U",
        age="P0D/", description="no living subject: model afferents of human skin (TouchSim-style) driven by a TouchReal "
        "tactile sensor; species is the modelled afferents', sex (U) and age (P0D/: any) do not apply")
    _units(nwb, session, origin)
    misc = nwb.create_processing_module("misc", "TouchReal: preprocessed channels, decoder outputs, parameters, clock; "
                                        f"times are (wire-clock stamp - {origin} us) / 1e6 s")
    _channels(misc, session, origin)
    _decoded(misc, session, origin)
    _params(nwb, misc, session)
    _clock(misc, session)
    for tr in session.trials:
        if not nwb.trials:
            nwb.add_trial_column("trial_id", "the dataset's trial id")
            nwb.add_trial_column("origin_time", "time (s) of the trial's own t = 0 on this file's timeline")
        nwb.add_trial((tr.start_us - origin) / 1e6, (tr.stop_us - origin) / 1e6, trial_id=tr.id,
                      origin_time=(tr.origin_us - origin) / 1e6)
    with NWBHDF5IO(str(out), "w") as io:
        io.write(nwb)
    return out


def _sec(t_us: np.ndarray, origin: int) -> np.ndarray:
    return (np.asarray(t_us, np.int64) - origin) / 1e6


def _units(nwb: NWBFile, s: Session, origin: int) -> None:
    if not s.coverage_us:  # no spikes were recorded (e.g. channels only)
        return
    rev = ", ".join(f"rev {p['rev']} sha256 {p['sha256']}" for p in s.params) or "unknown"
    if s.afferents is not None:
        _population_units(nwb, s, origin, rev)
        return
    nwb.units = Units(name="units", resolution=RESOLUTION_S,
                      description=f"afferent spike trains per (taxel, class); parameter set: {rev}")
    nwb.add_unit_column("taxel", "taxel id")
    nwb.add_unit_column("afferent_class", "afferent class: SA1, RA or PC")
    nwb.add_unit_column("position_mm", "taxel position [x, y] (mm)")
    pos = {int(t["id"]): (float(t.get("x_mm", 0.0)), float(t.get("y_mm", 0.0))) for t in s.taxels}
    for taxel in sorted(pos):
        for k, c in enumerate(P.CLASSES):
            if c not in s.coverage_us:
                continue
            lo, hi = s.coverage_us[c]
            t = np.sort(s.t_us[(s.taxel == taxel) & (s.cls == k)])
            nwb.add_unit(spike_times=_sec(t, origin), obs_intervals=[[(lo - origin) / 1e6, (hi - origin) / 1e6]],
                         taxel=taxel, afferent_class=c, position_mm=list(pos[taxel]))


def _population_units(nwb: NWBFile, s: Session, origin: int, rev: str) -> None:
    """One unit per afferent of the recorded population, with its class, position and model."""
    aff = s.afferents
    nwb.units = Units(name="units", resolution=RESOLUTION_S,
                      description=f"afferent spike trains, one unit per afferent of a population placed by the plan "
                      f"{json.dumps(aff.plan, sort_keys=True)}; parameter set: {rev}")
    nwb.add_unit_column("afferent", "afferent id (the stream's id)")
    nwb.add_unit_column("afferent_class", "afferent class: SA1, RA or PC")
    nwb.add_unit_column("position_mm", "afferent position [x, y] (mm)")
    nwb.add_unit_column("model", "TouchSim single-unit model of the class the afferent runs (its variant)")
    order = np.argsort(s.taxel, kind="stable")
    bounds = np.searchsorted(s.taxel[order], np.arange(len(aff.cls) + 1))
    for a in range(len(aff.cls)):
        c = P.CLASSES[int(aff.cls[a])]
        if c not in s.coverage_us:
            continue
        lo, hi = s.coverage_us[c]
        t = np.sort(s.t_us[order[bounds[a]:bounds[a + 1]]])
        nwb.add_unit(spike_times=_sec(t, origin), obs_intervals=[[(lo - origin) / 1e6, (hi - origin) / 1e6]],
                     afferent=a, afferent_class=c, position_mm=[float(v) for v in aff.xy_mm[a]], model=int(aff.model[a]))


def _series(name: str, t_us: np.ndarray, origin: int, data: np.ndarray, unit: str, description: str) -> TimeSeries:
    """Regular steps as starting_time + rate, irregular ones (frames were dropped) as timestamps."""
    d = np.diff(t_us)
    if t_us.size > 1 and np.all(d == d[0]):
        return TimeSeries(name=name, data=data, unit=unit, description=description,
                          starting_time=float(_sec(t_us[:1], origin)[0]), rate=1e6 / float(d[0]))
    return TimeSeries(name=name, data=data, unit=unit, description=description, timestamps=_sec(t_us, origin))


def _channels(misc, s: Session, origin: int) -> None:
    ch = s.channels
    if ch is None:
        return
    for j, (name, unit) in enumerate(zip(P.CHANNELS, P.CHANNEL_UNITS)):
        misc.add(_series(name, ch.t_us, origin, ch.data[:, :, j], unit,
                         f"preprocessed {name} on the 5 kHz grid (decimated); columns: taxels {ch.taxels.tolist()}"))


def _decoded(misc, s: Session, origin: int) -> None:
    for name, d in s.decoded.items():
        unit = "N" if all(o.endswith("_N") for o in d.outputs) else "probability"
        misc.add(_series(f"decoded_{name}", d.t_us, origin, d.values, unit,
                         f"decoder {name}: data[step, taxel, output], outputs {d.outputs}, taxels {d.taxels.tolist()}; "
                         "time = end of the decoding window"))


def _params(nwb: NWBFile, misc, s: Session) -> None:
    """The revisions as a table; each full parameter set (JSON) as scratch data ``parameters_rev<N>``."""
    if not s.params:
        return
    table = DynamicTable(name="parameter_revisions", description="encoder parameter sets that made the spikes "
                         "(rev 0: a parameter file, not a service revision); the sets themselves: scratch/parameters_rev<N>")
    for col, desc in (("rev", "revision"), ("sha256", "sha256 of the canonical JSON"), ("source", "where it came from")):
        table.add_column(col, desc)
    for p in s.params:
        table.add_row(rev=int(p["rev"] or 0), sha256=str(p["sha256"]), source=str(p["source"]))
        if p["params"] is not None:
            nwb.add_scratch(json.dumps(p["params"]), name=f"parameters_rev{int(p['rev'] or 0)}",
                            description=f"encoder parameter set, sha256 {p['sha256']} (JSON)")
    misc.add(table)


def _clock(misc, s: Session) -> None:
    if not s.clock:
        return
    table = DynamicTable(name="clock", description="the stream's clock points: the sample stamped sensor_us (us) "
                         "was acquired at server wall time wall_us (us, Unix epoch); rate wall us per sensor us")
    for col, desc in (("sensor_us", "wire-clock stamp (us)"), ("wall_us", "server wall time (us)"),
                      ("rate", "wall us per sensor us"), ("error_us", "stated uncertainty (us)"),
                      ("epoch", "increments when the mapping jumps")):
        table.add_column(col, desc)
    for p in s.clock:
        table.add_row(sensor_us=p.sensor_us, wall_us=p.wall_us, rate=p.rate, error_us=p.error_us, epoch=p.epoch)
    misc.add(table)
