"""``touchreal export rosbag2``: a replay recorded by ``touchreal record`` from a real server, and a
``touchreal encode`` folder, as rosbag2 folders (MCAP storage, CDR) that rosbags reads back to the
session's spikes, channels and decoded outputs, stamped by the recorded clock model, with the metadata
``ros2 bag info`` and ``ros2 bag play`` read."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="touchreal export rosbag2 needs the ros2 extra (rosbags)")

import yaml  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402
from server_harness import running_server  # noqa: E402
from test_server_stream import _replay_dataset  # noqa: E402
from touchreal_client import protocol as P  # noqa: E402
from touchreal_client.ros2.rosbag2 import write_rosbag2  # noqa: E402
from touchreal_client.session import read_encode_dir, read_mcap  # noqa: E402

from touchreal.cli import main  # noqa: E402
from touchreal.server.settings import RuntimeConfig  # noqa: E402

MSG_DIR = Path(__file__).resolve().parents[1] / "clients/python/src/touchreal_client/ros2/touchreal_msgs/msg"
TOUCHREAL = Path(sys.executable).with_name("touchreal")  # the console script of the venv


def _export(src: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(TOUCHREAL), "export", "rosbag2", str(src), str(out)], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(recording, bag, the CLI's stdout): a replay of two trials recorded to its end (speed 8: the clock
    model's rate is 1/8 and its epoch jumps at the second trial), exported by the CLI in a subprocess."""
    tmp = tmp_path_factory.mktemp("rosbag2")
    ds, _ = _replay_dataset(tmp)
    rec, bag = tmp / "rec.mcap", tmp / "bag"
    with running_server(tmp / "state", RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc):
        # stops at the replay's `ended`; the 20 s only bound a failure
        assert main(["record", f"http://{addr}", "--out", str(rec), "--seconds", "20"]) == 0
        assert svc.runtime.state == "ended"
    run = _export(rec, bag)
    assert run.returncode == 0, run.stderr
    return rec, bag, run.stdout


def _msg_typestore():
    """A typestore of the .msg files as they are, built here (another distribution's standard types)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for f in sorted(MSG_DIR.glob("*.msg")):
        store.register(get_types_from_msg(f.read_text(), f"touchreal_msgs/msg/{f.stem}"))
    return store


def _read(bag: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time ns, message)]: the CDR bytes deserialized with :func:`_msg_typestore`."""
    store, out = _msg_typestore(), {}
    with Reader(bag) as r:
        for c, ts, raw in r.messages():
            out.setdefault(c.topic, []).append((ts, store.deserialize_cdr(raw, c.msgtype)))
    return out


def _ns(time) -> int:
    return time.sec * 1_000_000_000 + time.nanosec


def _wall_ns(session):
    """The clock model's mapping of a stamp (us) to ns, as the session states it."""
    return lambda t_us: session.wall_us_of(int(t_us)) * 1000


def _logged(session, got, wire_us) -> bool:
    """Log times are the header stamps, but no later than the wall time at which the next clock epoch
    starts (``wire_us(message)``: its header's wire stamp), and never run backwards."""
    starts = [(p.sensor_us, p.wall_us * 1000) for q, p in zip(session.clock, session.clock[1:]) if p.epoch != q.epoch]
    want = [min([_ns(m.header.stamp)] + [w for s, w in starts if s > wire_us(m)]) for _, m in got]
    logs = [log for log, _ in got]
    return logs == want and logs == sorted(logs)


