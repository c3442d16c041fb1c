"""clients/examples/: the stimulation mapping (sans-I/O) and each example run as a program against a
real service on 127.0.0.1; the recorder's output read back by touchreal's own recording reader."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from server_harness import running_server
from touchreal_client import protocol as P

from touchreal.cli import main
from touchreal.params import DEFAULT_PARAMS_PATH, default_params
from touchreal.recording import Dataset
from touchreal.server.settings import RuntimeConfig
from touchreal.stream import encode_trial

EXAMPLES = Path(__file__).resolve().parents[1] / "clients" / "examples"
sys.path.insert(0, str(EXAMPLES))
import prosthesis_feedback as pf  # noqa: E402


def _frame(t_us, taxel, cls, final_us):
    return P.SpikesFrame(P.Header(P.KIND_SPIKES), np.array(t_us, np.uint64), np.array(taxel, np.uint16),
                         np.array(cls, np.uint8), final_us)


def test_spike_rate_modulates_pulse_rate_or_amplitude_per_class():
    m = pf.StimulationMapper({"RA": pf.ChannelMap(mode="rate"), "SA1": pf.ChannelMap(mode="amplitude")})
    m.push(_frame([], [], [], {"SA1": 0, "RA": 0, "PC": None}))
    ra = list(range(0, 100_000, 5_000))  # 200 Hz on taxel 0: the top of the rate range
    sa = list(range(0, 100_000, 10_000))  # 100 Hz on taxel 1: half the amplitude range
    t = ra + sa
    order = np.argsort(t, kind="stable")
    f = _frame(np.array(t)[order], np.array([0] * 20 + [1] * 10)[order], np.array([1] * 20 + [0] * 10)[order],
               {"SA1": 100_000, "RA": 100_000, "PC": None})
    pulses = m.push(f)
    ra_p = [p for p in pulses if p[2] == "RA"]
    sa_p = [p for p in pulses if p[2] == "SA1"]
    assert [p[0] for p in ra_p] == list(range(0, 100_000, 5_000)) and {p[3] for p in ra_p} == {500.0}
    assert [p[0] for p in sa_p] == list(range(0, 100_000, 20_000)) and {p[3] for p in sa_p} == {550.0}
    assert {p[1] for p in ra_p} == {0} and {p[1] for p in sa_p} == {1}
    # silence: the rate window empties, the channel stops
    assert m.push(_frame([], [], [], {"SA1": 300_000, "RA": 300_000, "PC": None})) == []
    with pytest.raises(ValueError):
        pf.StimulationMapper({"XX": pf.ChannelMap()})


def test_population_channels_take_the_mean_rate_of_their_afferents():
    aff = P.Afferents(np.array([0, 0, 0, 1]), np.array([[0.0, 0.0], [1.0, 0.0], [9.0, 0.0], [9.0, 1.0]]),
                      np.zeros(4, np.int64), {})
    groups = pf.electrode_groups(aff, 1, 2)
    assert groups == {0: 0, 1: 0, 2: 1, 3: 1}
    m = pf.StimulationMapper({"SA1": pf.ChannelMap(mode="amplitude")}, groups, {0: "SA1", 1: "SA1", 2: "SA1", 3: "RA"})
    m.push(_frame([], [], [], {"SA1": 0, "RA": None, "PC": None}))
    t = list(range(0, 100_000, 5_000))  # 200 Hz on afferent 0, none on 1: the field's mean is 100 Hz
    f = _frame(t + [50_000], [0] * 20 + [2], [0] * 21, {"SA1": 100_000, "RA": None, "PC": None})
    pulses = m.push(f)
    amp = {p[1]: p[3] for p in pulses}
    assert amp == {0: 550.0, 1: 145.0}  # field 0: half the amplitude range (100 Hz); field 1: its one SA1 at 10 Hz


@pytest.mark.slow
def test_prosthesis_example_drives_electrode_fields_from_a_population(tmp_path):
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"variants": {"SA1": [1.0], "RA": [1.0], "PC": [1.0]}}))
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(plan)) as (addr, _):
        run = [sys.executable, EXAMPLES / "prosthesis_feedback.py", "--url", f"http://{addr}", "--seconds", "4",
               "--out", tmp_path / "pulses.csv", "--map", "RA=rate,PC=rate", "--electrodes", "2x3"]
        pros = subprocess.run(run, capture_output=True, text=True, timeout=120)
    assert pros.returncode == 0, pros.stderr
    rows = list(csv.DictReader((tmp_path / "pulses.csv").open()))
    assert rows and {r["class"] for r in rows} <= {"RA", "PC"} and {int(r["channel"]) for r in rows} <= set(range(6))


@pytest.mark.slow
def test_prosthesis_and_recorder_examples_run_against_a_live_service(tmp_path):
    with running_server(tmp_path / "state", RuntimeConfig(taxels=2)) as (addr, _):
        url = f"http://{addr}"
        run = [sys.executable, EXAMPLES / "prosthesis_feedback.py", "--url", url, "--seconds", "4",
               "--out", tmp_path / "pulses.csv", "--map", "RA=rate,PC=rate"]
        pros = subprocess.run(run, capture_output=True, text=True, timeout=120)
        rec = subprocess.run([sys.executable, EXAMPLES / "record_session.py", "--url", url, "--seconds", "5",
                              "--out", tmp_path / "ds"], capture_output=True, text=True, timeout=120)
    assert pros.returncode == 0, pros.stderr
    rows = list(csv.DictReader((tmp_path / "pulses.csv").open()))
    assert rows and {r["class"] for r in rows} <= {"RA", "PC"} and {r["channel"] for r in rows} <= {"0", "1"}
    assert all(float(r["amplitude_uA"]) == 500.0 for r in rows)

    assert rec.returncode == 0, rec.stderr
    ds = Dataset.open(tmp_path / "ds")  # touchreal's reader validates rates, lengths and references
    assert [e["id"] for e in ds.entries()] == ["live-taxel0", "live-taxel1"]
    trial = ds.load("live-taxel0")
    assert trial.duration_s > 2.0 and trial.st.size > 200 and trial.pvdf.size > 4000
    live = {c: np.asarray(trial.reference[c].train(0, 0)) for c in P.CLASSES}
    again = {c: np.asarray(v) for c, v in encode_trial(trial, default_params()).items()}  # `touchreal encode`
    assert sum(v.size for v in live.values()) > 0
    # re-encoding the recorded (already filtered) channels gives back the streamed spikes, nearly: after a
    # second of warm-up, the same counts to 30 %, and RA/PC spikes at a median distance under 10 ms (SA1
    # follows the SingleTact, which the second pass low-passes again: its spikes move by more)
    t0 = trial.st_t[0] + 1.0
    compared = 0
    for c in P.CLASSES:
        a, b = live[c][live[c] > t0], again[c][again[c] > t0]
        if a.size >= 10:
            compared += 1
            assert abs(b.size - a.size) <= 0.3 * a.size, (c, a.size, b.size)
            dist = np.min(np.abs(b[None, :] - a[:, None]), axis=1)
            assert c == "SA1" or np.median(dist) < 0.010, (c, np.median(dist))
    assert compared >= 1
    # `touchreal evaluate` reads it: a live session has no commanded ramp, so no turning-point analysis
    assert main(["evaluate", str(tmp_path / "ds"), "--params", str(DEFAULT_PARAMS_PATH), "--out", str(tmp_path / "rep"),
                 "--split", "all", "--latency-trials", "1"]) == 0
    metrics = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert "turning_points" not in metrics and metrics["mapping"]


@pytest.mark.slow
def test_grasp_example_runs_the_downloaded_force_model_like_the_service(tmp_path):
    pytest.importorskip("onnxruntime")
    import grasp_force as gf

    ctl = gf.GripController(target_n=1.5, tolerance_n=0.1, gain_mm_s_per_n=4.0, max_speed_mm_s=10.0)
    assert ctl.command(1.0) == 2.0 and ctl.command(1.45) == 0.0 and ctl.command(9.0) == -10.0
    assert ctl.command(float("nan")) == 0.0
    with running_server(tmp_path) as (addr, _):
        run = subprocess.run([sys.executable, EXAMPLES / "grasp_force.py", "--url", f"http://{addr}", "--seconds", "5",
                              "--check"], capture_output=True, text=True, timeout=120)
        wrong = subprocess.run([sys.executable, EXAMPLES / "grasp_force.py", "--url", f"http://{addr}", "--model",
                                "texture", "--seconds", "1"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "t_us,taxel,force_N,command_mm_s" and len(lines) > 60  # ~31 steps per second
    steps = [int(ln.split(",")[0]) for ln in lines[1:]]
    assert all(b - a == 32_000 for a, b in zip(steps, steps[1:]))
    assert "max |local - service| = 0 N" in run.stderr
    assert wrong.returncode != 0 and "pick a force model" in wrong.stderr
