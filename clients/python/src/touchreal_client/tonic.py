"""A TouchReal recording as a Tonic dataset: samples of afferent spikes as structured event arrays
that ``tonic.transforms`` and a DataLoader take (extra ``[tonic]``; this module itself needs only numpy).

* Source: an MCAP file of ``touchreal record`` or a folder of ``touchreal encode`` (:mod:`.session`).
* Events (one per spike, in time order): ``x`` the taxel's column (int32), ``y`` its row (int32,
  only when the taxels form a 2-D grid), ``t`` in integer µs from the sample's start (int64), ``p``
  the afferent class (int8: 0 SA1, 1 RA, 2 PC). ``ordering``: ``"xytp"`` on a 2-D grid, else
  ``"xtp"``, the field names in order.
* ``sensor_size``: ``(columns, rows, 3)`` on a 2-D grid (the hello's ``layout``,
  :func:`.protocol.grid_layout`: row-major ids; x_mm and y_mm increase with the column and row
  index); any other layout (one taxel, one row or column, positions on no such grid) is 1-D: ``x``
  = the taxel id and ``sensor_size = (n_taxels, 1, 3)``; the positions are in ``session.taxels``.
  Tonic's ``Denoise`` reads ``y``: it takes 2-D samples only.
* Samples: the trials of an encode folder (with ``dataset``: its manifest's order and durations;
  without: file-name order, each up to the whole second after its last spike), else the whole
  recording (an MCAP recording has no trials: from its earliest stamp to after its last spike or
  its coverage end); ``window_us`` cuts each into consecutive windows of that length (a shorter
  rest is dropped). A trial starts at its t = 0, or at its first spike if that is earlier
  (``touchreal encode``'s reference clock moves spikes earlier by the alignment lag; ``--clock
  sensor`` does not).
* Targets: the index of the sample's label in ``classes`` (sorted labels, or the ``classes``
  given); the label is the ``dataset`` manifest entry's ``texture``, else its ``condition`` (as the
  decoders' training labels them), or ``label`` for every sample; :data:`UNLABELLED` without either.

>>> from touchreal_client.tonic import TouchRealDataset
>>> ds = TouchRealDataset("enc", dataset="ds")          # a touchreal encode folder and its dataset
>>> ds.transform = tonic.transforms.ToFrame(sensor_size=ds.sensor_size, time_window=100_000)
>>> frames, target = ds[0]                              # frames (n, 3, 1); ds.classes[target]: a texture
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import protocol as P
from .session import Session, read_encode_dir, read_mcap

UNLABELLED = -1  #: the target of a sample without a label


@dataclass(frozen=True)
class Sample:
    """One sample: the spikes stamped in [``start_us``, ``stop_us``) of the session's timeline (µs);
    ``id``: the trial id or the recording's name, ``@k`` for its k-th window."""

    id: str
    start_us: int
    stop_us: int
    label: str | None


class TouchRealDataset:
    """Samples of a recording as ``(events, target)`` pairs, with tonic's ``transform`` (events),
    ``target_transform`` (target) and ``transforms`` ((events, target)), applied in that order.

    ``source``: a ``.mcap`` file of ``touchreal record`` or a folder of ``touchreal encode``.
    ``dataset``: the dataset folder (``manifest.json``) an encode folder was encoded from: its trial
    order, durations (``duration_s``) and labels. ``label``: one label for every sample (a recording
    of one texture). ``classes``: the labels targets index (default: the sorted labels present).
    ``window_us``: cut each trial (or the recording) into windows of this many µs.
    ValueError for anything it cannot use.

    Attributes: ``sensor_size``, ``dtype`` (of the events), ``ordering``, ``samples``
    (:class:`Sample`), ``classes``, ``targets`` (one per sample), ``session`` (:class:`.session.Session`)."""

    def __init__(self, source: str | Path, *, dataset: str | Path | None = None, label: str | None = None,
                 classes: Sequence[str] | None = None, window_us: int | None = None,
                 transform: Callable[[np.ndarray], Any] | None = None,
                 target_transform: Callable[[int], Any] | None = None,
                 transforms: Callable[[Any, Any], tuple[Any, Any]] | None = None) -> None:
        if dataset is not None and label is not None:
            raise ValueError("give dataset (labels per trial) or label (one for every sample), not both")
        if window_us is not None and (not isinstance(window_us, int) or isinstance(window_us, bool) or window_us <= 0):
            raise ValueError(f"window_us must be a positive integer (µs), got {window_us!r}")
        self.session, labels = _read(Path(source), None if dataset is None else Path(dataset))
        self.sensor_size, self.dtype, self._col, self._row = _layout(self.session)
        self.ordering = "".join(self.dtype.names)
        self.samples = [Sample(f"{sid}@{k}" if window_us else sid, lo, hi, labels.get(sid, label))
                        for sid, start, stop in _spans(self.session)
                        for k, (lo, hi) in enumerate(_windows(start, stop, window_us))]
        if not self.samples:
            raise ValueError(f"{source}: no sample: every trial (or the recording) is shorter than "
                             f"window_us = {window_us}")
        self.classes = _classes([s.label for s in self.samples if s.label is not None], classes)
        index = {c: i for i, c in enumerate(self.classes)}
        self.targets = [UNLABELLED if s.label is None else index[s.label] for s in self.samples]
        self.transform, self.target_transform, self.transforms = transform, target_transform, transforms

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> tuple[Any, Any]:
        events, target = self.events(index), self.targets[index]
        if self.transform is not None:
            events = self.transform(events)
        if self.target_transform is not None:
            target = self.target_transform(target)
        if self.transforms is not None:
            events, target = self.transforms(events, target)
        return events, target

    def events(self, index: int) -> np.ndarray:
        """The events of sample ``index`` before any transform (a new array: transforms may write in it)."""
        s = self.samples[index]
        lo, hi = np.searchsorted(self.session.t_us, [s.start_us, s.stop_us], side="left")
        taxel = self.session.taxel[lo:hi]
        out = np.empty(hi - lo, self.dtype)
        out["x"] = self._col[taxel]
        if self._row is not None:
            out["y"] = self._row[taxel]
        out["t"] = self.session.t_us[lo:hi] - s.start_us
        out["p"] = self.session.cls[lo:hi]
        return out