def _check_spikes(session, msgs, wall_ns, hop_us: int) -> int:
    """Per class: the session's spikes exactly, cut at increasing ``final_us`` a hop apart that end at the
    coverage's end, but where the wire clock jumps to a new clock epoch; every stamp and header stamp by
    ``wall_ns``. Returns how many such jumps the messages make."""
    rev = session.params[-1]["rev"] if session.params else 0
    epochs = [p.sensor_us for q, p in zip(session.clock, session.clock[1:]) if p.epoch != q.epoch]
    jumped = 0
    for k, c in enumerate(P.CLASSES):
        mine = session.cls == k
        got = msgs[f"/touchreal/spikes/{c}"]
        assert np.array_equal(np.concatenate([m.t_us for _, m in got]), session.t_us[mine]), c
        assert np.array_equal(np.concatenate([m.taxel for _, m in got]), session.taxel[mine]), c
        finals = np.array([m.final_us for _, m in got])
        lo, hi = session.coverage_us[c]
        assert finals[-1] == hi and finals[0] - hop_us <= lo and np.all(np.diff(finals) > 0)
        over = np.flatnonzero(np.diff(finals) > hop_us)
        assert all(any(finals[i] < e <= finals[i + 1] for e in epochs) for i in over), c
        jumped += len(over)
        starts = np.concatenate([[lo], finals[:-1]])
        for (log, m), start in zip(got, starts):
            assert m.afferent_class == c and m.params_rev == rev and m.header.frame_id == "touchreal"
            assert np.all((m.t_us >= start) & (m.t_us < m.final_us))
            assert _ns(m.header.stamp) == wall_ns(m.final_us)
            assert [_ns(s) for s in m.stamps] == [wall_ns(t) for t in m.t_us]
        assert _logged(session, got, lambda m: m.final_us)
    return jumped


def test_a_recording_exports_to_a_bag_with_the_sessions_spikes_channels_and_decoded_outputs(exported):
    rec, bag, stdout = exported
    s = read_mcap(rec)
    msgs = _read(bag)
    wall_ns = _wall_ns(s)
    assert s.clock and len({p.epoch for p in s.clock}) >= 2 and s.t_us.size and s.channels is not None
    assert f"({s.t_us.size} spikes), stamped by the recorded clock model" in stdout
    # the replay's second trial starts a clock epoch, the wire clock jumping over time that never ran:
    # no empty messages there
    assert _check_spikes(s, msgs, wall_ns, s.hello["hop_us"]) == len(P.CLASSES)

    # the hello, once, first, at the bag's first time
    firsts = {topic: got[0][0] for topic, got in msgs.items()}
    [(log, desc)] = msgs["/touchreal/description"]
    assert json.loads(desc.data) == s.hello and log == min(firsts.values())

    # channels and force: blocks of evenly spaced samples, every recorded sample once
    ch, force = msgs["/touchreal/channels"], msgs["/touchreal/force"]
    assert len(ch) == len(force)
    t = np.concatenate([m.t0_us + m.period_us * np.arange(m.samples) for _, m in ch])
    assert np.array_equal(t, s.channels.t_us)
    data = np.concatenate([m.data.reshape(m.samples, len(m.taxels), 4) for _, m in ch])
    np.testing.assert_array_equal(data, s.channels.data)
    np.testing.assert_array_equal(np.concatenate([m.force_n for _, m in force]), s.channels.data[:, :, 0].reshape(-1))
    for (log, m), (flog, f) in zip(ch, force):
        assert list(m.channels) == list(P.CHANNELS) and list(m.units) == list(P.CHANNEL_UNITS)
        assert np.array_equal(m.taxels, s.channels.taxels) and (f.t0_us, f.samples) == (m.t0_us, m.samples)
        assert log == flog and _ns(m.header.stamp) == _ns(f.header.stamp) == wall_ns(m.t0_us)
    assert _logged(s, ch, lambda m: m.t0_us) and _logged(s, force, lambda m: m.t0_us)

    # decoded: one message per step of every decoder
    assert "force" in s.decoded
    for name, d in s.decoded.items():
        got = msgs[f"/touchreal/decoded/{name}"]
        assert [m.t_us for _, m in got] == d.t_us.tolist()
        for (_, m), values in zip(got, d.values):
            assert m.decoder == name and list(m.outputs) == d.outputs and np.array_equal(m.taxels, d.taxels)
            np.testing.assert_array_equal(m.values, values.reshape(-1).astype(np.float64))
            assert _ns(m.header.stamp) == wall_ns(m.t_us)
        assert _logged(s, got, lambda m: m.t_us)

    # the definitions embedded in the bag (what a reader without touchreal_msgs uses) read the same spikes
    with AnyReader([bag]) as r:
        spikes = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages() if c.topic == "/touchreal/spikes/SA1"]
    assert np.array_equal(np.concatenate([m.t_us for m in spikes]), s.t_us[s.cls == 0])


