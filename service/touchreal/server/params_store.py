"""Parameter sets of the service: the active one, a short history, persisted in the state directory.

Layout under ``STATE_DIR/params/``: ``rev-000001.json`` ... (one file per revision, the versioned
JSON of ``touchreal fit``) and ``history.json`` (``{"active": rev, "revisions": [...]}``). Writes go
to a temporary file and are renamed into place, so a crash never leaves a torn file.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ..params import EncoderParams, ParamsError, default_params

log = logging.getLogger("touchreal.server")
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
    origin: str  #: "shipped", "file:PATH", "upload", "config", "rollback:N", "fallback:N" / "fallback:shipped"


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
        #: why the set the service started with, or ran, is not the one it was asked for (None: it is)
        self.fallback_reason: str | None = None
        hist = self.dir / "history.json"
        active_rev = None
        if hist.is_file():
            try:
                data = json.loads(hist.read_text())
                self.revisions = [Revision(**r) for r in data["revisions"]]
                active_rev = int(data["active"])
            except (ValueError, KeyError, TypeError) as exc:
                log.error("%s is unreadable (%s); starting a new history", hist, exc)
                self.revisions = []
        if initial is not None:
            self.current = self._add(EncoderParams.load(initial), f"file:{initial}")
        elif active_rev is not None:
            self.current = self._last_loadable(active_rev)
        else:
            self.current = self._add(default_params(), "shipped")

    def _last_loadable(self, active_rev: int) -> tuple[int, EncoderParams]:
        """The persisted active revision; if it no longer loads (the schema's bounds tightened, a
        damaged file), the newest earlier one that does, else the shipped set, activated as a new
        revision ``fallback:N`` with the reason logged and kept in :attr:`fallback_reason`."""
        try:
            return active_rev, self.load(active_rev)
        except (KeyError, ParamsError) as exc:
            reason = f"persisted parameter revision {active_rev} cannot be used: {exc}"
        for r in reversed([r.rev for r in self.revisions if r.rev < active_rev]):
            try:
                return self.fall_back(r, reason)
            except (KeyError, ParamsError):
                continue
        return self.fall_back(None, reason)

    def fall_back(self, rev: int | None, reason: str) -> tuple[int, EncoderParams]:
        """Activate revision ``rev`` (None: the shipped set) as a new revision ``fallback:REV``,
        logging ``reason``; returns the new (revision, parameters)."""
        params = default_params() if rev is None else self.load(rev)
        with self._lock:
            self.current = self._add(params, f"fallback:{'shipped' if rev is None else rev}")
        self.fallback_reason = f"{reason}; running revision {self.current[0]} (a copy of " \
                               f"{'the shipped set' if rev is None else f'revision {rev}'})"
        log.error(self.fallback_reason)
        return self.current

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
        """Make ``params`` (already validated and proved runnable) the active set; returns its revision."""
        with self._lock:
            self.current = self._add(params, origin)
            self.fallback_reason = None
            return self.current[0]

    def info(self, rev: int | None = None) -> Revision:
        rev = self.active_rev if rev is None else rev
        return next(r for r in self.revisions if r.rev == rev)
