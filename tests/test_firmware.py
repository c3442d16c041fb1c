"""The firmware core (firmware/core) compiled with the host's gcc: frames the host accepts, spikes
equal to the recording's, stalls that show up as sequence gaps and never as corruption.

The core is driven two ways: as a shared library through ctypes (CRCs, clock, ring, argument
checks) and as the stdin/stdout harness firmware/host/tr_host.c fed with a recording's samples.
"""

from __future__ import annotations

import asyncio
import binascii
import ctypes
import json
import shutil
import struct
import subprocess
import sys
import threading
import zlib
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from helpers import synthetic_trial
from server_harness import collect, connect, hello_and_subscribe, running_server, wait_until
from touchreal_client import protocol as P

from touchreal.params import default_params
from touchreal.recording import Dataset, Trial, write_dataset
from touchreal.device.mcu_emulator import PtyPort, frame_schedule, play
from touchreal.device.serial_frame import PERIOD_US, Channel, Frame, FrameParser, Gap, encode_frame
from touchreal.device.serial_source import SampleCollector
from touchreal.server.settings import RuntimeConfig
from touchreal.settings import CLASSES
from touchreal.stream import encode_chunks, encode_trial

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", f"-I{FIRMWARE / 'core'}"]
CORE = [str(FIRMWARE / "core" / "tr_fw.c")]


def _gcc() -> str:
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no host C compiler (gcc): the firmware core cannot be built")
    return cc


@pytest.fixture(scope="module")
def host(tmp_path_factory) -> Path:
    """The harness program, built with -Werror and the address and undefined-behaviour sanitizers
    (any out-of-bounds access or overflow aborts the run, so the test fails)."""
    out = tmp_path_factory.mktemp("fw") / "tr_host"
    sanitize = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    subprocess.run([_gcc(), *CFLAGS, *sanitize, "-o", str(out), str(FIRMWARE / "host" / "tr_host.c"), *CORE], check=True)
    return out


@pytest.fixture(scope="module")
def lib(tmp_path_factory) -> ctypes.CDLL:
    """The core as a shared library."""
    out = tmp_path_factory.mktemp("fw") / "libtr_fw.so"
    subprocess.run([_gcc(), *CFLAGS, "-shared", "-fPIC", "-o", str(out), *CORE], check=True)
    core = ctypes.CDLL(str(out))
    core.tr_crc16.restype = ctypes.c_uint16
    core.tr_crc32.restype = ctypes.c_uint32
    core.tr_nan.restype = ctypes.c_float
    core.tr_clock_now.restype = ctypes.c_uint64
    core.tr_clock_now.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    core.tr_clock_init.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    core.tr_pvdf_block_for.restype = ctypes.c_uint16
    core.tr_ring_init.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32]
    core.tr_device_init.argtypes = [ctypes.c_void_p, ctypes.c_uint16, ctypes.c_uint16, ctypes.c_uint16,
                                    ctypes.c_void_p, ENTROPY, ctypes.c_void_p]
    return core


ENTROPY = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p)


# ---- driving the harness ------------------------------------------------------------------------


@dataclass
class Sample:
    t_us: int
    channel: Channel
    values: np.ndarray  # float32 (n_taxels,)


def samples_of(trial: Trial, n_taxels: int = 1) -> list[Sample]:
    """The trial's samples as the device takes them: in time order, every taxel carrying the recording."""
    out = []
    for ch, t_s, x in ((Channel.SINGLETACT, trial.st_t, trial.st), (Channel.PVDF, trial.pvdf_t, trial.pvdf)):
        t_us = np.rint(np.asarray(t_s) * 1e6).astype(np.int64)
        out += [Sample(int(t), ch, np.full(n_taxels, v, np.float32)) for t, v in zip(t_us, np.asarray(x, np.float32))]
    return sorted(out, key=lambda s: (s.t_us, s.channel))


def run_host(host: Path, samples: list[Sample], n_taxels: int = 1, ring: int = 1 << 16, reads=lambda s: b"D",
             st_block: int = 1, pvdf_block: int = 10, seed: int = 1) -> tuple[bytes, dict]:
    """Feed ``samples`` to the harness; after each one, ``reads(sample)`` says what the host reads."""
    cmds = bytearray()
    for s in samples:
        cmds += b"P" + struct.pack("<BQ", s.channel, s.t_us) + s.values.astype("<f4").tobytes() + reads(s)
    args = [str(host), str(n_taxels), str(st_block), str(pvdf_block), str(ring), str(seed)]
    proc = subprocess.run(args, input=bytes(cmds), capture_output=True, check=True)
    return proc.stdout, json.loads(proc.stderr)


def read_up_to(n: int) -> bytes:
    return b"R" + struct.pack("<I", n)


def parse(data: bytes) -> tuple[FrameParser, list]:
    parser = FrameParser()
    return parser, parser.feed(data)


