"""``touchreal_client.tonic``: a ``touchreal encode`` folder of simulated textures and a ``touchreal
record`` MCAP recording of a live 5-taxel skin as Tonic datasets: the events are the session's spikes
exactly, inside ``sensor_size``; Tonic's transforms and a batching loop take them; targets are the
manifest's textures; the texture example trains a classifier above chance."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from server_harness import running_server
from touchreal_client import Client
from touchreal_client.tonic import UNLABELLED, TouchRealDataset

from touchreal.cli import main
from touchreal.server.settings import RuntimeConfig

tonic = pytest.importorskip("tonic", reason="tonic is not installed (pip install -e 'clients/python[tonic]')")
import tonic.transforms as T  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "clients" / "examples" / "texture_tonic.py"
COMBS = ["comb_0.5mm", "comb_2mm", "comb_4mm"]


@pytest.fixture(scope="module")
def textures(tmp_path_factory):
    """(dataset folder, encode folder on the reference clock, manifest entries): 3 simulated texture
    trials, one per comb."""
    root = tmp_path_factory.mktemp("textures")
    assert main(["simulate", "texture", "--trials", "3", "--seed", "1", "--out", str(root / "ds")]) == 0
    assert main(["encode", str(root / "ds"), "--out", str(root / "enc")]) == 0
    return root / "ds", root / "enc", json.loads((root / "ds" / "manifest.json").read_text())["trials"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """An MCAP recording (spikes) of a live simulated skin of 5 taxels: a 3 x 2 grid, the last row one short."""
    root = tmp_path_factory.mktemp("recording")
    with running_server(root / "state", RuntimeConfig(taxels=5)) as (addr, _):
        with Client(f"http://{addr}") as tr:
            tr.wait_ready(60)
        assert main(["record", f"http://{addr}", "--out", str(root / "rec.mcap"), "--seconds", "2.5",
                     "--streams", "spikes"]) == 0
    return root / "rec.mcap"


def _spikes_of(ds: TouchRealDataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every sample's events back on the session's timeline: (t_us, column, class)."""
    evs = [(ds.events(i), s.start_us) for i, s in enumerate(ds.samples)]
    return (np.concatenate([e["t"] + start for e, start in evs]), np.concatenate([e["x"] for e, _ in evs]),
            np.concatenate([e["p"] for e, _ in evs]))


def _batches(ds: TouchRealDataset, size: int):
    """A torch-free DataLoader: stacked transformed samples and their targets, in order."""
    for lo in range(0, len(ds), size):
        items = [ds[i] for i in range(lo, min(lo + size, len(ds)))]
        yield np.stack([x for x, _ in items]), np.array([y for _, y in items])


def test_an_encode_folder_gives_its_trials_as_samples_with_their_textures(textures):
    ds_dir, enc, entries = textures
    ds = TouchRealDataset(enc, dataset=ds_dir)
    assert [s.id for s in ds.samples] == [e["id"] for e in entries]
    assert ds.classes == COMBS and sorted(e["texture"] for e in entries) == COMBS
    assert ds.targets == [COMBS.index(e["texture"]) for e in entries]
    assert [ds[i][1] for i in range(len(ds))] == ds.targets
    # one taxel: 1-D events, (taxels, 1, classes)
    assert ds.sensor_size == (1, 1, 3) and ds.ordering == "xtp" and ds.dtype.names == ("x", "t", "p")
    s = ds.session
    t, x, p = _spikes_of(ds)
    assert np.array_equal(t, s.t_us) and np.array_equal(p, s.cls) and not x.any() and s.t_us.size > 100
    for i, (sample, trial, entry) in enumerate(zip(ds.samples, s.trials, entries)):
        ev = ds[i][0]
        assert ev.dtype == ds.dtype and np.all(np.diff(ev["t"]) >= 0)
        assert ev["t"].min() >= 0 and ev["t"].max() < sample.stop_us - sample.start_us
        assert sample.start_us == trial.start_us <= trial.origin_us and trial.stop_us - trial.origin_us == 3_000_000
        written = json.loads((enc / f"{entry['id']}.json").read_text())
        for k, c in enumerate(("SA1", "RA", "PC")):  # the trial's own clock: the written times, to the µs
            mine = ev["t"][ev["p"] == k] + sample.start_us - trial.origin_us
            assert np.array_equal(mine, np.round(np.array(written[c]) * 1e6).astype(np.int64)), (entry["id"], c)
    # a new array per call: transforms may write into it
    ds.events(0)["p"] = 0
    assert np.array_equal(ds.events(0)["p"], ds[0][0]["p"]) and ds[0][0]["p"].any()


