// TouchReal live dashboard: one /v1/stream connection (binary frames), REST for the causal window.
// State is kept per class/taxel for the last SPAN_US of sensor time and drawn every animation frame.
"use strict";
(() => {
  const { CLASSES, FLAGS, decode } = TRProtocol;
  const SPAN_US = 5e6;
  const COLORS = { SA1: "#4fc3f7", RA: "#ffb74d", PC: "#e57373" };
  const $ = (id) => document.getElementById(id);
  const nowUs = () => (performance.timeOrigin + performance.now()) * 1000;

  const state = {
    hello: null, subscribed: null, connected: false, ws: null, retryMs: 500,
    spikes: [],            // {t, taxel, cls}
    finalUs: 0,            // latest sensor time that is final for some class
    force: new Map(),      // taxel -> [[t_us, N], ...] measured ST
    decodedForce: new Map(),  // taxel -> [[t_us, N], ...]
    texture: null, decodedNames: [],
    frames: 0, events: 0, drawnSpikes: 0, nextSeq: null, gaps: 0, missed: 0, serverDropped: 0, sourceGaps: 0,
    offsetUs: 0, bestRtt: Infinity, delivery: [], rate: { t: performance.now(), frames: 0, events: 0 },
    clocks: [],            // the server's clock model: recent {sensor_us, wall_us, rate, epoch} points
    spikeLatency: { SA1: [], RA: [], PC: [] },  // receipt minus acquisition of the causing sample (us)
  };
  window.touchreal = state;  // for the browser test and the console

  function log(text, err) {
    const li = document.createElement("li");
    li.textContent = `${new Date().toLocaleTimeString()} ${text}`;
    if (err) li.className = "err";
    $("log").prepend(li);
    while ($("log").children.length > 30) $("log").lastChild.remove();
  }

  // -- subscription ------------------------------------------------------------------------------
  function subscriptionFromForm() {
    const raw = $("taxels").value.trim();
    let taxels = null;
    if (raw && raw !== "all") {
      taxels = raw.split(/[\s,]+/).filter(Boolean).map(Number);
      if (taxels.some((t) => !Number.isInteger(t) || t < 0)) throw new Error("taxels: 'all' or a list of ids such as 0,1,4");
    }
    const picked = (name) => [...document.querySelectorAll(`input[name=${name}]:checked`)].map((e) => e.value);
    // the decoded panel shows one force and one texture model (each decoder costs the service an inference per step)
    const names = state.decodedNames.map((d) => d.name), decoders = ["force", "texture"].filter((n) => names.includes(n));
    // over a population (hello.addresses "afferents", protocol version 2) the ids are afferents, which have spikes only
    const population = isPopulation(), streams = picked("stream").filter((x) => !population || x === "spikes");
    return { type: "subscribe", version: state.hello && (state.hello.versions || []).includes(2) ? 2 : 1, taxels,
             classes: picked("cls"), streams, encoding: "binary", channels: { decimation: 50 }, decoders };
  }

  function isPopulation() {
    return !!(state.hello && state.hello.addresses === "afferents" && state.hello.population);
  }

  function sendSubscription() {
    if (!state.connected) return;
    try {
      state.ws.send(JSON.stringify(subscriptionFromForm()));
    } catch (e) { log(e.message, true); }
  }

  // -- connection --------------------------------------------------------------------------------
  function connect() {
    const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/v1/stream`);
    ws.binaryType = "arraybuffer";
    state.ws = ws;
    ws.onmessage = (ev) => (typeof ev.data === "string" ? onText(JSON.parse(ev.data)) : onFrame(decode(ev.data)));
    ws.onclose = (ev) => {
      state.connected = false; state.nextSeq = null;
      $("conn").textContent = `disconnected (${ev.code}${ev.reason ? ": " + ev.reason : ""}), retrying`;
      $("conn").className = "pill off";
      setTimeout(connect, state.retryMs);
      state.retryMs = Math.min(state.retryMs * 2, 5000);
    };
  }

  function onText(m) {
    if (m.type === "hello") {
      const fresh = !state.hello || state.hello.session !== m.session;
      state.hello = m; state.connected = true; state.retryMs = 500;
      state.decodedNames = (m.streams.decoded && m.streams.decoded.decoders) || [];
      const units = m.addresses === "afferents" && m.population
        ? `${m.population.n_afferents} afferents over ${m.n_taxels} taxel(s)` : `${m.n_taxels} taxel(s)`;
      $("conn").textContent = `${m.server} · ${units} · session ${m.session.slice(0, 8)}`;
      $("conn").className = "pill on";
      if (fresh) { state.spikes = []; state.force.clear(); state.decodedForce.clear(); state.finalUs = 0; state.clocks = []; }
      if (m.clock) onClock(m.clock);
      sendSubscription();
      syncClock();
    } else if (m.type === "subscribed") {
      state.subscribed = m;
      log(`subscribed: taxels ${m.taxels === null ? "all" : m.taxels.join(",")}, ${m.classes.join("/")}, ${m.streams.join("+")}`);
    } else if (m.type === "time") {
      const t3 = nowUs(), rtt = (t3 - m.t0_us) - (m.t2_us - m.t1_us);
      if (rtt <= state.bestRtt) { state.bestRtt = rtt; state.offsetUs = ((m.t1_us - m.t0_us) + (m.t2_us - t3)) / 2; }
    } else if (m.type === "clock") {
      onClock(m);
    } else if (m.type === "error") {
      log(`server: ${m.code}: ${m.message}`, true);
    }
  }

  // the clock model (docs/stream-protocol.md, "clock"): keep the points of the last few epochs
  function onClock(c) {
    const last = state.clocks[state.clocks.length - 1];
    if (last && (c.epoch < last.epoch || (c.epoch === last.epoch && c.sensor_us < last.sensor_us))) return;
    if (last && c.sensor_us < last.sensor_us) state.clocks = [];
    state.clocks.push({ sensor_us: c.sensor_us, wall_us: c.wall_us, rate: c.rate, epoch: c.epoch });
    if (state.clocks.length > 16) state.clocks.shift();
  }

  // local wall time (us) at which the sample stamped t (wire clock) was acquired; NaN before any point
  function toLocal(t) {
    let p = null;
    for (const q of state.clocks) if (q.sensor_us <= t || p === null) p = q;
    return p === null ? NaN : p.wall_us + (t - p.sensor_us) * p.rate - state.offsetUs;
  }

  function syncClock() {
    for (let i = 0; i < 3; i++) {
      setTimeout(() => state.connected && state.ws.send(JSON.stringify({ type: "time", id: i, t0_us: Math.round(nowUs()) })), 200 * i);
    }
  }

  function onFrame(f) {
    const h = f.header;
    if (state.nextSeq !== null && h.seq !== state.nextSeq) { state.gaps += 1; state.missed += (h.seq - state.nextSeq) >>> 0; }
    state.nextSeq = (h.seq + 1) >>> 0;
    state.serverDropped = h.dropped;
    if (h.flags & FLAGS.SOURCE_GAP) state.sourceGaps += 1;
    state.frames += 1; state.rate.frames += 1;
    state.delivery.push(nowUs() + state.offsetUs - h.emit_us);
    if (state.delivery.length > 200) state.delivery.shift();
    if (f.type === "spikes") onSpikes(f);
    else if (f.type === "channels") onChannels(f);
    else onDecoded(f);
  }

  function onSpikes(f) {
    const recv = nowUs(), delays = (state.hello && state.hello.delay_us) || {};
    for (let i = 0; i < f.t_us.length; i++) {
      state.spikes.push({ t: f.t_us[i], taxel: f.taxel[i], cls: f.cls[i] });
      const c = CLASSES[f.cls[i]], lat = recv - toLocal(f.t_us[i] - (delays[c] || 0));
      if (Number.isFinite(lat)) { state.spikeLatency[c].push(lat); if (state.spikeLatency[c].length > 500) state.spikeLatency[c].shift(); }
    }
    state.events += f.t_us.length; state.rate.events += f.t_us.length;
    for (const c of CLASSES) if (f.final_us[c] !== null) state.finalUs = Math.max(state.finalUs, f.final_us[c]);
    const keep = state.finalUs - SPAN_US;
    let k = 0;
    while (k < state.spikes.length && state.spikes[k].t < keep) k++;
    if (k) state.spikes.splice(0, k);
  }

  function pushTrace(map, taxel, t, v) {
    if (!map.has(taxel)) map.set(taxel, []);
    const tr = map.get(taxel);
    tr.push([t, v]);
    while (tr.length && tr[0][0] < t - SPAN_US) tr.shift();
  }

  function onChannels(f) {
    const nt = f.taxels.length, nc = f.n_channels;
    for (let s = 0; s < f.n_samples; s++) {
      const t = f.t0_us + s * f.period_us;
      for (let i = 0; i < nt; i++) pushTrace(state.force, f.taxels[i], t, f.data[(s * nt + i) * nc]);  // channel 0 = ST (N)
      state.finalUs = Math.max(state.finalUs, t);
    }
  }

  function onDecoded(f) {
    const d = state.decodedNames[f.decoder] || { name: `#${f.decoder}`, outputs: [] };
    const nt = f.taxels.length, nv = f.n_values, labels = d.task === "texture" ? d.outputs : null;  // one probability per label
    for (let s = 0; s < f.t_us.length; s++) {
      for (let i = 0; i < nt; i++) {
        const row = f.values.subarray((s * nt + i) * nv, (s * nt + i + 1) * nv);
        if (d.outputs[0] === "force_N" && Number.isFinite(row[0])) {
          pushTrace(state.decodedForce, f.taxels[i], f.t_us[s], row[0]);
          $("decoded-force").textContent = `${row[0].toFixed(2)} N (${d.name}, taxel ${f.taxels[i]})`;
        } else if (labels && i === 0 && row.every(Number.isFinite)) {
          let best = 0;
          for (let j = 1; j < Math.min(nv, labels.length); j++) if (row[j] > row[best]) best = j;
          state.texture = `${labels[best]} (p = ${row[best].toFixed(2)}, ${d.name})`;
          $("texture").textContent = state.texture;
        }
      }
    }
  }

  // -- drawing -----------------------------------------------------------------------------------
  function taxelList() {
    const sub = state.subscribed;
    if (sub && sub.taxels !== null) return sub.taxels;
    if (!state.hello) return [0];
    return state.hello.taxels ? state.hello.taxels.map((t) => t.id) : [...Array(Math.min(state.hello.n_taxels, 32)).keys()];
  }

  // per class, the ids of its raster rows (at most 32): every taxel has every class; an afferent has one
  function rowIds() {
    if (!isPopulation()) { const ids = taxelList().slice(0, 32); return CLASSES.map(() => ids); }
    const sub = state.subscribed, wanted = sub && sub.taxels !== null ? new Set(sub.taxels) : null;
    return CLASSES.map((c) => {
      const ids = [];
      for (const [a, b] of state.hello.population.classes[c] || []) {
        for (let i = a; i < b && ids.length < 32; i++) if (!wanted || wanted.has(i)) ids.push(i);
      }
      return ids;
    });
  }

  function drawRaster() {
    const cv = $("raster"), g = cv.getContext("2d"), W = cv.width, H = cv.height;
    g.clearRect(0, 0, W, H);
    const ids = rowIds(), first = [], rows = ids.reduce((n, r) => (first.push(n), n + r.length), 0);
    const rowH = (H - 20) / Math.max(rows, 1);
    const x0 = 60, t0 = state.finalUs - SPAN_US, sx = (W - x0 - 10) / SPAN_US;
    g.font = "11px sans-serif";
    CLASSES.forEach((c, ci) => {
      g.fillStyle = COLORS[c];
      g.fillText(c, 4, (first[ci] + ids[ci].length / 2) * rowH + 4);
      g.fillStyle = "#1c2630";
      g.fillRect(x0, first[ci] * rowH, W - x0 - 10, 1);
    });
    const rowOf = ids.map((r) => new Map(r.map((t, i) => [t, i])));
    let drawn = 0;
    for (const s of state.spikes) {
      const r = rowOf[s.cls].get(s.taxel);
      if (r === undefined || s.t < t0) continue;
      g.fillStyle = COLORS[CLASSES[s.cls]];
      g.fillRect(x0 + (s.t - t0) * sx, (first[s.cls] + r) * rowH + 1, 1.5, Math.max(rowH - 2, 1));
      drawn++;
    }
    state.drawnSpikes = drawn;
    g.fillStyle = "#8a96a3";
    g.fillText(`${(t0 / 1e6).toFixed(2)} s`, x0, H - 4);
    g.fillText(`${(state.finalUs / 1e6).toFixed(2)} s (sensor clock)`, W - 170, H - 4);
  }

  function drawForce() {
    const cv = $("force"), g = cv.getContext("2d"), W = cv.width, H = cv.height;
    g.clearRect(0, 0, W, H);
    const x0 = 40, t0 = state.finalUs - SPAN_US, sx = (W - x0 - 10) / SPAN_US;
    let top = 1;
    for (const m of [state.force, state.decodedForce]) for (const tr of m.values()) for (const [, v] of tr) top = Math.max(top, v);
    const sy = (H - 20) / (top * 1.1), y = (v) => H - 14 - v * sy;
    g.fillStyle = "#8a96a3"; g.font = "11px sans-serif";
    g.fillText(`${top.toFixed(1)} N`, 2, y(top) + 4); g.fillText("0", 2, y(0) + 4);
    const line = (tr, color, dash) => {
      g.strokeStyle = color; g.setLineDash(dash); g.beginPath();
      tr.forEach(([t, v], i) => (i ? g.lineTo : g.moveTo).call(g, x0 + (t - t0) * sx, y(v)));
      g.stroke();
    };
    for (const tr of state.force.values()) line(tr, "#9ccc65", []);
    for (const tr of state.decodedForce.values()) line(tr, "#ce93d8", [6, 4]);
    g.setLineDash([]);
  }

  function median(a) { const s = [...a].sort((x, y) => x - y); return s.length ? s[s.length >> 1] : NaN; }

  function drawFigures() {
    const dt = (performance.now() - state.rate.t) / 1000;
    if (dt >= 1) {
      $("fps").textContent = (state.rate.frames / dt).toFixed(1);
      $("eps").textContent = (state.rate.events / dt).toFixed(0);
      state.rate = { t: performance.now(), frames: 0, events: 0 };
    }
    const d = median(state.delivery);
    if (Number.isFinite(d)) {
      $("delivery").textContent = `${(d / 1000).toFixed(1)} ms`;
    }
    // per class: median of receipt minus the acquisition of each spike's causing sample
    $("latency").textContent = CLASSES.map((c) => {
      const m = median(state.spikeLatency[c]);
      return Number.isFinite(m) ? (m / 1000).toFixed(0) : "–";
    }).join(" / ") + " ms";
    $("drops").textContent = `${state.missed} (${state.gaps}) / ${state.serverDropped}`;
    $("srcgaps").textContent = state.sourceGaps;
  }

  function frame() {
    drawRaster(); drawForce(); drawFigures();
    requestAnimationFrame(frame);
  }

  // -- REST: causal window -------------------------------------------------------------------------
  async function loadConfig() {
    const r = await fetch("/v1/config");
    const cfg = await r.json();
    $("window-ms").value = cfg.window_ms;
    $("config").textContent = `source ${cfg.source} · ${cfg.taxels} taxel(s) · update ${cfg.update_ms} ms · window ${cfg.window_ms} ms`;
  }

  async function applyWindow(ev) {
    ev.preventDefault();
    const headers = { "Content-Type": "application/json" }, token = $("token").value;
    if (token) headers.Authorization = `Bearer ${token}`;
    const r = await fetch("/v1/config", { method: "PATCH", headers, body: JSON.stringify({ window_ms: Number($("window-ms").value) }) });
    const body = await r.json().catch(() => ({}));
    if (r.ok) log(`window ${body.config.window_ms} ms (restarted: ${body.restarted.join(", ") || "nothing"})`);
    else log(`window not changed: HTTP ${r.status}: ${typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail)}`, true);
    await loadConfig();
  }

  $("sub-form").addEventListener("submit", (ev) => { ev.preventDefault(); sendSubscription(); });
  $("window-form").addEventListener("submit", applyWindow);
  $("span-s").textContent = SPAN_US / 1e6;
  loadConfig().catch((e) => log(`config: ${e}`, true));
  connect();
  setInterval(() => state.connected && syncClock(), 10000);
  requestAnimationFrame(frame);
})();
