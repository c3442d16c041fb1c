"""The live simulated e-skin's hop: a chunk ends with each SingleTact sample and halfway between."""

import time

import numpy as np
import pytest

from touchreal.raw import RawChunk
from touchreal.sources.live import SIM_RING_BYTES, HopRing, SimLiveSource


@pytest.mark.parametrize("seed", [0, 3])
def test_sim_hop_ends_a_chunk_with_each_singletact_sample(seed):
    src = SimLiveSource(2, 0.005, seed=seed)
    t0 = time.monotonic()
    chunks = [src.next_chunk() for _ in range(41)]
    pv = np.concatenate([c.pvdf_t for c in chunks])
    assert np.allclose(np.diff(pv), 0.0005)  # every tick once, in order
    st = np.concatenate([c.st_t for c in chunks])
    assert st.size >= 20 and np.allclose(np.diff(st), 0.01)
    # every chunk ends with a SingleTact sample (and its PVDF tick) or halfway between two
    half = (np.array([c.pvdf_t[-1] for c in chunks]) - st[0]) / 0.005
    assert np.allclose(half, np.round(half))
    assert all(c.st_t[-1] == c.pvdf_t[-1] for c, h in zip(chunks, np.round(half)) if h % 2 == 0)
    assert all(c.pvdf_t.size % 10 == 0 for c in chunks[1:])  # whole 5 ms hops after the aligning first chunk
    # paced: a chunk is released at the instant of its newest sample (the first one at the first call)
    assert time.monotonic() - t0 >= pv[-1] - chunks[0].pvdf_t[-1]
    clock = src.clock()
    assert clock.sensor_us == round(pv[-1] * 1e6) and clock.rate == 1.0
    src.close()
    assert src.next_chunk() is None


def test_a_consumer_that_fell_behind_gets_the_due_hops_in_one_chunk():
    src = SimLiveSource(1, 0.005, seed=1)
    first = src.next_chunk()
    time.sleep(0.1)  # the stimulus, not a wait: the consumer falls behind while ~20 hops come due
    late = src.next_chunk()
    assert 15 <= late.pvdf_t.size // 10 <= 64  # the due hops at once, not one per call
    assert np.allclose(np.diff(np.concatenate([first.pvdf_t, late.pvdf_t])), 0.0005)
    assert src.clock().sensor_us == round(late.pvdf_t[-1] * 1e6)
    assert src.next_chunk().pvdf_t.size < late.pvdf_t.size  # catching up
    src.close()


def test_the_sim_in_a_process_of_its_own_gives_the_same_hops_paced_the_same_way():
    here = SimLiveSource(3, 0.005, seed=2)
    there = SimLiveSource(3, 0.005, seed=2, own_process=True)
    for _ in range(120):  # unpaced: more than the process simulates ahead
        assert there.next_newest_s() == here.next_newest_s()
        a, b = here.read_hop(), there.read_hop()
        for f in ("st_t", "st", "pvdf_t", "pvdf"):
            assert np.array_equal(getattr(a, f), getattr(b, f))
    t0 = time.monotonic()
    chunks = [there.next_chunk() for _ in range(20)]  # (a late call gets the due hops in one chunk)
    paced = np.concatenate([c.pvdf for c in chunks])
    hops = []
    while sum(h.shape[0] for h in hops) < paced.shape[0]:
        hops.append(here.read_hop().pvdf)
    assert np.array_equal(paced, np.concatenate(hops))
    # released at the instant of the newest sample, as in this thread
    assert time.monotonic() - t0 >= chunks[-1].pvdf_t[-1] - chunks[0].pvdf_t[-1]
    assert there.clock().sensor_us == round(chunks[-1].pvdf_t[-1] * 1e6)
    proc = there.hops._proc
    there.close()
    assert there.next_chunk() is None
    assert not proc.is_alive() and proc.exitcode is not None


def test_a_sim_process_that_dies_fails_the_source_with_a_reason():
    src = SimLiveSource(1, 0.005, seed=1, own_process=True)
    assert src.next_chunk() is not None
    src.hops._proc.kill()
    deadline = time.monotonic() + 10.0
    with pytest.raises(RuntimeError, match="simulated e-skin's process ended"):
        while time.monotonic() < deadline:  # the hops already simulated are still handed over
            src.next_chunk()
    src.close()


