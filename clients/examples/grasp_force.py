"""Robot grasp-force loop: download the service's force decoder and run it locally on the stream.

The robot computer needs ``touchreal-client[onnx]`` only (numpy, websockets, httpx, onnxruntime).
The ONNX model comes from ``GET /v1/decoders/{name}/model.onnx``; its embedded metadata says which
classes, window, bins and step it reads, and :class:`touchreal_client.features.StreamBinner` turns
the spike events into exactly the counts the service would feed it. Every decoding step (32 ms on
the sensor clock) the estimated force drives a proportional grip controller: close while the force
is below the target, open when above, hold inside the tolerance band.

    python grasp_force.py --url http://127.0.0.1:8765 --target 1.5 --seconds 10 [--check]

Prints one CSV line per step (``t_us, taxel, force_N, command_mm_s``). ``--check`` also subscribes
to the service's own decoded output of the same model and reports the largest difference (the two
agree exactly on steps whose window lies inside the subscription).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass

import numpy as np
import onnxruntime as ort
from touchreal_client import Client, DecodedFrame, SpikesFrame, Subscription
from touchreal_client.features import META_KEY, StreamBinner


@dataclass
class GripController:
    """Proportional force control of a gripper's closing speed (sans-I/O: force in, command out)."""

    target_n: float = 1.5
    tolerance_n: float = 0.1
    gain_mm_s_per_n: float = 4.0
    max_speed_mm_s: float = 10.0

    def command(self, force_n: float) -> float:
        """Closing speed (mm/s; negative opens) for an estimated force; 0 inside the tolerance band
        or when the estimate is not a number."""
        err = self.target_n - force_n
        if not np.isfinite(err) or abs(err) <= self.tolerance_n:
            return 0.0
        return float(np.clip(self.gain_mm_s_per_n * err, -self.max_speed_mm_s, self.max_speed_mm_s))


class LocalDecoder:
    """The downloaded ONNX model with its streaming binner: spike frames in, (T, forces) out."""

    def __init__(self, onnx_bytes: bytes, taxels: list[int]):
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
        self.session = ort.InferenceSession(onnx_bytes, so, providers=["CPUExecutionProvider"])
        self.meta = json.loads(self.session.get_modelmeta().custom_metadata_map[META_KEY])
        if self.meta["task"] != "force":
            raise ValueError(f"model {self.meta['name']!r} is a {self.meta['task']} model; pick a force model")
        self.binner = StreamBinner.from_metadata(self.meta, taxels)
        self.output = self.meta["outputs"][0]

    def push(self, frame: SpikesFrame) -> list[tuple[int, np.ndarray]]:
        final = {c: v for c, v in frame.final_us.items() if v is not None}
        out = []
        for t, counts, filled in self.binner.push(frame.t_us, frame.taxel, frame.cls, final):
            force = self.session.run([self.output], {"counts": counts})[0][:, 0]
            out.append((t, np.where(filled, force, np.nan)))
        return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8765")
    ap.add_argument("--model", default="force", help="a force decoder of GET /v1/decoders")
    ap.add_argument("--taxels", default="0", help="comma list of taxels to decode")
    ap.add_argument("--target", type=float, default=1.5, help="grip force to hold (N)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--check", action="store_true", help="compare with the service's own decoded output")
    args = ap.parse_args(argv)
    taxels = [int(t) for t in args.taxels.split(",")]
    ctl = GripController(target_n=args.target)
    local_out: dict[tuple[int, int], float] = {}
    service_out: dict[tuple[int, int], float] = {}
    with Client(args.url) as tr:
        tr.wait_ready(60)
        dec = LocalDecoder(tr.download_model(args.model), taxels)
        streams = ["spikes", "decoded"] if args.check else ["spikes"]
        sub = Subscription(taxels=taxels, classes=list(dec.meta["classes"]), streams=streams, decoders=[args.model])
        print("t_us,taxel,force_N,command_mm_s")
        with tr.stream(sub) as s:
            first_final: int | None = None
            end = time.monotonic() + args.seconds
            for frame in s.frames():
                if isinstance(frame, DecodedFrame):
                    for k, t in enumerate(frame.t_us.tolist()):
                        for i, taxel in enumerate(frame.taxels.tolist()):
                            service_out[(t, taxel)] = float(frame.values[k, i, 0])
                elif isinstance(frame, SpikesFrame):
                    if first_final is None:
                        first_final = min(v for v in frame.final_us.values() if v is not None)
                    for t, forces in dec.push(frame):
                        for taxel, f in zip(taxels, forces.tolist()):
                            local_out[(t, taxel)] = f
                            print(f"{t},{taxel},{f:.4f},{ctl.command(f):.2f}")
                if time.monotonic() >= end:
                    break
    if args.check:
        window = int(round(dec.meta["window_ms"] * 1000))
        common = [k for k in local_out if k in service_out and first_final is not None and k[0] - window >= first_final
                  and np.isfinite(local_out[k])]
        diff = max((abs(local_out[k] - service_out[k]) for k in common), default=float("nan"))
        print(f"check: {len(common)} steps compared, max |local - service| = {diff:.3g} N", file=sys.stderr)
        if not common or diff > 1e-5:
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
