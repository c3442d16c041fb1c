"""SerialSource through a real pty driven by the MCU emulator: exact samples, faults, unplug, spikes."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from helpers import synthetic_trial
from waiting import wait_until

from touchreal.encoding.encoder import SpikeEvents
from touchreal.params import default_params
from touchreal.recording import Trial, write_dataset
from touchreal.device.mcu_emulator import STALL_JITTERS, Faults, Link, PtyPort, departures, frame_schedule, play
from touchreal.raw import RawChunk
from touchreal.device.serial_frame import Channel, Frame, FrameParser, encode_frame
from touchreal.device.serial_source import SampleCollector, SerialSource
from touchreal.stream import StreamEncoder, encode_trial

SPEED = 6.0  # playback speed: a 1.5 s trial streams in 0.25 s


@contextmanager
def reading(path: Path, n_taxels: int = 1) -> Iterator[tuple[PtyPort, SerialSource]]:
    """A plugged emulated port and a SerialSource that has opened it (and flushed its input)."""
    port = PtyPort(path)
    port.plug()
    src = SerialSource(str(path), n_taxels=n_taxels, update_s=0.02)
    try:
        wait_until(lambda: src.status()["connects"] > 0, 5, "the source opened the port", interval=0.005)
        yield port, src
    finally:
        src.close()
        port.close()


@contextmanager
def emulated(port: PtyPort, trials: list[Trial], n_taxels: int = 1, speed: float = SPEED) -> Iterator[threading.Thread]:
    """The emulator in a thread, writing ``trials`` to the real pty of ``port``."""
    stop = threading.Event()
    schedule = frame_schedule(trials, n_taxels=n_taxels)
    kw = dict(speed=speed, linger_s=0.3, should_stop=stop.is_set)
    thread = threading.Thread(target=play, args=(schedule, port), kwargs=kw, daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        stop.set()
        thread.join(5)


def drain(
    src: SerialSource, done: Callable[[], bool], on_chunk: Callable[[RawChunk], None] = lambda c: None, timeout_s: float = 15.0
) -> tuple[RawChunk, list[str]]:
    """Every chunk until ``done()`` (plus one more), and the states seen along the way."""
    chunks, states = [], []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        finished = done()
        chunk = src.next_chunk()
        assert chunk is not None
        on_chunk(chunk)
        chunks.append(chunk)
        if not states or states[-1] != src.status()["state"]:
            states.append(src.status()["state"])
        if finished:
            break
    else:
        pytest.fail("the stream did not end in time")
    return RawChunk.concat(chunks), states


def assert_spikes_equal(events, trial: Trial, n_taxels: int) -> None:
    want = encode_trial(trial, default_params())
    assert sum(v.size for v in want.values()) > 0
    for cls in want:
        for taxel in range(n_taxels):
            got = events.train(cls, taxel)
            assert got.size == want[cls].size, (cls, taxel)
            np.testing.assert_allclose(got, want[cls], rtol=0, atol=1e-6)


def stream_encoded(path: Path, trial: Trial, n_taxels: int) -> tuple[RawChunk, StreamEncoder, list, dict]:
    """Play ``trial`` through a pty into a SerialSource and a live StreamEncoder."""
    se = StreamEncoder(default_params(), n_taxels)
    parts = []
    with reading(path, n_taxels) as (port, src), emulated(port, [trial], n_taxels) as emu:
        got, states = drain(src, lambda: not emu.is_alive(), lambda c: parts.append(se.process(c)))
        status = src.status()
    parts.append(se.finish())
    assert "streaming" in states
    return got, se, parts, status


def test_samples_and_spikes_through_a_pty_equal_the_recording(tmp_path):
    trial = synthetic_trial(duration_s=1.5)
    got, se, parts, status = stream_encoded(tmp_path / "ttyTR0", trial, n_taxels=2)
    np.testing.assert_allclose(got.st_t, trial.st_t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.pvdf_t, trial.pvdf_t, rtol=0, atol=1e-9)
    for taxel in range(2):
        assert np.array_equal(got.st[:, taxel], trial.st) and np.array_equal(got.pvdf[:, taxel], trial.pvdf)
    assert status["frames"] == trial.st.size + trial.pvdf.size // 10
    assert status["crc_errors"] == status["gaps"] == status["bytes_discarded"] == status["reconnects"] == 0
    assert 0 <= status["seconds_since_frame"] < 2
    assert_spikes_equal(SpikeEvents.concatenate(parts), trial, n_taxels=2)


def test_missing_port_never_raises_and_close_ends_the_stream(tmp_path):
    src = SerialSource(str(tmp_path / "absent"), update_s=0.01)
    chunk = src.next_chunk()  # no port: an empty chunk, no exception
    assert chunk is not None and chunk.st_t.size == chunk.pvdf_t.size == 0
    status = src.status()
    assert status["state"] in ("connecting", "disconnected") and status["connects"] == 0
    wait_until(lambda: "could not open port" in src.status()["last_error"], 5, "the open failed", interval=0.005)
    assert src.clock() is None and src.status()["clock_error_us"] == -1
    src.close()
    assert src.next_chunk() is None and src.status()["state"] == "closed"


@pytest.mark.shared
def test_rig_trial_through_a_pty_gives_the_recorded_samples_and_spikes(tmp_path, rig):
    trial = rig.load(rig.entries("ramp")[0])
    got, se, parts, status = stream_encoded(tmp_path / "ttyTR0", trial, n_taxels=1)
    np.testing.assert_allclose(got.st_t, trial.st_t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.pvdf_t, trial.pvdf_t, rtol=0, atol=1e-6)
    assert np.array_equal(got.st[:, 0], trial.st) and np.array_equal(got.pvdf[:, 0], trial.pvdf)
    assert status["crc_errors"] == status["gaps"] == 0
    assert_spikes_equal(SpikeEvents.concatenate(parts), trial, n_taxels=1)


def test_non_finite_samples_pass_through_and_the_encoder_stays_finite(tmp_path):
    trial = synthetic_trial(duration_s=1.2, seed=4)
    trial.st[[40, 41, 60]] = [np.nan, np.inf, np.nan]
    trial.pvdf[1000:1010] = np.nan
    trial.pvdf[[1500, 1501]] = [np.inf, -np.inf]
    got, se, parts, status = stream_encoded(tmp_path / "ttyTR0", trial, n_taxels=1)
    assert np.array_equal(got.st[:, 0], trial.st, equal_nan=True)
    assert np.array_equal(got.pvdf[:, 0], trial.pvdf, equal_nan=True)
    assert se.stats["singletact"]["non_finite"] == 3 and se.stats["pvdf"]["non_finite"] == 12
    finite, peak, _ = se.state_report()
    assert finite and np.isfinite(peak)
    events = SpikeEvents.concatenate(parts)
    assert len(events) > 0 and np.all(np.isfinite(events.t_s))


def test_a_step_of_the_wall_clock_moves_the_mapping_in_a_new_epoch(tmp_path):
    step_ns = 0
    port = PtyPort(tmp_path / "ttyTR0")
    port.plug()
    src = SerialSource(str(port.path), update_s=0.02, wall_ns=lambda: time.time_ns() + step_ns)
    try:
        wait_until(lambda: src.status()["connects"] > 0, 5, "the source opened the port", interval=0.005)
        with emulated(port, [synthetic_trial(duration_s=1.0)], speed=1.0):
            wait_until(lambda: src.clock() is not None, 5, "a clock point", interval=0.005)
            before = src.clock()
            step_ns = 5_000_000_000  # the wall clock is stepped 5 s ahead (NTP at boot)
            after, again = src.clock(), src.clock()
    finally:
        src.close()
        port.close()
    assert after.epoch == again.epoch == before.epoch + 1
    moved = after.wall_us - before.wall_us - (after.sensor_us - before.sensor_us) * after.rate
    assert abs(moved - 5_000_000) <= before.error_us + after.error_us


def test_a_second_reader_of_the_same_port_is_refused_and_says_why(tmp_path):
    with reading(tmp_path / "ttyTR0") as (port, first):
        second = SerialSource(str(port.path), update_s=0.01)
        wait_until(lambda: "lock" in second.status()["last_error"], 5, "the second source refused by the lock",
                   interval=0.005)
        status = second.status()
        second.close()
    assert first.status()["connects"] == 1 and not port.host_attached()
    assert status["connects"] == 0 and status["state"] == "disconnected" and "lock" in status["last_error"]


def test_frames_with_another_taxel_count_are_rejected_and_counted(tmp_path):
    with reading(tmp_path / "ttyTR0", n_taxels=1) as (port, src):
        with emulated(port, [synthetic_trial(duration_s=0.5)], n_taxels=3) as emu:
            got, _ = drain(src, lambda: not emu.is_alive())
        status = src.status()
    assert got.st_t.size == got.pvdf_t.size == 0
    assert status["frames"] == status["wrong_taxels"] == 50 + 100


def test_device_restart_rebases_the_clock_so_time_keeps_increasing():
    parser, coll = FrameParser(), SampleCollector(n_taxels=2)
    x = np.ones((10, 2), np.float32)
    coll.add(parser.feed(encode_frame(Channel.PVDF, 0, 1, 5_000_000, x)), now_s=100.0)
    coll.add(parser.feed(encode_frame(Channel.PVDF, 0, 2, 0, x)), now_s=100.75)  # rebooted 0.75 s later
    coll.add(parser.feed(encode_frame(Channel.PVDF, 1, 2, 5000, x)), now_s=100.76)
    coll.add(parser.feed(encode_frame(Channel.PVDF, 2, 2, 10_000, np.ones((10, 3), np.float32))), now_s=100.77)
    chunk = coll.take()
    assert np.all(np.diff(chunk.pvdf_t) > 0) and chunk.pvdf.shape == (30, 2)
    assert chunk.pvdf_t[10] == pytest.approx(5.0045 + 0.75) and chunk.pvdf_t[20] == pytest.approx(5.7545 + 0.005)
    assert parser.stats.restarts == 1 and parser.stats.gaps == 0 and coll.wrong_taxels == 1
    assert coll.take().pvdf_t.size == 0
    assert coll.device_clock.epoch == 1 and coll.last_us == round(chunk.pvdf_t[-1] * 1e6)  # a new device clock, a new epoch
    est = coll.device_clock.estimate(coll.last_us)
    assert est is not None and est.epoch == 1 and est.host_us == 100_755_000  # provisional: rate 1 through the fastest frame


def test_frames_stamped_beyond_the_sensor_clock_are_dropped_and_counted():
    parser, coll = FrameParser(), SampleCollector(n_taxels=1)
    x = np.ones((2, 1), np.float32)
    for seq, t0 in enumerate([1_000, 2**63 + 5, 2**64 - 1, (1 << 62) - 500, 3_000]):  # a device clock gone wild
        coll.add(parser.feed(encode_frame(Channel.PVDF, seq, 1, t0, x)), now_s=1.0 + seq / 1000)
    chunk = coll.take()
    assert coll.bad_times == 3 and chunk.pvdf_t.tolist() == [0.001, 0.0015, 0.003, 0.0035]
    assert coll.last_us == 3_500 and coll.device_clock.estimate(coll.last_us) is not None


def test_samples_nobody_takes_are_bounded_and_counted():
    parser, coll = FrameParser(), SampleCollector(n_taxels=1)
    data = b"".join(encode_frame(Channel.SINGLETACT, k, 1, 10_000 * k, [[float(k)]]) for k in range(1500))
    coll.add(parser.feed(data), now_s=0.0)  # 15 s of SingleTact, never taken
    chunk = coll.take()
    assert coll.overflowed == 500 and chunk.st.shape == (1000, 1) and chunk.st[0, 0] == 500.0
    with pytest.raises(ValueError, match="n_taxels"):
        SerialSource("loop://", n_taxels=0)


def test_schedule_plays_trials_back_to_back_on_one_device_clock_with_seeded_faults():
    a, b = synthetic_trial(duration_s=0.6, seed=1), synthetic_trial(duration_s=0.4, seed=2)
    sched = list(frame_schedule([a, b], pvdf_block=10))
    assert all(s1 <= s2 for (s1, _), (s2, _) in zip(sched, sched[1:]))  # in send order
    parser = FrameParser()
    events = parser.feed(b"".join(d for _, d in sched))
    st_frames = [e for e in events if isinstance(e, Frame) and e.channel is Channel.SINGLETACT]
    t_us = np.concatenate([f.times_us for f in st_frames])
    offset = t_us[a.st.size] - round(b.st_t[0] * 1e6)
    assert offset % 10_000 == 0 and offset > a.duration_s * 1e6  # phase kept, after trial a
    assert np.array_equal(t_us[: a.st.size], np.rint(a.st_t * 1e6)) and np.all(np.diff(t_us) > 0)
    assert np.array_equal(np.concatenate([f.samples[:, 0] for f in st_frames]), np.concatenate([a.st, b.st]))
    assert parser.stats.frames == len(sched) == a.st.size + b.st.size + (a.pvdf.size + b.pvdf.size) // 10
    assert parser.stats.gaps == 0
    faulty = list(frame_schedule([a, b], faults=Faults(drop_rate=0.1, corrupt_rate=0.1, seed=7)))
    assert faulty == list(frame_schedule([a, b], faults=Faults(drop_rate=0.1, corrupt_rate=0.1, seed=7)))
    hurt = FrameParser()
    hurt.feed(b"".join(d for _, d in faulty))
    assert hurt.stats.frames < len(faulty) < len(sched) and hurt.stats.crc_errors > 0
    assert hurt.stats.frames + hurt.stats.frames_missed == len(sched)  # every loss is counted
    with pytest.raises(ValueError, match="drop_rate"):
        Faults(drop_rate=1.5)


def test_emulator_command_reports_bad_arguments_clearly(tmp_path, capsys):
    from touchreal.cli import main

    root = tmp_path / "data"
    entry = {"id": "syn", "protocol": "ramp", "condition": "press", "repeat": 0, "params": {}, "onset_s": 0.3, "stim_end_s": 1.0}
    write_dataset(root, {"trials": [entry]}, {"syn": synthetic_trial(duration_s=0.3)})
    (tmp_path / "file").write_text("keep me")
    assert main(["mcu-emulate", str(root), "--port", str(tmp_path / "p"), "--trial", "nope"]) == 2
    assert "no trial 'nope'" in capsys.readouterr().err
    assert main(["mcu-emulate", str(root), "--port", str(tmp_path / "file")]) == 2
    assert "not a symlink" in capsys.readouterr().err and (tmp_path / "file").read_text() == "keep me"
    assert main(["mcu-emulate", str(root), "--port", str(tmp_path / "p"), "--taxels", "200"]) == 2
    assert "values per frame" in capsys.readouterr().err and not (tmp_path / "p").exists()
    assert main(["mcu-emulate", str(tmp_path), "--port", str(tmp_path / "p")]) == 2
    assert "no manifest.json" in capsys.readouterr().err
    assert main(["mcu-emulate", str(root), "--port", str(tmp_path / "p"), "--clock-drift-ppm", "1e6"]) == 2
    assert "drift_ppm must be in" in capsys.readouterr().err and not (tmp_path / "p").exists()
    assert main(["mcu-emulate", str(root), "--port", str(tmp_path / "p"), "--jitter-ms", "nan"]) == 2
    assert "jitter_ms must be in" in capsys.readouterr().err


@pytest.mark.slow
def test_emulator_command_with_faults_and_unplug_the_stream_goes_on(tmp_path):
    """The real ``touchreal mcu-emulate`` process: corrupted bytes, dropped frames, two unplugs."""
    trial = synthetic_trial(duration_s=3.0, seed=5)
    root = tmp_path / "data"
    entry = {"id": "syn", "protocol": "ramp", "condition": "press", "repeat": 0, "params": {}, "onset_s": 0.3, "stim_end_s": 1.0}
    write_dataset(root, {"trials": [entry]}, {"syn": trial})
    path = tmp_path / "ttyTR0"
    cmd = [sys.executable, "-m", "touchreal", "mcu-emulate", str(root), "--port", str(path), "--speed", "3",
           "--corrupt-rate", "0.05", "--drop-rate", "0.03", "--unplug-after", "1.0", "--replug-after", "0.3",
           "--wait-for-host", "20", "--seed", "3"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == str(path)
        src = SerialSource(str(path), update_s=0.02)
        try:
            got, states = drain(src, lambda: proc.poll() is not None, timeout_s=30)
            status, clock = src.status(), src.clock()
        finally:
            src.close()
        device = json.loads(proc.stdout.read().strip().splitlines()[-1])
    finally:
        proc.kill() if proc.poll() is None else None
        proc.wait(5)
    assert proc.returncode == 0
    # every sample that arrived is the recorded one at that time: nothing corrupted got through
    i_st = np.rint((got.st_t - trial.st_t[0]) * 100).astype(int)
    i_pv = np.rint((got.pvdf_t - trial.pvdf_t[0]) * 2000).astype(int)
    assert np.array_equal(got.st[:, 0], trial.st[i_st]) and np.array_equal(got.pvdf[:, 0], trial.pvdf[i_pv])
    # faults were seen and counted; every frame up to the last received one is received or missed
    assert status["crc_errors"] > 0 and status["gaps"] > 0 and status["reconnects"] >= 2
    assert status["frames"] + status["frames_missed"] == (i_st[-1] + 1) + (i_pv[-1] // 10 + 1)
    assert status["frames"] == got.st_t.size + got.pvdf_t.size // 10
    assert device["plugs"] >= 3 and device["frames_unread"] > 0
    assert clock is not None and clock.epoch == status["reconnects"]  # one device clock, a new epoch per reconnect
    # the stream went on after each unplug: samples arrived in the last 0.5 s of the trial
    assert got.st_t[-1] > trial.st_t[-1] - 0.5
    assert states[0] in ("connecting", "streaming") and "disconnected" in states
    assert states.index("disconnected") < len(states) - 1 - states[::-1].index("streaming")
    assert not path.exists()


def test_link_drifts_the_device_clock_delays_frames_in_order_and_stalls():
    frames = [(5_000 * k, b"f%d" % k) for k in range(4000)]  # 20 s of 5 ms frames
    ideal = list(departures(frames, Link(drift_ppm=-250.0), speed=2.0))
    assert [(d, a) for d, a, leave, _ in ideal] == [(d, a) for d, a, a2, _ in ideal if a2 == a]  # no jitter: leave when acquired
    assert ideal[-1][1] == pytest.approx(19.995 / 2 / (1 - 250e-6), abs=1e-9)  # a slow device clock: more host time
    got = list(departures(frames, Link(drift_ppm=100.0, jitter_ms=2.0, seed=4)))
    device, acquired, leave = (np.array([g[i] for g in got]) for i in range(3))
    assert np.array_equal(device, [d for d, _ in frames]) and [g[3] for g in got] == [f for _, f in frames]
    assert np.allclose(acquired, device / 1e6 / (1 + 100e-6), rtol=0, atol=1e-12)
    delay = leave - acquired
    assert np.all(np.diff(leave) >= 0) and np.all(delay >= 0)  # in order, never before acquisition
    assert 0.0015 < np.median(delay) < 0.006  # exponential jitter, made longer by queueing behind stalls
    stalled = delay > STALL_JITTERS * 0.002 * 0.75  # held by a stall of 20 ms (a 2 ms exponential: 1 frame in 1800)
    assert 8 < np.count_nonzero(np.diff(stalled.astype(int)) == 1) < 40  # about one stall a second
    assert list(departures(frames, Link(drift_ppm=100.0, jitter_ms=2.0, seed=4))) == got  # seeded
    with pytest.raises(ValueError, match="jitter_ms"):
        Link(jitter_ms=-1.0)


@pytest.mark.slow
def test_clock_of_a_drifting_device_behind_a_jittery_link_through_a_pty(tmp_path):
    """The real ``touchreal mcu-emulate`` process, device clock 100 ppm fast, 2 ms mean jitter with
    stalls: after settling, the wall time SerialSource.clock() states for a sample is within 2 ms of
    when the emulator acquired it (its --truth file), and the estimated rate within 50 ppm."""
    trial = synthetic_trial(duration_s=5.0, seed=6)
    root = tmp_path / "data"
    entry = {"id": "syn", "protocol": "ramp", "condition": "press", "repeat": 0, "params": {}, "onset_s": 0.3, "stim_end_s": 1.0}
    write_dataset(root, {"trials": [entry]}, {"syn": trial})
    path, truth_file = tmp_path / "ttyTR0", tmp_path / "truth.csv"
    cmd = [sys.executable, "-m", "touchreal", "mcu-emulate", str(root), "--port", str(path), "--clock-drift-ppm", "100",
           "--jitter-ms", "2", "--truth", str(truth_file), "--wait-for-host", "20", "--seed", "8"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    points = []
    try:
        assert proc.stdout.readline().strip() == str(path)
        src = SerialSource(str(path), update_s=0.02)
        try:
            drain(src, lambda: proc.poll() is not None, lambda c: points.append(src.clock()), timeout_s=30)
            status = src.status()
        finally:
            src.close()
    finally:
        proc.kill() if proc.poll() is None else None
        proc.wait(5)
    assert proc.returncode == 0
    truth = np.loadtxt(truth_file, delimiter=",", skiprows=1, dtype=np.int64)
    points = [p for p in points if p is not None]
    assert points and {p.epoch for p in points} == {0}
    settled = [p for p in points if p.sensor_us >= truth[0, 0] + 3_000_000]
    assert len(settled) > 50
    sensor = np.array([p.sensor_us for p in settled])
    err = np.array([p.wall_us for p in settled]) - np.interp(sensor, truth[:, 0], truth[:, 1].astype(np.float64))
    print(f"clock error after settling: max {np.abs(err).max():.0f} us, median {np.median(np.abs(err)):.0f} us, stated <= {max(p.error_us for p in settled)} us")
    assert np.abs(err).max() <= 2000, np.abs(err).max()
    assert settled[-1].rate == pytest.approx(1 / (1 + 100e-6), abs=50e-6)  # the drift is seen (6 s, loaded host)
    assert max(p.error_us for p in settled) <= 3000
    assert status["clock_drift_ppm"] == pytest.approx(100, abs=50) and status["clock_resets"] == 0
    assert 0 < status["clock_error_us"] <= 3000