def test_windows_one_label_chosen_classes_and_no_labels(textures):
    ds_dir, enc, entries = textures
    whole = TouchRealDataset(enc, dataset=ds_dir)
    ds = TouchRealDataset(enc, dataset=ds_dir, window_us=1_000_000)
    assert [s.id for s in ds.samples] == [f"{e['id']}@{k}" for e in entries for k in range(3)]
    assert ds.targets == [t for t in whole.targets for _ in range(3)]
    for i, s in enumerate(ds.samples):
        ev = ds.events(i)
        assert s.stop_us - s.start_us == 1_000_000 and (ev["t"].size == 0 or ev["t"].max() < 1_000_000)
    t, _, p = _spikes_of(ds)
    inside = np.zeros(whole.session.t_us.size, bool)
    for s in ds.samples:
        inside |= (whole.session.t_us >= s.start_us) & (whole.session.t_us < s.stop_us)
    assert np.array_equal(t, whole.session.t_us[inside]) and np.array_equal(p, whole.session.cls[inside])

    one = TouchRealDataset(enc, label="comb_2mm", classes=COMBS)
    assert one.targets == [1, 1, 1] and one.classes == COMBS
    bare = TouchRealDataset(enc)
    assert bare.targets == [UNLABELLED] * 3 and bare.classes == [] and {s.label for s in bare.samples} == {None}


def test_tonic_transforms_and_batches_over_an_encode_folder(textures):
    ds_dir, enc, _ = textures
    ds = TouchRealDataset(enc, dataset=ds_dir)
    ev = ds.events(1)
    frames = T.ToFrame(sensor_size=ds.sensor_size, time_window=100_000, start_time=0, end_time=3_000_000)(ev)
    assert frames.shape == (30, 3, 1)
    assert frames.sum(axis=(0, 2)).tolist() == [int(np.sum(ev["p"] == k)) for k in range(3)]
    dropped = T.DropEvent(p=0.5)(ev)
    assert dropped.size == ev.size - int(0.5 * ev.size + 0.5) and np.isin(dropped, ev).all()
    # tonic's own wrappers take it: slices of 1 s are the trials' thirds
    sliced = tonic.SlicedDataset(ds, tonic.slicers.SliceByTime(time_window=1_000_000, start_time=0, end_time=3_000_000))
    assert len(sliced) == 9 and [sliced[i][1] for i in range(9)] == [y for y in ds.targets for _ in range(3)]
    assert np.array_equal(np.concatenate([sliced[i][0] for i in range(3)]), ds.events(0))

    ds.transform = T.ToFrame(sensor_size=ds.sensor_size, time_window=300_000, start_time=0, end_time=3_000_000)
    ds.target_transform = lambda y: ds.classes[y]
    batches = list(_batches(ds, 2))
    assert [b.shape for b, _ in batches] == [(2, 10, 3, 1), (1, 10, 3, 1)]
    assert [y for _, ys in batches for y in ys] == [ds.classes[y] for y in ds.targets]
    assert sum(int(b.sum()) for b, _ in batches) == ds.session.t_us.size
    ds.transform = ds.target_transform = None
    ds.transforms = lambda e, y: (e.size, y + 10)
    assert ds[2] == (ds.events(2).size, ds.targets[2] + 10)


