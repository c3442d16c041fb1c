"""Parameter sets of the service: the active one, a short history, persisted in the state directory.

Layout under ``STATE_DIR/params/``: ``rev-000001.json`` ... (one file per revision, the versioned
JSON of ``touchreal fit``) and ``history.json`` (``{"active": rev, "revisions": [...]}``). Writes go
to a temporary file and are renamed into place, so a crash never leaves a torn file.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ..params import EncoderParams, default_params

HISTORY_KEEP = 20  #: revisions kept on disk


def params_sha256(params: EncoderParams) -> str:
    """Content hash of a parameter set (of its canonical JSON, provenance included)."""
    canon = json.dumps(params.model_dump(by_alias=True, mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode()).hexdigest()


@dataclass(frozen=True)
class Revision:
    rev: int
    sha256: str
    created_us: int
    origin: str  #: "shipped", "file:PATH", "upload", "config", "rollback:N"


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class ParamsStore:
    """Thread-safe store. ``current`` is the (revision, parameters) pair, swapped as one reference,
    so a reader on another thread never sees one revision's number with another's parameters."""

    def __init__(self, state_dir: Path, initial: Path | None = None):
        self.dir = Path(state_dir) / "params"
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self.revisions: list[Revision] = []
        hist = self.dir / "history.json"
        if hist.is_file():
            data = json.loads(hist.read_text())
            self.revisions = [Revision(**r) for r in data["revisions"]]
            active_rev = data["active"]
        if initial is not None:
            self.current = self._add(EncoderParams.load(initial), f"file:{initial}")
        elif self.revisions:
            self.current = (active_rev, self.load(active_rev))
        else:
            self.current = self._add(default_params(), "shipped")

    def _path(self, rev: int) -> Path:
        return self.dir / f"rev-{rev:06d}.json"

    @property
    def active(self) -> EncoderParams:
        return self.current[1]

    @property
    def active_rev(self) -> int:
        return self.current[0]

    def _add(self, params: EncoderParams, origin: str) -> tuple[int, EncoderParams]:
        rev = (self.revisions[-1].rev + 1) if self.revisions else 1
        _write_atomic(self._path(rev), params.to_json() + "\n")
        self.revisions.append(Revision(rev, params_sha256(params), time.time_ns() // 1000, origin))
        for old in self.revisions[:-HISTORY_KEEP]:
            self._path(old.rev).unlink(missing_ok=True)
        self.revisions = self.revisions[-HISTORY_KEEP:]
        self._save_history(rev)
        return rev, params

    def _save_history(self, active: int) -> None:
        doc = {"active": active, "revisions": [asdict(r) for r in self.revisions]}
        _write_atomic(self.dir / "history.json", json.dumps(doc, indent=1) + "\n")

    def load(self, rev: int) -> EncoderParams:
        if not any(r.rev == rev for r in self.revisions) or not self._path(rev).is_file():
            raise KeyError(f"no parameter revision {rev} (kept: {[r.rev for r in self.revisions]})")
        return EncoderParams.load(self._path(rev))

    def put(self, params: EncoderParams, origin: str = "upload") -> int:
        """Make ``params`` (already validated) the active set; returns its revision."""
        with self._lock:
            self.current = self._add(params, origin)
            return self.current[0]

    def rollback(self, rev: int) -> int:
        """Activate an earlier revision again (as a new revision, so the history stays linear)."""
        with self._lock:
            self.current = self._add(self.load(rev), f"rollback:{rev}")
            return self.current[0]

    def info(self, rev: int | None = None) -> Revision:
        rev = self.active_rev if rev is None else rev
        return next(r for r in self.revisions if r.rev == rev)
