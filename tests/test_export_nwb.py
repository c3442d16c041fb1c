"""``touchreal export nwb``: an MCAP recording of a real server, and an encode folder, as NWB files that
nwbinspector accepts and pynwb reads back to the same spikes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from nwbinspector import Importance, inspect_nwbfile
from pynwb import NWBHDF5IO
from server_harness import running_server
from test_server_stream import _replay_dataset
from touchreal_client import protocol as P
from touchreal_client.session import read_mcap

from touchreal.cli import main


def _inspect(path):
    """The inspector's messages that matter: CRITICAL and BEST_PRACTICE_VIOLATION (and errors running a check)."""
    bad = {Importance.CRITICAL, Importance.BEST_PRACTICE_VIOLATION, Importance.ERROR, Importance.PYNWB_VALIDATION}
    return [f"{m.importance.name} {m.check_function_name} {m.object_name}: {m.message}"
            for m in inspect_nwbfile(nwbfile_path=str(path)) if m.importance in bad]


def _units(nwb):
    """(taxel, class) -> spike times (s) and obs intervals, from the file's Units table."""
    df = nwb.units.to_dataframe()
    return {(int(r.taxel), r.afferent_class): (np.asarray(r.spike_times), np.asarray(r.obs_intervals), list(r.position_mm))
            for r in df.itertuples()}


@pytest.mark.slow
def test_a_recording_of_a_live_server_exports_to_nwb(tmp_path):
    rec, out = tmp_path / "live.mcap", tmp_path / "live.nwb"
    with running_server(tmp_path / "state") as (addr, svc):
        assert main(["record", f"http://{addr}", "--out", str(rec), "--seconds", "2.5"]) == 0
    assert main(["export", "nwb", str(rec), "--out", str(out)]) == 0
    assert _inspect(out) == []

    s = read_mcap(rec)
    origin = s.origin_us()
    assert s.t_us.size > 0 and s.channels is not None and "force" in s.decoded
    with NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        units = _units(nwb)
        assert set(units) == {(0, c) for c in P.CLASSES}
        for k, c in enumerate(P.CLASSES):
            st, obs, pos = units[(0, c)]
            want = np.sort(s.t_us[(s.cls == k) & (s.taxel == 0)])
            assert np.array_equal(np.round(st * 1e6).astype(np.int64) + origin, want), c
            lo, hi = s.coverage_us[c]
            assert np.allclose(obs, [[(lo - origin) / 1e6, (hi - origin) / 1e6]]) and pos == [0.0, 0.0]
        assert nwb.units.resolution == 1e-6
        assert nwb.session_start_time.timestamp() * 1e6 == pytest.approx(s.wall_us_of(origin), abs=1)
        misc = nwb.processing["misc"]
        st = misc["ST"]
        assert st.unit == "N" and st.rate == pytest.approx(1e6 / 5000)  # decimation 25 -> 200 Hz
        np.testing.assert_array_equal(st.data[:], s.channels.data[:, :, 0])
        assert st.starting_time == pytest.approx((s.channels.t_us[0] - origin) / 1e6)
        np.testing.assert_array_equal(misc["decoded_force"].data[:], s.decoded["force"].values)
        revs = misc["parameter_revisions"].to_dataframe()
        assert revs["sha256"].tolist() == [svc.view.hello()["params"]["sha256"]] and revs["rev"].tolist() == [1]
        assert json.loads(nwb.scratch["parameters_rev1"].data) == s.params[0]["params"]
        clock = misc["clock"].to_dataframe()
        assert clock["sensor_us"].tolist() == [p.sensor_us for p in s.clock]


def test_an_encode_folder_exports_to_nwb_with_its_trials(tmp_path):
    ds, trials = _replay_dataset(tmp_path)
    enc, out = tmp_path / "enc", tmp_path / "enc.nwb"
    assert main(["encode", str(ds), "--out", str(enc)]) == 0  # the reference clock: stamps - the alignment lag
    assert main(["export", "nwb", str(enc), "--out", str(out), "--dataset", str(ds)]) == 0
    assert _inspect(out) == []
    with NWBHDF5IO(str(out), "r") as io:
        nwb = io.read()
        units = _units(nwb)
        tr = nwb.trials.to_dataframe()
        assert tr["trial_id"].tolist() == list(trials)
        for _, row in tr.iterrows():
            written = json.loads((enc / f"{row.trial_id}.json").read_text())
            assert row.stop_time - row.origin_time == pytest.approx(trials[row.trial_id].duration_s)
            for c in P.CLASSES:
                st = units[(0, c)][0]
                mine = st[(st >= row.start_time) & (st < row.stop_time)]
                assert np.array_equal(np.round((mine - row.origin_time) * 1e6), np.round(np.array(written[c]) * 1e6)), c
        revs = nwb.processing["misc"]["parameter_revisions"].to_dataframe()
        assert revs["rev"].tolist() == [0] and revs["source"].tolist() == ["the shipped parameter set"]
        assert "ST" not in nwb.processing["misc"].data_interfaces  # an encode folder has no channels


def test_export_refuses_what_it_cannot_read(tmp_path, capsys):
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap")
    assert main(["export", "nwb", str(tmp_path / "junk.mcap"), "--out", str(tmp_path / "x.nwb")]) == 2
    assert "not a readable TouchReal MCAP recording" in capsys.readouterr().err
    (tmp_path / "enc").mkdir()
    (tmp_path / "enc" / "t.json").write_text(json.dumps({"SA1": [0.1, "x"]}))
    assert main(["export", "nwb", str(tmp_path / "enc"), "--out", str(tmp_path / "x.nwb")]) == 2
    assert "SA1 must be a list of spike times" in capsys.readouterr().err
    assert main(["export", "nwb", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.nwb")]) == 2
    assert not (tmp_path / "x.nwb").exists()
