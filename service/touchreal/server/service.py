"""The service's state and what changes it: source + runtime, hub, parameter store, metrics, and the
changes clients ask for (config, parameters). What it reports (hello, status, readiness, views) is
:class:`~.view.ServiceView`, ``Service.view``: the routers read through the view and write through
the service.

Clients are told what they need to trust a spike in time: the source's clock model as a ``clock``
message (after every ``hello``, at least every :data:`CLOCK_EVERY_US`, and at once when the mapping
jumps), and a new ``hello`` whenever what it describes changes (parameter revision, windows,
classes, decoders, the address map).

Threading: the acquisition :class:`~.runtime.Runtime` runs on its own thread and posts each update
to the event loop (``call_soon_threadsafe``), then waits at most :data:`HANDOFF_S` until the loop has
taken it up, so the fan-out gets the interpreter lock first; everything else here runs on the event
loop. If the loop falls more than :data:`MAX_BACKLOG` updates behind, further updates are dropped and
counted (``touchreal_updates_dropped_overload``) rather than queued without bound; every subscriber
is told with the next update it gets: its ``seq`` jumps and ``dropped`` counts one frame per lane
(spikes, channels, a decoder's outputs) it takes for each update lost (see :meth:`.hub.Hub.skip`),
so no loss goes unseen.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from touchreal_client import protocol as P
from touchreal_client.clock import ClockPoint

from ..population.encoder import Population
from ..population.layout import PopulationPlan
from ..decoding.model import ModelStore, params_warning
from ..dryrun import prove_runnable
from ..fitting.variants import resolve_plan
from ..params import EncoderParams, ParamsError
from ..preprocess.activity import ActivityPlan
from ..redaction import redact
from .hub import Hub
from .metrics import Metrics
from .params_store import ParamsStore
from .runtime import Runtime, Update, wall_us
from .settings import ConfigPatch, RuntimeConfig, ServeSettings, parse_source
from .sources import SourceRefused, confine_source, open_source
from .view import ServiceView

log = logging.getLogger("touchreal.server")
MAX_BACKLOG = 64
#: After posting an update the acquisition thread waits at most this long (s) for the event loop to
#: take it up: the GIL passes to the fan-out at once instead of when the acquisition thread next
#: blocks (e.g. after a slow class's frame); without it the p99 fan-out latency to 100 subscribers
#: is about 1 ms longer (docs/architecture.md).
HANDOFF_S = 0.002
CLOCK_EVERY_US = 1_000_000  #: the clock model is restated at least this often (us)


def _lanes(upd: Update) -> list[tuple[str, str | None]]:
    """The (stream, decoder) lanes an update feeds: spikes and channels, or its decoders' outputs."""
    lanes: list[tuple[str, str | None]] = [("spikes", None)] if upd.spikes else []
    if upd.channels is not None:
        lanes.append(("channels", None))
    return lanes + [("decoded", name) for name, *_ in upd.decoded]


def _settle_heap() -> None:
    """Collect once, then exempt everything alive (modules, the warmed-up kernels: some 300,000
    objects) from the cyclic garbage collector: its full passes over them stalled the event loop
    for about 150 ms every few seconds of streaming; afterwards they only walk what was made since."""
    gc.collect()
    gc.freeze()


class SourceOpenError(ValueError):
    """A source change whose source cannot be opened (the previous source was restored)."""