def frames_of(events) -> list[Frame]:
    return [e for e in events if isinstance(e, Frame)]


def per_channel(frames: list[Frame]) -> dict[Channel, list[tuple]]:
    """(seq, t0_us, sample bytes) of each channel's frames, in order."""
    return {c: [(f.seq, f.t0_us, f.samples.tobytes()) for f in frames if f.channel is c] for c in Channel}


# ---- the recording ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recording(request, tmp_path_factory) -> tuple[Path, Trial]:
    """A one-trial dataset folder: the first rig-v1 ramp when ../shared is there, else `touchreal simulate`."""
    root = tmp_path_factory.mktemp("dataset")
    try:
        rig = request.getfixturevalue("rig")
    except pytest.skip.Exception:
        cmd = [sys.executable, "-m", "touchreal", "simulate", "ramp", "--out", str(root), "--trials", "1",
               "--no-reference", "--quiet"]
        subprocess.run(cmd, check=True)
    else:
        entry = dict(rig.entries("ramp")[0])
        manifest = {k: v for k, v in rig.manifest.items() if k != "trials"} | {"trials": [entry]}
        write_dataset(root, manifest, {entry["id"]: rig.load(entry)})
    ds = Dataset.open(root)
    assert len(ds.trials) == 1
    return root, ds.load(ds.trials[0])


# ---- core pieces through ctypes -----------------------------------------------------------------


def test_crcs_give_the_protocol_check_values_and_agree_with_python(lib):
    assert lib.tr_crc16(b"123456789", 9) == 0x29B1
    assert lib.tr_crc32(b"123456789", 9) == 0xCBF43926
    data = np.random.default_rng(0).integers(0, 256, 4122, dtype=np.uint8).tobytes()
    assert lib.tr_crc16(data, len(data)) == binascii.crc_hqx(data, 0xFFFF)
    assert lib.tr_crc32(data, len(data)) == zlib.crc32(data)
    assert np.isnan(lib.tr_nan())


def test_device_clock_is_monotonic_64_bit_across_counter_wraps(lib):
    clk = ctypes.create_string_buffer(16)
    lib.tr_clock_init(clk, 0xFFFF_FF00)
    assert lib.tr_clock_now(clk, 0xFFFF_FF00) == 0
    assert lib.tr_clock_now(clk, 0x100) == 0x200  # the 32-bit counter wrapped
    t, raw = 0x200, 0x100
    for _ in range(5):  # five more wraps in steps of 2^31 us
        raw = (raw + (1 << 31)) & 0xFFFF_FFFF
        now = lib.tr_clock_now(clk, raw)
        assert now == t + (1 << 31)
        t = now
    assert t > 1 << 32


def test_pvdf_block_shrinks_to_fit_the_frame_bound(lib):
    assert [lib.tr_pvdf_block_for(n) for n in (0, 1, 16, 102, 103, 256, 257)] == [0, 10, 10, 10, 9, 4, 0]


def test_device_init_rejects_bad_sizes_and_draws_the_session_from_the_entropy(lib):
    dev = ctypes.create_string_buffer(16384)
    store = ctypes.create_string_buffer(1 << 13)
    ring = ctypes.create_string_buffer(64)
    assert lib.tr_ring_init(ring, store, 1000) == -1  # not a power of two
    assert lib.tr_ring_init(ring, store, 1 << 13) == 0

    def session(seed: int) -> int:
        state = ctypes.c_uint32(seed)

        @ENTROPY
        def entropy(ctx):
            state.value = state.value * 1664525 + 1013904223
            return state.value

        assert lib.tr_device_init(dev, 1, 1, 10, ring, entropy, None) == 0
        return struct.unpack_from("<H", dev.raw, 2)[0]  # tr_device_t: u16 n_taxels, u16 session

    sessions = [session(s) for s in range(64)]
    assert session(7) == sessions[7] and len(set(sessions)) >= 60
    noise = ENTROPY(lambda ctx: 0)
    for n_taxels, st_block, pvdf_block in [(0, 1, 10), (257, 1, 1), (103, 1, 10), (1, 0, 10), (1, 1, 0)]:
        assert lib.tr_device_init(dev, n_taxels, st_block, pvdf_block, ring, noise, None) == -1
    small = ctypes.create_string_buffer(64)
    assert lib.tr_ring_init(small, store, 256) == 0
    assert lib.tr_device_init(dev, 8, 1, 10, small, noise, None) == -1  # a PVDF frame would never fit


# ---- the recording through the harness ----------------------------------------------------------