def test_a_consumer_late_by_more_than_a_catch_up_chunk_keeps_the_schedule():
    """The consumer's own lateness is the consumer's to see (the service sheds on it): a fast simulation
    has the hops ready, so the schedule stays and the late hops' clock says how late they are. On a large
    skin too, whose first hop pays the skin's start (it does not count in the simulation's load)."""
    src = SimLiveSource(4096, 0.005, seed=0, touched=0.05, own_process=True)  # its first hop: one tick
    src.next_chunk()
    time.sleep(0.5)  # the stimulus: 100 hops come due, more than one catch-up chunk
    late = src.next_chunk()
    assert late.pvdf_t.size // 10 == 64  # one catch-up chunk's worth
    assert src.status()["fell_behind"] == 0 and src.clock().epoch == 0
    assert time.time_ns() // 1000 - src.clock().wall_us > 100_000  # its newest sample was acquired long ago
    src.close()


def test_a_simulation_slower_than_real_time_restarts_its_clock_and_says_so():
    """A skin this machine cannot simulate in real time (65,536 taxels in one process: about twice real
    time on a 2-core AMD EPYC): once the consumer waits for a hop more than a catch-up chunk late, the
    schedule restarts there (a new clock epoch), the samples stay continuous, and the status counts it."""
    src = SimLiveSource(65536, 0.005, seed=0, touched=0.05, own_process=True)
    try:
        chunks, deadline = [src.next_chunk()], time.monotonic() + 120
        while src.status()["fell_behind"] == 0:
            assert time.monotonic() < deadline, "the simulation never fell a catch-up chunk behind"
            chunks.append(src.next_chunk())
        restarted = src.next_chunk()  # the first chunk on the new schedule
        chunks.append(restarted)
        status, clock = src.status(), src.clock()
    finally:
        src.close()
    assert np.allclose(np.diff(np.concatenate([c.pvdf_t for c in chunks])), 0.0005)  # no sample lost or repeated
    assert clock.epoch >= 1 and clock.sensor_us == round(restarted.pvdf_t[-1] * 1e6)
    assert abs(time.time_ns() // 1000 - clock.wall_us) < 1_000_000  # acquired about now on the new schedule
    assert status["sim_load"] > 1.0 and status["behind_s"] > 0.32 and status["behind_wall_us"] is not None


def test_hops_cross_in_shared_memory_of_bounded_size_freed_on_close():
    """The ring holds at most SIM_RING_BYTES (a large skin gets fewer hops ahead, never fewer than 4), a
    hop that does not fit a slot (rows, dtypes, slot index) is refused with the reason, and closing the source frees the memory."""
    big = HopRing.slots_for(65536, 10, 32)
    assert 4 <= big < 32 and big * HopRing._layout(65536, 10)[1] <= SIM_RING_BYTES
    assert HopRing.slots_for(16, 10, 32) == 32
    ring = HopRing(3, 10, 4)
    try:
        rng = np.random.default_rng(0)
        hop = RawChunk(np.arange(1.0), rng.normal(size=(1, 3)).astype(np.float32), np.arange(10.0),
                       rng.normal(size=(10, 3)).astype(np.float32))
        got = ring.take(3, *ring.put(3, hop))
        for f in ("st_t", "st", "pvdf_t", "pvdf"):
            assert np.array_equal(getattr(got, f), getattr(hop, f)) and getattr(got, f).dtype == getattr(hop, f).dtype
        ring.put(3, RawChunk(*(np.zeros_like(a) for a in (hop.st_t, hop.st, hop.pvdf_t, hop.pvdf))))
        assert got.pvdf.any()  # taken hops are copies: the slot is written again without touching them
        with pytest.raises(ValueError, match="does not fit a slot"):
            ring.put(0, RawChunk(np.zeros(0), np.zeros((0, 3), np.float32), np.zeros(11), np.zeros((11, 3), np.float32)))
        with pytest.raises(ValueError, match="dtypes"):  # float64 samples would be stored rounded to float32
            ring.put(0, RawChunk(hop.st_t, hop.st.astype(np.float64), hop.pvdf_t, hop.pvdf))
        with pytest.raises(ValueError, match="not one of the ring's 4"):
            ring.put(4, hop)
    finally:
        ring.close(unlink=True)
    src = SimLiveSource(3, 0.005, seed=2, own_process=True)
    name = src.hops._ring.shm.name
    assert src.next_chunk() is not None
    src.close()
    with pytest.raises(FileNotFoundError):
        HopRing(3, 10, 4, name=name)