def test_an_mcap_recording_of_a_grid_is_2d(recording):
    ds = TouchRealDataset(recording, label="live")
    s = ds.session
    assert ds.sensor_size == (3, 2, 3) and ds.ordering == "xytp" and ds.dtype.names == ("x", "y", "t", "p")
    assert len(ds) == 1 and ds.samples[0].id == "rec" and ds.targets == [0] and ds.classes == ["live"]
    ev, target = ds[0]
    start = ds.samples[0].start_us
    assert start == s.origin_us() and ds.samples[0].stop_us >= max(hi for _, hi in s.coverage_us.values())
    # the events are the spikes, each at its taxel's column (x_mm) and row (y_mm)
    assert s.t_us.size > 5 and np.unique(s.taxel).size >= 2
    xs = sorted({t["x_mm"] for t in s.taxels})
    ys = sorted({t["y_mm"] for t in s.taxels})
    pos = {t["id"]: (xs.index(t["x_mm"]), ys.index(t["y_mm"])) for t in s.taxels}
    assert np.array_equal(ev["t"] + start, s.t_us) and np.array_equal(ev["p"], s.cls)
    assert [(int(a), int(b)) for a, b in zip(ev["x"], ev["y"])] == [pos[int(k)] for k in s.taxel]
    assert (ev["x"].max() < 3 and ev["y"].max() < 2 and ev["p"].max() < 3 and ev["t"].min() >= 0
            and ev["x"].min() >= 0 and ev["y"].min() >= 0)

    duration = ds.samples[0].stop_us - start
    frames = T.ToFrame(sensor_size=ds.sensor_size, time_window=250_000, start_time=0, end_time=duration,
                       include_incomplete=True)(ev)
    assert frames.shape[1:] == (3, 2, 3) and frames.sum() == ev.size
    for j, k in pos.items():  # every taxel's spikes land on its own pixel
        assert frames[:, :, k[1], k[0]].sum() == np.sum(s.taxel == j)
    kept = T.Denoise(filter_time=1_000_000)(ev)  # reads x and y: a 2-D layout
    assert kept.dtype == ds.dtype and np.isin(kept, ev).all()
    dropped = T.DropEvent(p=0.25)(ev)
    assert dropped.size == ev.size - int(0.25 * ev.size + 0.5) and np.isin(dropped, ev).all()

    win = TouchRealDataset(recording, window_us=500_000)
    assert len(win) == duration // 500_000 and win.targets == [UNLABELLED] * len(win)
    t = np.concatenate([win.events(i)["t"] + w.start_us for i, w in enumerate(win.samples)])
    assert np.array_equal(t, s.t_us[s.t_us < win.samples[-1].stop_us])


def test_a_torch_dataloader_pads_frames_with_tonic_collation(textures):
    torch = pytest.importorskip("torch", reason="torch is not installed: the torch-free batching is tested above")
    ds_dir, enc, _ = textures
    frames = T.ToFrame(sensor_size=(1, 1, 3), time_window=100_000, start_time=0, end_time=1_000_000)
    ds = TouchRealDataset(enc, dataset=ds_dir, window_us=1_000_000, transform=frames)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, collate_fn=tonic.collation.PadTensors())
    batches = list(loader)
    assert [len(y) for _, y in batches] == [4, 4, 1]
    assert torch.cat([y for _, y in batches]).tolist() == ds.targets


def test_what_it_refuses(textures, tmp_path):
    ds_dir, enc, _ = textures
    cases = [
        (dict(source=enc, dataset=ds_dir, label="x"), "not both"),
        (dict(source=enc, window_us=0), "positive integer"),
        (dict(source=enc, window_us=True), "positive integer"),
        (dict(source=enc, window_us=4_000_000), "shorter than window_us"),
        (dict(source=enc, dataset=tmp_path), "not a readable dataset manifest"),
        (dict(source=enc, label="x", classes=["y"]), "not in classes"),
        (dict(source=enc, label="x", classes=["x", "x"]), "must not repeat"),
        (dict(source=tmp_path / "none"), "no such file or folder"),
    ]
    (tmp_path / "rec.mcap").write_bytes(b"not an mcap")
    cases += [(dict(source=tmp_path / "rec.mcap", dataset=ds_dir), "dataset is for a touchreal encode folder"),
              (dict(source=tmp_path / "rec.mcap"), "not a readable TouchReal MCAP recording")]
    other = tmp_path / "other"
    other.mkdir()
    (other / "elsewhere.json").write_text(json.dumps({"SA1": [0.1]}))
    cases.append((dict(source=other, dataset=ds_dir), "trials not in"))
    (other / "manifest.json").write_text(json.dumps({"trials": [{"id": "a"}]}))
    cases.append((dict(source=enc, dataset=other), "needs id, duration_s and condition"))
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            TouchRealDataset(kw.pop("source"), **kw)


def test_importing_the_client_imports_no_tonic():
    code = ("import sys, touchreal_client, touchreal_client.session, touchreal_client.tonic; "
            "assert 'tonic' not in sys.modules, 'tonic imported'")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr


@pytest.mark.slow  # ~12 s: simulate, encode and train the example end to end; .ci/run runs it (pytest -m slow)
def test_the_texture_example_classifies_above_chance(tmp_path):
    pytest.importorskip("sklearn", reason="scikit-learn is not installed")
    run = subprocess.run([sys.executable, EXAMPLE, "--trials", "30", "--work", tmp_path], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "sensor_size (1, 1, 3), ordering xtp" in run.stdout
    m = re.search(r"accuracy ([\d.]+) on 10 held-out trials \(chance ([\d.]+)\)", run.stdout)
    assert m, run.stdout
    assert float(m[1]) > float(m[2]) + 0.2, run.stdout
