"""What a :class:`~.service.Service` reports, read-only: the ``hello`` clients get, ``/v1/status``,
readiness and health, the config and decoder views. Nothing here changes the service's state."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


from touchreal_client import protocol as P

from .. import __version__
from ..decoding.model import params_warning
from ..redaction import redact
from .hub import limits
from .runtime import wall_us


SHED_DEGRADED_S = 10.0  #: health stays ``degraded`` this long (s) after compute last shed load


class ServiceView:
    """The reports of one service (``service.view``; ``service`` is the :class:`~.service.Service`
    it reads, never imported here so the state depends on nothing that reports it)."""

    def __init__(self, service: Any):
        self.service = service

    def hop_ms(self) -> float:
        """The source's hop (ms): ``hop_ms``, at most the update interval."""
        return min(self.service.settings.hop_ms, self.service.store.active.preprocess.update_ms)

    def clock_message(self) -> str | None:
        """The current ``clock`` message (None before the first sample)."""
        clock = self.service.clock
        return None if clock is None else json.dumps(clock.to_json(), separators=(",", ":"))

    def describe(self) -> tuple:
        """What the hello describes, for change detection."""
        # windows, latencies, delays and the update interval all follow from the active revision: no need
        # to recompute them on every hop to notice a change
        s = self.service
        return s.store.active_rev, tuple(s.config.classes), self.n_taxels, tuple(s.hub.decoder_names)

    @property
    def n_taxels(self) -> int:
        """Ids spikes address: the taxels, or the population's afferents."""
        return self.service.hub.n_taxels

    def population_view(self) -> dict[str, Any] | None:
        """The hello's ``population``: the plan and every afferent as columns (ids 0..n-1 in order; the
        ids of a class are contiguous, given as id ranges); None without a population."""
        pop = self.service.population
        if pop is None:
            return None
        lay = pop.layout
        return {"plan": json.loads(pop.plan.to_json()), "n_afferents": len(lay),
                "classes": {c: P.id_ranges(lay.ids(c)) for c in P.CLASSES if lay.ids(c).size},
                "x_mm": [round(v, 3) for v in lay.xy_mm[:, 0].tolist()], "y_mm": [round(v, 3) for v in lay.xy_mm[:, 1].tolist()],
                "model": lay.model.tolist()}

    def served_classes(self) -> list[str]:
        """Classes computed for subscribers: those the active parameters define and the config allows."""
        return [c for c in P.CLASSES if c in self.service.store.active.classes and c in self.service.config.classes]

    def latency_us(self) -> dict[str, int]:
        """Per class of the active set: algorithmic latency of the pipeline (us)."""
        from ..stream import class_latency_s

        params = self.service.store.active
        return {c: int(round(class_latency_s(params, c) * 1e6)) for c in params.classes}

    def hello(self) -> dict[str, Any]:
        params = self.service.store.active
        positions = self.service.runtime.source.positions_mm if self.service.runtime is not None else []
        skin = P.hello_skin(positions)  # n_taxels, layout, taxels: listed up to P.HELLO_LISTED_TAXELS on a grid
        population = self.population_view()
        info, clock = self.service.store.info(), self.service.clock
        return {
            "type": "hello",
            "protocol": P.PROTOCOL,
            "version": P.VERSION,
            "versions": list(P.SUPPORTED_VERSIONS),
            "session": self.service.session,
            "server": f"touchreal {__version__}",
            "units": {"time": "us", "force": "N", "pvdf": "V", "channels": dict(zip(P.CHANNELS, P.CHANNEL_UNITS))},
            "clock": None if clock is None else {k: v for k, v in clock.to_json().items() if k != "type"},
            "update_us": int(round(params.preprocess.update_ms * 1000)),
            "hop_us": int(round(self.hop_ms() * 1000)),
            "window_us": {c: int(round(params.window_ms(c) * 1000)) for c in params.classes},
            "latency_us": self.latency_us(),
            "delay_us": {c: int(round(params.classes[c].delay_ms * 1000)) for c in params.classes},
            "classes": self.served_classes(),
            **skin,
            "addresses": "taxels" if population is None else "afferents",
            "population": population,
            "streams": {
                "spikes": {"event_bytes": P.EVENT_DTYPE.itemsize},
                "channels": {"names": list(P.CHANNELS), "units": list(P.CHANNEL_UNITS), "rate_hz": 5000,
                             "default_decimation": P.Subscription().decimation},
                "decoded": {"decoders": self.decoder_list()},
            },
            "encodings": list(P.ENCODINGS),
            "default_encoding": "binary",
            "params": {"rev": info.rev, "sha256": info.sha256},
            "limits": limits(self.service.settings),
        }

    def decoder_classes(self) -> dict[str, list[str]]:
        """Usable installed decoders (name -> the classes they read), in the hello's order; none with a
        population (decoders read taxels)."""
        if self.service.population is not None:
            return {}
        return {m["name"]: list(m["classes"]) for m in self.service.models.list() if "error" not in m}

    def decoders_view(self) -> list[dict[str, Any]]:
        """Installed decoder models (``GET /v1/decoders``, also through a gateway): metadata, and a
        warning where the active parameters differ from the ones a model was trained on."""
        params = self.service.store.active
        # a model's file is named, not located: no path of this machine goes out
        return [{**m, "file": Path(m["file"]).name, "warning": None if "error" in m else params_warning(m, params)}
                for m in self.service.models.list()]

    def decoder_list(self) -> list[dict[str, Any]]:
        """The hello's decoders: what a client needs to read decoded frames (index = position here);
        none with a population (:meth:`decoder_classes`)."""
        if self.service.population is not None:
            return []
        params = self.service.store.active
        out = []
        for m in self.service.models.list():
            if "error" in m:
                continue
            out.append({"name": m["name"], "task": m["task"], "outputs": m["output_names"], "classes": m["classes"],
                        "window_us": int(round(m["window_ms"] * 1000)), "step_us": int(round(m["step_ms"] * 1000)),
                        "warning": params_warning(m, params)})
        return out

    def status(self) -> dict[str, Any]:
        """``GET /v1/status``; the source's spec, its texts and the pipeline's error go through
        :func:`~touchreal.redaction.redact` (a URL source or port may carry credentials). Sets of
        taxels (demand, active columns) are id ranges (:func:`touchreal_client.protocol.id_ranges`),
        so the status of a 65,536-taxel skin stays a few kilobytes."""
        rt = self.service.runtime
        src = (rt.source.status() if rt is not None else {"state": "failed", "error": self.service.source_error}
               if self.service.opened.is_set() else {"state": "opening", "error": None})
        error = rt.error if rt else self.service.source_error
        return {
            "session": self.service.session,
            "source": {k: redact(v) if isinstance(v, str) else v
                       for k, v in {"spec": self.service.config.source, **src}.items()},
            "pipeline": {"state": rt.state if rt else "stopped", "error": error and redact(error),
                         "updates": rt.update_no if rt else 0,
                         "mains_hz": rt.encoder.mains_hz if rt and rt.encoder is not None else None,
                         "active": {c: P.id_ranges(t) for c, t in rt.active.items()} if rt and rt.active is not None else None},
            "demand": {"columns": {c: P.id_ranges(t) for c, t in self.service.hub.demand.columns.items()},
                       "channel_taxels": P.id_ranges(self.service.hub.demand.channel_taxels),
                       "decoders": {n: P.id_ranges(t) for n, t in self.service.hub.demand.decoders.items()}},
            "clients": [{"id": s.id, "seq": s.seq, "sent": s.sent, "dropped": s.dropped, "queued": len(s.queue)}
                        for s in self.service.hub.subscribers.values()],
            "realtime": self.realtime(),
            "faults": dict(rt.counters) if rt else {},
            "params": {"rev": self.service.store.active_rev, "sha256": self.service.store.info().sha256,
                       "fallback": self.service.store.fallback_reason},
            "ended": self.service.ended,
            **{name: section() for name, section in self.service.status_sections.items()},
        }

    def ready(self) -> tuple[bool, str]:
        if not self.service.opened.is_set():
            return False, "warming up (compiling the pipeline, opening the source)"
        rt = self.service.runtime
        if rt is None:
            return False, redact(f"source not open: {self.service.source_error}")
        if rt.state in ("failed", "stopped"):
            return False, redact(f"pipeline {rt.state}: {rt.error}")
        st = rt.source.status().get("state")
        if st != "streaming":
            return False, f"source {st}"
        if rt.state == "starting":
            return False, "pipeline warming up"
        return True, self.health()

    def realtime(self) -> dict[str, Any]:
        """Whether compute keeps up with acquisition (``/v1/status``'s ``realtime``): the latest
        chunk's lag (ms, clock model), the real-time factor (wall time per second of signal; < 1
        keeps up), and what was shed because compute fell more than ``max_lag_ms`` behind."""
        rt = self.service.runtime
        last = rt.last_shed_us if rt is not None else None
        enc = rt.encoder if rt is not None else None
        detector = enc.detector if enc is not None else None
        return {"compute": "dense" if rt is None or rt.activity is None else "sparse",
                "taxels": rt.source.n_taxels if rt else 0, "awake_taxels": enc.awake_taxels if enc is not None else 0,
                "activity": ({**detector.counters, "stuck_taxels": detector.stuck, "plan": detector.plan.describe()}
                             if detector is not None else None),
                "lag_ms": round(rt.lag_s * 1e3, 3) if rt else 0.0, "max_lag_ms": self.service.settings.max_lag_ms,
                "real_time_factor": round(rt.real_time_factor, 4) if rt else 0.0,
                "shed_ms": round(rt.shed_s * 1e3, 1) if rt else 0.0, "sheds": rt.sheds if rt else 0,
                "last_shed_age_s": None if last is None else round((wall_us() - last) / 1e6, 3)}

    def health(self) -> str:
        """``ok``; ``degraded: WHY`` while the parameters in force are a fallback, or while the
        simulated skin or compute has fallen behind within the last :data:`SHED_DEGRADED_S`;
        ``failed`` once the acquisition thread has failed."""
        rt = self.service.runtime
        if rt is not None and rt.state == "failed":
            return "failed"
        if self.service.store.fallback_reason:
            return f"degraded: {self.service.store.fallback_reason}"
        src = rt.source.status() if rt is not None else {}
        if src.get("behind_wall_us") is not None and wall_us() - src["behind_wall_us"] < SHED_DEGRADED_S * 1e6:
            return (f"degraded: the simulated skin cannot be simulated in real time on this machine; it fell behind "
                    f"{src['fell_behind']} times, {src['behind_s']:.1f} s in all (its clock restarted each time)")
        if rt is not None and rt.last_shed_us is not None and wall_us() - rt.last_shed_us < SHED_DEGRADED_S * 1e6:
            return (f"degraded: compute fell behind acquisition; {rt.shed_s:.1f} s of signal shed in {rt.sheds} "
                    f"chunks (max_lag_ms {self.service.settings.max_lag_ms:g}, real-time factor "
                    f"{rt.real_time_factor:.2f})")
        return "ok"

    def config_view(self) -> dict[str, Any]:
        p, config = self.service.store.active.preprocess, self.service.config
        return {**config.model_dump(), "source": redact(config.source), "update_ms": p.update_ms,
                "window_ms": p.window_ms}