class Service:
    def __init__(self, settings: ServeSettings, config: RuntimeConfig):
        kind, arg = parse_source(config.source)  # fail early on a bad spec
        self.settings, self.config = settings, config
        #: where PATCH /v1/config may open replays: STATE_DIR/datasets, the settings' roots, serve's own --source folder
        self.data_roots = [Path(settings.state_dir) / "datasets", *settings.data_roots,
                           *([Path(arg.partition(":")[0])] if kind == "replay" else [])]
        self.session = uuid.uuid4().hex
        self.started_us = wall_us()
        self.store = ParamsStore(settings.state_dir, settings.params)
        self.models = ModelStore(Path(settings.state_dir) / "models")
        self.metrics = Metrics()
        self.metrics.follow(lambda: self.runtime)
        self.hub = Hub(settings.queue_frames, settings.slow_timeout_s, settings.max_frame_age_ms / 1000 or None,
                       refresh_s=settings.hop_ms / 1000)
        self.hub.on_drop = self.metrics.count_drop
        self.view = ServiceView(self)  #: what this service reports (read-only)
        #: the population plan spikes follow (None: one afferent per taxel and class), resolved at the first
        #: source open; the population built from it for the open source's taxels
        self.population_plan: PopulationPlan | None = None
        self.population: Population | None = None
        #: the scanning speed (mm/s) a robot reports (``PUT /v1/context``) for decoders that read one; None: unknown
        self.scan_speed_mm_s: float | None = None
        self.runtime: Runtime | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.clock: ClockPoint | None = None  #: the source's clock model, as last told to the clients
        self._clock_told_us = 0
        #: called with each ``clock`` message text as it goes to the clients (e.g. the NATS publisher)
        self.clock_listeners: list[Callable[[str], None]] = []
        self._hello_key: tuple | None = None
        self.opened = threading.Event()  #: set once the warm-up and the first source open are done
        #: more sections of ``/v1/status`` (name -> callable), e.g. the NATS publisher's ``nats``
        self.status_sections: dict[str, Callable[[], dict[str, Any]]] = {}
        self._startup: asyncio.Task | None = None
        self._posted = 0
        self._delivered = 0
        self._taken = threading.Event()  #: set by the event loop as it takes up a posted update
        #: per (stream, decoder): frames of the updates _post dropped since the last one it posted (acquisition thread)
        self._lost: dict[tuple[str, str | None], int] = {}
        self.source_error: str | None = None
        self.ended: dict[str, Any] | None = None  #: the ``ended`` message once the source has ended (a finished replay)
        #: decoder name -> (its file's identity, the loaded model, its session): :meth:`_make_decoder`
        self._decoder_models: dict[str, tuple[tuple, Any, Any]] = {}

    # -- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        """Start serving at once: the JIT warm-up and the source open in the background, and
        ``/v1/ready`` says so until they are done (``/v1/health`` answers meanwhile)."""
        self.loop = asyncio.get_running_loop()
        self._startup = asyncio.create_task(self._warm_and_open())

    async def _warm_and_open(self) -> None:
        try:
            await asyncio.to_thread(self._prove_active)
            _settle_heap()
            await self._open_runtime()
        finally:
            self.opened.set()

    def _prove_active(self) -> None:
        """The dry run of the active set (which also compiles the numba kernels, cached on disk
        after the first run); a set that does not run is replaced by the shipped one, logged."""
        rev, params = self.store.current
        try:
            prove_runnable(params)
        except ParamsError as exc:
            self.store.fall_back(None, f"parameter revision {rev} does not run: {exc}")
            prove_runnable(self.store.active)

    def _fall_back(self, failed: int, good: int | None, exc: Exception) -> bool:
        """Called on the acquisition thread when revision ``failed`` raised in the pipeline: activate
        the last revision that ran (else the shipped set) unless ``failed`` is itself a fallback."""
        if self.store.active_rev != failed:
            return True  # a newer set is already active: the runtime takes it up next update
        if self.store.info(failed).origin.startswith("fallback:"):
            return False
        reason = f"parameter revision {failed} failed in the pipeline: {type(exc).__name__}: {exc}"
        try:
            self.store.fall_back(good if good not in (None, failed) else None, reason)
        except (KeyError, ParamsError):  # the good revision left the history meanwhile
            self.store.fall_back(None, reason)
        return True

    async def stop(self) -> None:
        if self._startup is not None and not self._startup.done():
            self._startup.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._startup
        if self.runtime is not None:
            rt, self.runtime = self.runtime, None
            await asyncio.to_thread(rt.stop)

    async def _open_runtime(self, device_present: bool = False) -> str | None:
        """Open the configured source and start the runtime on it; returns why it could not open (None: it
        did). ``device_present``: a serial device must be there and free now (:func:`.sources.open_source`)."""
        try:
            source = await asyncio.to_thread(open_source, self.config, self.settings, self.view.hop_ms() / 1000.0,
                                             device_present)
        except (ValueError, OSError) as exc:
            self.source_error = str(exc)
            log.error("cannot open source %s: %s", redact(self.config.source), redact(str(exc)))
            return self.source_error
        self.source_error, self.ended = None, None
        self.population = None
        if self.settings.population:
            try:
                self.population = pop = await asyncio.to_thread(self._build_population, source.positions_mm)
            except (ValueError, OSError) as exc:
                source.close()
                self.source_error = f"population: {exc}"
                log.error("cannot build the population: %s", redact(str(exc)))
                return self.source_error
            self.hub.configure(len(pop), self.view.served_classes(), {}, pop.layout.xy_mm, addresses="afferents")
        else:
            self.hub.configure(source.n_taxels, self.view.served_classes(), self.view.decoder_classes(),
                               source.positions_mm, addresses="taxels")
        self.runtime = Runtime(source, lambda: self.hub.demand, lambda: self.store.current, self._post, self._make_decoder,
                               self.settings.taxel_block or None, self._fall_back, self._post_end,
                               self.settings.compute_dtype, None if self.settings.dense else ActivityPlan(),
                               self.settings.max_lag_ms / 1000.0, self._shed, self.population,
                               lambda: self.scan_speed_mm_s)
        self.clock = None
        self.runtime.start()
        self.announce_hello()  # the address map may have changed: say it again
        return None

    def _build_population(self, taxels_xy_mm) -> Population:
        """The population for the source's taxels; the plan is resolved once (``fingertip``: the default
        plan with its model variants matched for the active parameters) and logged."""
        if self.population_plan is None:
            spec = self.settings.population
            self.population_plan = resolve_plan(self.store.active, path=None if spec == "fingertip" else Path(spec))
            log.info("population plan: %s", self.population_plan.to_json().replace("\n", ""))
        return Population.build(taxels_xy_mm, self.population_plan)

    async def restart_source(self, device_present: bool = False) -> str | None:
        """Close and reopen the source; returns why it could not open (None: it did)."""
        await self.stop()
        return await self._open_runtime(device_present)

    # -- acquisition thread -> event loop ------------------------------------------------------------
    def _post(self, upd: Update) -> None:
        """Called on the acquisition thread; blocks at most HANDOFF_S."""
        if self._posted - self._delivered >= MAX_BACKLOG:
            self.metrics.overload.inc()
            for lane in _lanes(upd):
                self._lost[lane] = self._lost.get(lane, 0) + 1
            return
        self._posted += 1
        self._taken.clear()
        self.loop.call_soon_threadsafe(self._deliver, upd, self._lost)
        self._lost = {}
        self._taken.wait(HANDOFF_S)  # hand the GIL to the event loop (HANDOFF_S)

    def _shed(self, seconds: float, began: bool) -> None:
        """Called on the acquisition thread for each chunk it dropped (:meth:`.runtime.Runtime._shed`;
        ``began``: the first of a shed): the update it did not make is lost for every subscriber, one
        frame per lane the demand feeds, told with the next update (``upstream_loss``), and counted."""
        demand = self.hub.demand
        lanes = [("spikes", None)] + ([("channels", None)] if demand.channel_taxels else [])
        for lane in lanes + [("decoded", name) for name in demand.decoders]:
            self._lost[lane] = self._lost.get(lane, 0) + 1
        self.metrics.shed_seconds.inc(seconds)
        if began:
            self.metrics.sheds.inc()

    def _post_end(self) -> None:
        """Called on the acquisition thread after the source's last update was posted."""
        self.loop.call_soon_threadsafe(self._deliver_end)

    def _deliver_end(self) -> None:
        """Tell every client, after the frames queued for it, that the stream has ended."""
        if self.runtime is None:
            return
        st = self.runtime.source.status()
        if st.get("kind") == "replay":
            self.ended = {"type": "ended", "reason": "replay_finished", "trials": int(st.get("segment", -1)) + 1,
                          "end_us": int(st.get("end_us", 0))}
        else:
            self.ended = {"type": "ended", "reason": "source_ended"}
        text = json.dumps(self.ended, separators=(",", ":"))
        for sub in self.hub.subscribers.values():
            if sub.takes_control:
                sub.say_after_frames(text)

    def _deliver(self, upd: Update, lost_before: dict[tuple[str, str | None], int] | None = None) -> None:
        """Publish ``upd``; ``lost_before``: per (stream, decoder) the frames of the updates dropped
        between it and the one before (overload). The metrics are kept after the fan-out
        (:meth:`_account`): its senders go first."""
        self._taken.set()
        self._delivered += 1
        self._follow_served_classes()  # whichever way a parameter set became active
        self._tell_clock(upd.clock)
        if self._hello_key != self.view.describe():
            self.announce_hello()
        for (stream, decoder), n in (lost_before or {}).items():
            self.hub.skip(n, stream, decoder)
        self.hub.publish(upd)
        self.loop.call_soon(self._account, upd)

    def _account(self, upd: Update) -> None:
        """The metrics of one delivered update (on the event loop, after its fan-out's senders)."""
        m = self.metrics
        if upd.spikes:  # (not the decoders' outputs that follow it)
            m.updates.inc()
            m.compute.observe(upd.compute_s)
        for i, c in enumerate(P.CLASSES):
            n = int((upd.cls == i).sum())
            if n:
                m.events.labels(c).inc(n)
        for c, lat in upd.latency_us.items():
            m.latency.observe(c, lat)
        if self.runtime is not None:
            for kind, v in self.runtime.counters.items():
                m.faults.labels(kind).set(v)
            state = str(self.runtime.source.status().get("state"))
            for s in ("connecting", "streaming", "disconnected", "closed", "ended"):
                m.source_state.labels(s).set(1.0 if s == state else 0.0)
        m.ready.set(1.0 if self.view.ready()[0] else 0.0)
        for sub in self.hub.subscribers.values():
            if sub.dropped:
                m.client_drops.labels(str(sub.id)).set(sub.dropped)

    # -- what clients are told besides frames ------------------------------------------------------
    def _tell_clock(self, point: ClockPoint | None) -> None:
        """Restate the clock model when its epoch changes or CLOCK_EVERY_US has passed."""
        if point is None:
            return
        now = wall_us()
        if self.clock is None or point.epoch != self.clock.epoch or now - self._clock_told_us >= CLOCK_EVERY_US:
            self.clock, self._clock_told_us = point, now
            text = json.dumps(point.to_json(), separators=(",", ":"))
            self.hub.broadcast(text)
            for listener in self.clock_listeners:
                listener(text)

    def announce_hello(self) -> None:
        """Send the current hello (then the clock) to every client."""
        self._hello_key = self.view.describe()
        self.hub.broadcast(json.dumps(self.view.hello(), separators=(",", ":")))
        clock = self.view.clock_message()
        if clock is not None:
            self.hub.broadcast(clock)

    def _follow_served_classes(self) -> None:
        if self.view.served_classes() != self.hub.allowed_classes:
            self.hub.configure(self.view.n_taxels, self.view.served_classes(), self.view.decoder_classes())

    def _make_decoder(self, name: str, taxels: tuple[int, ...]):
        """Called on the acquisition thread when a decoder becomes demanded. The model and its
        onnxruntime session are loaded once per model file (kept while the file is unchanged), so a
        client that toggles a decoder on and off costs a binner, not a model load."""
        from ..decoding.streaming import StreamingDecoder

        path = self.models.path(name)
        stat = path.stat()
        key = (str(path), stat.st_mtime_ns, stat.st_size)
        cached = self._decoder_models.get(name)
        if cached is None or cached[0] != key:
            model = self.models.load(name)
            warning = params_warning(model.meta, self.store.active)
            if warning:
                log.warning(warning)
            cached = self._decoder_models[name] = (key, model, model.session(1))
        _, model, session = cached
        return StreamingDecoder(model, taxels, session=session)

    async def patch_config(self, patch: ConfigPatch) -> dict[str, Any]:
        """Apply a validated patch; returns the new config and what was restarted. Raises ValueError
        (nothing changed), ParamsError (the new preprocessing does not run; nothing changed) or
        :class:`SourceOpenError` (the new source cannot be opened; the previous one runs again)."""
        changes = patch.model_dump(exclude_none=True)
        if not self.settings.source_changes and changes.keys() & {"source", "taxels", "speed", "loop"}:
            raise SourceRefused("source changes are off on this service (TOUCHREAL_SOURCE_CHANGES)")
        if "source" in changes:
            confine_source(changes["source"], self.data_roots, self.settings.serial_urls)
        if "classes" in changes:
            bad = [c for c in changes["classes"] if c not in P.CLASSES]
            if bad:
                raise ValueError(f"classes: unknown {bad}; expected names from {list(P.CLASSES)}")
        restarted = []
        pre = {k: changes.pop(k) for k in ("update_ms", "window_ms") if k in changes}
        if pre:
            params = self.store.active
            new = params.model_copy(update={"preprocess": params.preprocess.model_copy(update=pre)})
            await self.put_params(EncoderParams.parse(new.to_json()), "config")
            restarted.append("pipeline")
        old, cfg = self.config, self.config.model_copy(update=changes)
        source_change = any(getattr(cfg, k) != getattr(old, k) for k in ("source", "taxels", "speed", "loop"))
        self.config = cfg
        if source_change or "update_ms" in pre:
            error = await self.restart_source(device_present=source_change)
            if error is not None and source_change:
                self.config = old
                await self.restart_source()
                raise SourceOpenError(redact(f"cannot open source: {error} (the previous source {old.source!r} runs "
                                             "again)"))
            restarted.append("source")
        elif "classes" in changes:
            self.hub.configure(self.view.n_taxels, self.view.served_classes(), self.view.decoder_classes())
        return {"config": self.view.config_view(), "restarted": restarted}

    async def put_params(self, params: EncoderParams, origin: str = "upload") -> int:
        """A validated set, proved runnable (:func:`~touchreal.dryrun.prove_runnable`, raises
        ParamsError), becomes active at the start of the next update; a failed runtime restarts."""
        await asyncio.to_thread(prove_runnable, params)
        rev = self.store.put(params, origin)
        self._follow_served_classes()
        if self.runtime is not None and self.runtime.state == "failed":
            await self.restart_source()
        return rev

    async def rollback(self, rev: int) -> int:
        """Activate revision ``rev`` again as a new revision (KeyError: not kept; ParamsError: it no
        longer validates or runs)."""
        return await self.put_params(self.store.load(rev), f"rollback:{rev}")
