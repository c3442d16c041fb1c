"""``touchreal record`` -> MCAP, through a real server, read back with the ``mcap`` library."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading

import httpx
import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Attachment, Chunk, Footer, Message, Metadata
from mcap.stream_reader import StreamReader, breakup_chunk
from server_harness import free_port, running_server, wait_until
from test_bridge_nats import gateway, publishing
from test_server_stream import _replay_dataset
from touchreal_client import protocol as P
from touchreal_client.clock import ClockMap
from touchreal_client.session import read_mcap

from touchreal.cli import main
from touchreal.server.settings import RuntimeConfig


def _check_spike_times(messages, clock: ClockMap, hello: dict) -> None:
    """log_time is the spike's stamp by the clock model, exactly; publish_time (receipt) follows the
    acquisition of the spike's causing sample (stamp - the class's delay) by less than 2 s."""
    body = [json.loads(m.data) for m in messages]
    t = np.array([b["t_us"] for b in body], np.int64)
    delay = np.array([hello["delay_us"][b["class"]] for b in body], np.int64)
    log = np.array([m.log_time for m in messages], np.int64)
    pub = np.array([m.publish_time for m in messages], np.int64)
    assert t.size and np.array_equal(log, np.round(clock.to_local_us(t)).astype(np.int64) * 1000)
    after_ms = (pub / 1e3 - clock.to_local_us(t - delay)) / 1e3
    assert after_ms.min() > -2 and after_ms.max() < 2000, (after_ms.min(), after_ms.max())


def _mcap_contents(path):
    """Every record read sequentially with CRC checks, then the summary through the seeking reader."""
    with path.open("rb") as fp:
        records = list(StreamReader(fp, emit_chunks=True, validate_crcs=True).records)
    with path.open("rb") as fp:
        reader = make_reader(fp, validate_crcs=True)
        summary = reader.get_summary()
        messages = list(reader.iter_messages())
    return records, summary, messages


def test_recording_a_replay_gives_touchreal_encode_spikes_in_a_valid_mcap(tmp_path):
    ds, trials = _replay_dataset(tmp_path)
    assert main(["encode", str(ds), "--out", str(tmp_path / "enc"), "--clock", "sensor"]) == 0
    out = tmp_path / "rec.mcap"
    with running_server(tmp_path / "state", RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc):
        assert main(["record", f"http://{addr}", "--out", str(out), "--seconds", "3"]) == 0
        offsets, state = [0, svc.runtime.source.offset_us], svc.runtime.state
        active = httpx.get(f"http://{addr}/v1/params").json()
    assert state == "ended" and offsets[1] > 0  # both trials were played within the recording

    # the spikes of each trial are encode --clock sensor's, to the microsecond
    rec = read_mcap(out)
    _assert_trials_are_encodes(rec, trials, offsets, tmp_path / "enc", nonempty=True)

    # a complete MCAP: CRCs, a summary with statistics, every message in an indexed chunk
    records, summary, messages = _mcap_contents(out)
    assert isinstance(records[-1], Footer) and summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == len(messages) > rec.t_us.size
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert chunks and len(summary.chunk_indexes) == len(chunks)
    in_chunks = [r for c in chunks for r in breakup_chunk(c, validate_crc=True) if isinstance(r, Message)]
    assert len(in_chunks) == len(messages)
    assert all(ci.message_index_offsets for ci in summary.chunk_indexes)
    per_channel = {}
    for _, channel, _m in messages:
        per_channel[channel.topic] = per_channel.get(channel.topic, 0) + 1
    assert summary.statistics.channel_message_counts == {cid: per_channel[ch.topic] for cid, ch in summary.channels.items()}
    topics = set(per_channel)
    assert {"/touchreal/spikes/SA1", "/touchreal/spikes/RA", "/touchreal/spikes/PC", "/touchreal/channels",
            "/touchreal/clock", "/touchreal/decoded/force"} <= topics

    # every message is valid against its channel's JSON schema (what Foxglove reads)
    for schema_id, schema in summary.schemas.items():
        assert schema.encoding == "jsonschema"
        validator = jsonschema.Draft202012Validator(json.loads(schema.data))
        for _, ch, m in messages:
            if ch.schema_id == schema_id:
                validator.validate(json.loads(m.data))

    # log_time: acquisition by the recorded clock model (server wall clock minus the recorder's offset);
    # publish_time: receipt, after it
    meta = {r.name: r.metadata for r in records if isinstance(r, Metadata)}
    clock = ClockMap()
    for p in rec.clock:
        clock.update(p)
    clock.set_offset(float(meta["touchreal.recording"]["clock_offset_us"]))
    assert rec.clock and len({p.epoch for p in rec.clock}) >= 2  # the second trial jumps the mapping
    _check_spike_times([m for _, ch, m in messages if ch.topic.startswith("/touchreal/spikes/")], clock, rec.hello)
    assert json.loads(meta["touchreal.recording.end"]["log_time_from_receipt"]) == 0

    # hello and the parameter revision the frames carry, as attachments
    att = {r.name: json.loads(r.data) for r in records if isinstance(r, Attachment)}
    assert att["hello.json"]["session"] == svc.session
    assert att["params/rev-1.json"] == {"rev": 1, "sha256": active["sha256"], "params": active["params"],
                                        "source": "GET /v1/params"}
    assert meta["touchreal.recording.end"]["stop_reason"] == "ended"  # the replay finished (its `ended` message) within the 3 s


def test_record_refuses_a_bad_subscription_before_connecting(tmp_path, capsys):
    for extra, words in ((["--streams", "spikes,raw"], "unknown streams ['raw']"), (["--streams", ","], "streams must name"),
                         (["--decimation", "0"], "decimation must be an integer in 1..5000")):
        assert main(["record", "http://127.0.0.1:9", "--out", str(tmp_path / "x.mcap"), *extra]) == 2
        assert words in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_record_of_an_unreachable_service_says_so(tmp_path, capsys):
    assert main(["record", "http://127.0.0.1:9", "--out", str(tmp_path / "x.mcap"), "--seconds", "1"]) == 2
    assert "cannot open" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_each_parameter_revision_the_frames_carry_is_attached(tmp_path):
    out = tmp_path / "rev.mcap"
    with running_server(tmp_path / "state") as (addr, svc):
        first = httpx.get(f"http://{addr}/v1/params").json()
        done: list[int] = []
        recorder = threading.Thread(target=lambda: done.append(main(
            ["record", f"http://{addr}", "--out", str(out), "--seconds", "3", "--streams", "spikes"])))
        recorder.start()
        # about a second of 5 ms hops: spikes of revision 1
        wait_until(_sent_over(svc, 200), 20, "the recorder got 200 frames")
        changed = {**first["params"], "provenance": {**first["params"]["provenance"], "note": "uploaded mid-recording"}}
        put = httpx.put(f"http://{addr}/v1/params", json=changed).json()
        recorder.join(30)
    assert done == [0] and put["rev"] == 2
    with out.open("rb") as fp:
        reader = make_reader(fp, validate_crcs=True)
        att = {a.name: json.loads(a.data) for a in reader.iter_attachments()}
        revs = {json.loads(m.data)["params_rev"] for _, ch, m in reader.iter_messages() if "/spikes/" in ch.topic}
    assert revs == {1, 2}
    assert att["params/rev-1.json"]["sha256"] == first["sha256"]
    assert att["params/rev-2.json"] == {"rev": 2, "sha256": put["sha256"], "params": changed, "source": "GET /v1/params"}


def test_recording_through_a_gateway_gives_the_same_spikes_and_the_hellos_parameter_hash(tmp_path, nats_url):
    ds, trials = _replay_dataset(tmp_path)
    assert main(["encode", str(ds), "--out", str(tmp_path / "enc"), "--clock", "sensor"]) == 0
    out = tmp_path / "gw.mcap"
    with publishing(tmp_path / "state", nats_url, RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc, _), \
            gateway(nats_url) as (ga, _gw):
        assert main(["record", f"ws://{ga}/v1/stream", "--out", str(out), "--seconds", "3", "--streams", "spikes"]) == 0
        offsets, state, sha = [0, svc.runtime.source.offset_us], svc.runtime.state, svc.view.hello()["params"]["sha256"]
    assert state == "ended"
    rec = read_mcap(out)
    _assert_trials_are_encodes(rec, trials, offsets, tmp_path / "enc")
    assert rec.params == [{"rev": 1, "sha256": sha, "params": None, "source": "hello"}]  # a gateway has no /v1/params
    assert rec.clock and rec.hello["session"] == svc.session


def _assert_trials_are_encodes(rec, trials, offsets: list[int], enc, nonempty: bool = False) -> None:
    """Each trial's recorded spikes (its wire offset off) equal ``touchreal encode --clock sensor``'s, to the us."""
    for i, name in enumerate(trials):
        lo, hi = offsets[i], (offsets[i + 1] if i + 1 < len(offsets) else np.iinfo(np.int64).max)
        written = json.loads((enc / f"{name}.json").read_text())
        for k, cls in enumerate(P.CLASSES):
            got = rec.t_us[(rec.cls == k) & (rec.t_us >= lo) & (rec.t_us < hi)] - lo
            want = np.round(np.array(written[cls]) * 1e6).astype(np.int64)
            assert (got.size or not nonempty) and np.array_equal(got, want[want >= 0]), (name, cls, got[:5], want[:5])


def _sent_over(svc, n: int):
    """A predicate: the service has sent a client (the recorder) over ``n`` frames."""
    return lambda: any(sub.sent > n for sub in list(svc.hub.subscribers.values()))


@pytest.mark.slow
def test_a_recording_continues_across_a_server_restart(tmp_path):
    """The recorder reconnects to the restarted server (a new session): both hellos are attached and
    each session's spikes are placed by its own clock model."""
    port, out, done = free_port(), tmp_path / "restart.mcap", []
    recorder = threading.Thread(target=lambda: done.append(main(
        ["record", f"http://127.0.0.1:{port}", "--out", str(out), "--seconds", "8", "--streams", "spikes"])))
    sessions = []
    with running_server(tmp_path / "s1", port=port) as (addr, svc):
        recorder.start()
        wait_until(_sent_over(svc, 200), 20, "the recorder got 200 frames")  # about a second of 5 ms hops
        sessions.append(svc.session)
    with running_server(tmp_path / "s2", port=port) as (addr, svc):
        wait_until(_sent_over(svc, 200), 20, "the recorder got 200 frames")  # about a second of 5 ms hops
        sessions.append(svc.session)
        recorder.join(30)
    assert done == [0] and sessions[0] != sessions[1]
    with out.open("rb") as fp:
        reader = make_reader(fp, validate_crcs=True)
        hellos = [a for a in reader.iter_attachments() if a.name == "hello.json"]
        messages = [(ch.topic, m) for _, ch, m in reader.iter_messages()]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert [json.loads(h.data)["session"] for h in hellos] == sessions
    assert json.loads(meta["touchreal.recording.end"]["log_time_from_receipt"]) == 0
    second = hellos[1].log_time  # its receipt: what came later belongs to the second session
    for i, part in enumerate((lambda m: m.publish_time < second, lambda m: m.publish_time >= second)):
        clock = ClockMap()
        clock.set_offset(float(meta["touchreal.recording"]["clock_offset_us"]))
        for topic, m in messages:
            if topic == "/touchreal/clock" and part(m):
                clock.update(json.loads(m.data))
        spikes = [m for topic, m in messages if "/spikes/" in topic and part(m)]
        _check_spike_times(spikes, clock, json.loads(hellos[i].data))  # each session by its own clock
    assert main(["export", "nwb", str(out), "--out", str(tmp_path / "x.nwb")]) == 2  # one timeline per NWB file
    assert not (tmp_path / "x.nwb").exists()


def test_ctrl_c_leaves_a_complete_file(tmp_path):
    out = tmp_path / "int.mcap"
    with running_server(tmp_path / "state") as (addr, svc):
        proc = subprocess.Popen([sys.executable, "-m", "touchreal", "record", f"http://{addr}", "--out", str(out),
                                 "--streams", "spikes"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            wait_until(_sent_over(svc, 10), 20, "the recorder got 10 frames")
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "interrupted" in stdout
    records, summary, messages = _mcap_contents(out)
    assert isinstance(records[-1], Footer) and summary.statistics.message_count == len(messages)
    end = {r.name: r.metadata for r in records if isinstance(r, Metadata)}["touchreal.recording.end"]
    assert end["stop_reason"].startswith("aborted: CancelledError")


def test_the_base_client_imports_no_optional_library():
    code = ("import sys, touchreal_client, touchreal_client.session; "
            "print(sorted(m for m in ('mcap', 'pynwb', 'neo', 'quantities') if m in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "[]"