def test_recording_through_the_firmware_is_the_emulator_bit_for_bit_and_encodes_to_its_spikes(host, recording, tmp_path):
    root, trial = recording
    data, stats = run_host(host, samples_of(trial))
    parser, events = parse(data)
    assert parser.stats.crc_errors == parser.stats.bad_headers == parser.stats.bytes_discarded == parser.stats.gaps == 0
    got = frames_of(events)
    assert {f.session for f in got} == {stats["session"]}
    emulated = frames_of(FrameParser().feed(b"".join(d for _, d in frame_schedule([trial]))))
    assert per_channel(got) == per_channel(emulated)
    session = stats["session"]  # the stream is the emulator's, byte for byte, once it carries this session
    assert data == b"".join(encode_frame(f.channel, f.seq, session, f.t0_us, f.samples) for f in emulated)
    assert stats["singletact"]["frames_sent"] == trial.st.size and stats["pvdf"]["frames_sent"] == -(-trial.pvdf.size // 10)
    # the host's own collector, then the encoder: exactly what `touchreal encode --clock sensor` writes
    collector = SampleCollector(n_taxels=1)
    collector.add(events, now_s=0.0)
    chunk = collector.take()
    assert np.array_equal(chunk.st[:, 0], trial.st) and np.array_equal(chunk.pvdf[:, 0], trial.pvdf)
    spikes = encode_chunks(default_params(), [chunk])
    out = tmp_path / "encoded"
    subprocess.run([sys.executable, "-m", "touchreal", "encode", str(root), "--clock", "sensor", "--out", str(out)],
                   check=True, capture_output=True)
    (ref_file,) = out.glob("*.json")
    reference = json.loads(ref_file.read_text())
    assert sum(len(v) for v in reference.values()) > 0
    for cls, times in reference.items():
        assert [round(float(t), 6) for t in spikes.train(cls, 0)] == times, cls


def test_failed_readings_travel_as_nan_and_timing_breaks_close_frames_like_the_emulator(host):
    trial = synthetic_trial(duration_s=0.6, seed=3)
    trial.st[[5, 6]] = np.nan
    trial.pvdf[100:104] = np.nan
    keep = np.ones(trial.pvdf.size, bool)
    keep[[203, 204, 205, 517]] = False  # samples the ADC missed: frames must not span the holes
    trial = Trial(st_t=trial.st_t, st=trial.st, pvdf_t=trial.pvdf_t[keep], pvdf=trial.pvdf[keep], cmd_depth=trial.cmd_depth)
    data, stats = run_host(host, samples_of(trial, n_taxels=3), n_taxels=3)
    parser, events = parse(data)
    assert parser.stats.crc_errors == parser.stats.gaps == 0
    got = frames_of(events)
    emulated = frames_of(FrameParser().feed(b"".join(d for _, d in frame_schedule([trial], n_taxels=3))))
    assert per_channel(got) == per_channel(emulated)
    assert stats["pvdf"]["breaks"] == 2
    pv = [f for f in got if f.channel is Channel.PVDF]
    times = np.concatenate([f.times_us for f in pv])
    assert np.array_equal(times, np.rint(trial.pvdf_t * 1e6).astype(np.int64))  # every sample at its true time
    values = np.concatenate([f.samples for f in pv])
    assert values.shape == (trial.pvdf.size, 3) and np.isnan(values[100:104]).all() and np.isfinite(values[104:]).all()
    assert np.isnan(np.concatenate([f.samples for f in got if f.channel is Channel.SINGLETACT])[[5, 6]]).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_host_stalls_show_up_as_gaps_never_as_corruption(host, seed):
    """The host reads random amounts (frames cross reads) and stops reading for whole stretches."""
    trial = synthetic_trial(duration_s=2.0, seed=seed)
    samples = samples_of(trial, n_taxels=2)
    rng = np.random.default_rng(seed)
    stalls = rng.uniform(0, 2e6, 6).astype(int)
    sizes = iter(rng.integers(1, 300, len(samples)))

    def reads(s: Sample) -> bytes:  # nothing for 60 ms after each stall start, else up to 300 bytes
        return b"" if any(a <= s.t_us < a + 60_000 for a in stalls) else read_up_to(int(next(sizes)))

    data, stats = run_host(host, samples, n_taxels=2, ring=1024, reads=reads)
    parser, events = parse(data)
    assert parser.stats.crc_errors == parser.stats.bad_headers == parser.stats.bytes_discarded == 0
    dropped = {c: stats[n]["frames_dropped"] for c, n in ((Channel.SINGLETACT, "singletact"), (Channel.PVDF, "pvdf"))}
    assert dropped[Channel.PVDF] > 0  # the stalls overflowed the ring
    missed = {c: sum(e.missing for e in events if isinstance(e, Gap) and e.channel is c) for c in Channel}
    assert missed == dropped
    # every frame that arrived carries exactly the recording at its own times
    t_rec = {Channel.SINGLETACT: np.rint(trial.st_t * 1e6).astype(np.int64),
             Channel.PVDF: np.rint(trial.pvdf_t * 1e6).astype(np.int64)}
    x_rec = {Channel.SINGLETACT: trial.st, Channel.PVDF: trial.pvdf}
    got = frames_of(events)
    for f in got:
        idx = np.searchsorted(t_rec[f.channel], f.times_us)
        assert np.array_equal(t_rec[f.channel][idx], f.times_us)
        assert np.array_equal(f.samples, np.repeat(x_rec[f.channel][idx, None], 2, axis=1))
    for c in Channel:
        n_frames = sum(f.channel is c for f in got)
        assert n_frames == stats["singletact" if c is Channel.SINGLETACT else "pvdf"]["frames_sent"]
        assert [f.seq for f in got if f.channel is c][-1] == n_frames + dropped[c] - 1


def test_a_sample_not_later_than_the_previous_one_is_refused_and_counted(host):
    times = [1000, 1500, 2000, 1900, 2000, 2500, 3000]  # 1900 and the repeated 2000 run backwards
    samples = [Sample(t, Channel.PVDF, np.array([t / 1000], np.float32)) for t in times]
    data, stats = run_host(host, samples, pvdf_block=4)
    assert stats["pvdf"]["rejected"] == 2 and stats["pvdf"]["samples"] == 5
    got = frames_of(parse(data)[1])
    assert [list(f.times_us) for f in got] == [[1000, 1500, 2000, 2500], [3000]]
    assert np.array_equal(np.concatenate([f.samples[:, 0] for f in got]), np.array([1, 1.5, 2, 2.5, 3], np.float32))


def test_sequence_numbers_wrap_without_a_gap(host):
    n = 65536 + 4
    samples = [Sample(10_000 * k, Channel.SINGLETACT, np.array([k % 7], np.float32)) for k in range(n)]
    data, stats = run_host(host, samples)
    assert stats["singletact"]["frames_sent"] == n and len(data) == 30 * n
    parser, events = parse(data[-30 * 6 :])
    assert [f.seq for f in frames_of(events)] == [65534, 65535, 0, 1, 2, 3]
    assert [f.t0_us for f in frames_of(events)] == [10_000 * k for k in range(n - 6, n)]
    assert parser.stats.gaps == 0 and PERIOD_US[Channel.SINGLETACT] == 10_000


def test_firmware_bytes_through_a_pty_into_touchreal_serve_give_the_recording_spikes(host, recording, tmp_path):
    """The harness's bytes played in real time (x4) through a pty into a real `touchreal serve --source serial:`."""
    _, trial = recording
    data, _ = run_host(host, samples_of(trial))
    schedule, offset = [], 0
    for f in frames_of(FrameParser().feed(data)):  # each frame goes out when its last sample is taken
        size = 22 + 4 * f.samples.size + 4
        schedule.append((int(f.times_us[-1]), data[offset : offset + size]))
        offset += size
    assert offset == len(data)
    path = tmp_path / "ttyTR0"
    port = PtyPort(path)
    port.plug()
    player = threading.Thread(target=play, args=(schedule, port), kwargs={"speed": 4.0, "linger_s": 1.0}, daemon=True)
    end_us = schedule[-1][0]
    try:
        with running_server(tmp_path / "state", RuntimeConfig(source=f"serial:{path}")) as (addr, _svc):
            wait_until(lambda: port.host_attached() and httpx.get(f"http://{addr}/v1/status").json()["source"]["connects"],
                       20, "the service opened the port")

            def settled(frames) -> bool:
                finals = [f.final_us for f in frames if isinstance(f, P.SpikesFrame)]
                return bool(finals) and all(v is not None and v >= end_us - 400_000 for v in finals[-1].values())

            async def go():
                async with connect(addr) as ws:
                    await hello_and_subscribe(ws, streams=["spikes"])
                    player.start()
                    return await collect(ws, 30.0, settled, what="the service got through the recording")

            frames = asyncio.run(asyncio.wait_for(go(), 40))
            status = httpx.get(f"http://{addr}/v1/status").json()
    finally:
        player.join(10)
        port.close()
    spikes = [f for f in frames if isinstance(f, P.SpikesFrame)]
    assert settled(spikes), "the service did not get through the recording in time"
    assert status["faults"]["source_crc_errors"] == status["faults"]["source_gaps"] == 0
    want = encode_trial(trial, default_params())
    t_us = np.concatenate([f.t_us for f in spikes]).astype(np.int64)
    cls = np.concatenate([f.cls for f in spikes])
    final = spikes[-1].final_us
    assert sum(v.size for v in want.values()) > 0
    for i, name in enumerate(CLASSES):
        expected = np.rint(want[name] * 1e6).astype(np.int64)
        expected = expected[expected < final[name]]
        np.testing.assert_allclose(np.sort(t_us[cls == i]), expected, rtol=0, atol=1)