def test_the_bag_has_what_ros2_bag_info_and_play_read(exported):
    rec, bag, _ = exported
    msgs, decoders = _read(bag), read_mcap(rec).decoded
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 8 and info["storage_identifier"] == "mcap"
    [storage] = info["relative_file_paths"]
    assert (bag / storage).is_file() and storage.endswith(".mcap")
    times = [ts for got in msgs.values() for ts, _ in got]
    assert info["message_count"] == len(times) and info["starting_time"]["nanoseconds_since_epoch"] == min(times)
    assert info["duration"]["nanoseconds"] == max(times) - min(times)
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert set(topics) == set(msgs) == {"/touchreal/description", "/touchreal/channels", "/touchreal/force",
                                        *(f"/touchreal/decoded/{d}" for d in decoders),
                                        *(f"/touchreal/spikes/{c}" for c in P.CLASSES)}
    for topic, t in topics.items():
        meta = t["topic_metadata"]
        assert t["message_count"] == len(msgs[topic]) and meta["serialization_format"] == "cdr"
        assert meta["type"] == ("std_msgs/msg/String" if topic == "/touchreal/description" else
                                f"touchreal_msgs/msg/{topic.split('/')[2].capitalize()}")
        [qos] = yaml.safe_load(meta["offered_qos_profiles"])  # a YAML string up to version 8, as Humble reads it
        assert qos["reliability"] == 1 and qos["history"] == 1  # reliable, keep last
        latched = topic == "/touchreal/description"
        assert qos["durability"] == (1 if latched else 2)  # transient local : volatile

    # the MCAP storage as ros2's mcap plugin and Foxglove read it: ros2 profile, ros2msg schemas, CDR channels
    with (bag / storage).open("rb") as fp:
        reader = make_reader(fp)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    assert {s.name: s.encoding for s in summary.schemas.values()} == {
        "std_msgs/msg/String": "ros2msg", **{f"touchreal_msgs/msg/{f.stem}": "ros2msg" for f in MSG_DIR.glob("*.msg")}}
    assert {c.topic for c in summary.channels.values()} == set(msgs)
    assert all(c.message_encoding == "cdr" and "offered_qos_profiles" in c.metadata for c in summary.channels.values())
    assert summary.statistics.message_count == len(times)


def test_an_encode_folder_exports_stamped_from_when_it_was_encoded(exported, tmp_path):
    rec, _, _ = exported
    ds = rec.parent / "ds"
    enc, bag = tmp_path / "enc", tmp_path / "bag"
    assert main(["encode", str(ds), "--out", str(enc)]) == 0
    assert main(["export", "rosbag2", str(enc), str(bag)]) == 0
    s = read_encode_dir(enc)
    msgs = _read(bag)
    assert not s.clock and "/touchreal/description" not in msgs  # no hello, no clock points
    assert _check_spikes(s, msgs, lambda t_us: (s.created_wall_us + int(t_us) - s.origin_us()) * 1000, 5000) == 0
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert custom == {"touchreal.source": str(enc), "touchreal.stamps": "created_wall_us + (t_us - origin)"}


def test_export_refuses_what_it_cannot_read_or_would_overwrite(exported, tmp_path, capsys):
    rec, bag, _ = exported
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap")
    run = _export(tmp_path / "junk.mcap", tmp_path / "out")
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert "touchreal export: error:" in run.stderr and "not a readable TouchReal MCAP recording" in run.stderr
    assert not (tmp_path / "out").exists()

    assert main(["export", "rosbag2", str(rec), str(bag)]) == 2
    assert "exists already" in capsys.readouterr().err
    assert main(["export", "rosbag2", str(rec), str(tmp_path / "out"), "--dataset", str(tmp_path)]) == 2
    assert "--dataset: for encode folders only" in capsys.readouterr().err
    assert main(["export", "rosbag2", str(tmp_path / "nothing"), str(tmp_path / "out")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    # a recording across a server restart: two wire clocks on one timeline
    with pytest.raises(ValueError, match="spans 2 server sessions"):
        write_rosbag2(dataclasses.replace(read_mcap(rec), sessions=["before", "after"]), tmp_path / "out")
    assert not (tmp_path / "out").exists()
