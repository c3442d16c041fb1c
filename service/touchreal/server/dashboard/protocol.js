// The /v1/stream binary frames (docs/stream-protocol.md), decoded with DataView: little-endian,
// times in integer microseconds (u64 read as BigInt, returned as Number: exact below 2^53 us).
"use strict";
const TRProtocol = (() => {
  const CLASSES = ["SA1", "RA", "PC"];
  const KIND = { SPIKES: 1, CHANNELS: 2, DECODED: 3 };
  const FLAGS = { SOURCE_GAP: 1, PARAMS_CHANGED: 2, RESTARTED: 4 };
  const u64 = (dv, p) => Number(dv.getBigUint64(p, true));
  const pad4 = (n) => (4 - (n % 4)) % 4;

  function taxelIds(dv, p, n) {
    const ids = new Array(n);
    for (let i = 0; i < n; i++) ids[i] = dv.getUint16(p + 2 * i, true);
    return [ids, p + 2 * n + pad4(2 * n)];
  }

  function decode(buf) {
    const dv = new DataView(buf);
    if (buf.byteLength < 48 || dv.getUint8(0) !== 0x54 || dv.getUint8(1) !== 0x52) throw new Error("not a TouchReal frame");
    if (dv.getUint8(2) !== 1) throw new Error(`unsupported frame version ${dv.getUint8(2)}`);
    const h = {
      kind: dv.getUint8(3), flags: dv.getUint16(4, true), seq: dv.getUint32(8, true), dropped: dv.getUint32(12, true),
      update: u64(dv, 16), emit_us: u64(dv, 24), sent_us: u64(dv, 32), params_rev: dv.getUint32(40, true),
    };
    let p = dv.getUint16(6, true);  // header_len: later versions may append fields
    if (h.kind === KIND.SPIKES) {
      const n = dv.getUint32(p, true), mask = dv.getUint8(p + 4);
      const final_us = {};
      CLASSES.forEach((c, i) => { final_us[c] = (mask >> i) & 1 ? u64(dv, p + 8 + 8 * i) : null; });
      p += 32;
      const t_us = new Float64Array(n), taxel = new Uint16Array(n), cls = new Uint8Array(n);
      for (let i = 0; i < n; i++, p += 12) {
        t_us[i] = u64(dv, p); taxel[i] = dv.getUint16(p + 8, true); cls[i] = dv.getUint8(p + 10);
      }
      return { header: h, type: "spikes", final_us, t_us, taxel, cls };
    }
    if (h.kind === KIND.CHANNELS) {
      const t0_us = u64(dv, p), period_us = dv.getUint32(p + 8, true), ns = dv.getUint32(p + 12, true);
      const nt = dv.getUint16(p + 16, true), nc = dv.getUint8(p + 18);
      const [taxels, q] = taxelIds(dv, p + 20, nt);
      const data = new Float32Array(buf.slice(q, q + 4 * ns * nt * nc));  // [sample][taxel][channel]
      return { header: h, type: "channels", t0_us, period_us, n_samples: ns, n_channels: nc, taxels, data };
    }
    if (h.kind === KIND.DECODED) {
      const decoder = dv.getUint16(p, true), nt = dv.getUint16(p + 2, true), nv = dv.getUint16(p + 4, true);
      const ns = dv.getUint16(p + 6, true);
      const [taxels, q] = taxelIds(dv, p + 8, nt);
      const t_us = new Array(ns);
      for (let s = 0; s < ns; s++) t_us[s] = u64(dv, q + 8 * s);
      const values = new Float32Array(buf.slice(q + 8 * ns, q + 8 * ns + 4 * ns * nt * nv));  // [step][taxel][value]
      return { header: h, type: "decoded", decoder, taxels, n_values: nv, t_us, values };
    }
    throw new Error(`unknown frame kind ${h.kind}`);
  }

  return { CLASSES, KIND, FLAGS, decode };
})();