def _read(source: Path, dataset: Path | None) -> tuple[Session, dict[str, str]]:
    """The session and its trial labels (trial id -> label; empty without ``dataset``)."""
    if source.is_file():
        if dataset is not None:
            raise ValueError(f"{source}: dataset is for a touchreal encode folder (an MCAP recording has no trials)")
        session = read_mcap(source)
        if len(session.sessions) > 1:
            raise ValueError(f"{source} spans {len(session.sessions)} server sessions (the server restarted and its "
                             "clock with it); a dataset takes a recording of one session")
        return session, {}
    if not source.is_dir():
        raise ValueError(f"{source}: no such file or folder")
    if dataset is None:
        return read_encode_dir(source), {}
    durations, labels = _manifest(dataset)
    unknown = sorted(f.stem for f in source.glob("*.json") if f.stem not in durations)
    if unknown:
        raise ValueError(f"{source}: trials not in {dataset}'s manifest: {unknown[:5]} "
                         "(was it encoded from another dataset?)")
    return read_encode_dir(source, durations), labels


def _manifest(dataset: Path) -> tuple[dict[str, float], dict[str, str]]:
    """Trial id -> duration (s), in the manifest's order, and trial id -> label (``texture``, else
    ``condition``) of a dataset folder."""
    path = dataset / "manifest.json"
    try:
        entries = json.loads(path.read_text())["trials"]
        durations = {str(e["id"]): float(e["duration_s"]) for e in entries}
        labels = {str(e["id"]): str(e.get("texture") or e["condition"]) for e in entries}
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable dataset manifest ({exc})") from exc
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"{path}: every trial entry needs id, duration_s and condition ({exc!r})") from exc
    return durations, labels


def _layout(session: Session) -> tuple[tuple[int, int, int], np.dtype, np.ndarray, np.ndarray | None]:
    """(sensor_size, event dtype, column per taxel id, row per taxel id or None when 1-D)."""
    taxels = sorted(session.taxels, key=lambda t: int(t["id"]))
    n = len(taxels)
    if [int(t["id"]) for t in taxels] != list(range(n)):
        raise ValueError(f"{session.source}: the taxel layout must list the ids 0..n-1 once each")
    if session.taxel.size and int(session.taxel.max()) >= n:
        raise ValueError(f"{session.source}: taxel {int(session.taxel.max())} spiked outside the layout of {n} taxels")
    xy = np.array([[t["x_mm"], t["y_mm"]] for t in taxels], float).reshape(-1, 2)
    grid = P.grid_layout(xy)
    n_classes = len(P.CLASSES)
    if grid is None or grid["rows"] < 2 or grid["cols"] < 2:
        return (n, 1, n_classes), np.dtype([("x", np.int32), ("t", np.int64), ("p", np.int8)]), np.arange(n), None
    col = np.rint((xy[:, 0] - xy[:, 0].min()) / abs(grid["dx_mm"])).astype(np.int32)
    row = np.rint((xy[:, 1] - xy[:, 1].min()) / abs(grid["dy_mm"])).astype(np.int32)
    dtype = np.dtype([("x", np.int32), ("y", np.int32), ("t", np.int64), ("p", np.int8)])
    return (grid["cols"], grid["rows"], n_classes), dtype, col, row


def _spans(session: Session) -> list[tuple[str, int, int]]:
    """(id, start, stop) µs of each trial, else of the whole recording: from its earliest stamp to
    after its last spike or its coverage end, whichever is later."""
    if session.trials:
        return [(tr.id, tr.start_us, tr.stop_us) for tr in session.trials]
    start = session.origin_us()
    ends = [start] + [hi for _, hi in session.coverage_us.values()]
    if session.t_us.size:
        ends.append(int(session.t_us[-1]) + 1)
    return [(Path(session.source).stem, start, max(ends))]


def _windows(start: int, stop: int, window_us: int | None) -> list[tuple[int, int]]:
    """[start, stop) whole, or its consecutive windows of ``window_us`` (a shorter rest dropped)."""
    if window_us is None:
        return [(start, stop)]
    return [(lo, lo + window_us) for lo in range(start, stop - window_us + 1, window_us)]


def _classes(labels: list[str], given: Sequence[str] | None) -> list[str]:
    if given is None:
        return sorted(set(labels))
    out = [str(c) for c in given]
    if len(set(out)) != len(out):
        raise ValueError(f"classes must not repeat a label: {out}")
    missing = sorted(set(labels) - set(out))
    if missing:
        raise ValueError(f"labels {missing} are not in classes {out}")
    return out
