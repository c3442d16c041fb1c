"""The serial frame codec: round trip, resync after garbage, CRC errors, gaps, bounds, split-invariance."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchreal.device.serial_frame import (
    HEADER,
    HEADER_SIZE,
    MAX_VALUES,
    SYNC,
    Channel,
    CrcError,
    Frame,
    FrameParser,
    Gap,
    Restart,
    Resync,
    crc16,
    encode_frame,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "serial-protocol.md"


def frames(events):
    return [e for e in events if isinstance(e, Frame)]


def same_frame(a: Frame, b: Frame) -> bool:
    return (a.channel, a.seq, a.session, a.t0_us) == (b.channel, b.seq, b.session, b.t0_us) and np.array_equal(
        a.samples, b.samples, equal_nan=True
    )


def stream(n: int = 6, n_taxels: int = 3, seed: int = 0) -> tuple[list[bytes], list[Frame]]:
    """Interleaved SingleTact and PVDF frames and the frames they encode."""
    rng = np.random.default_rng(seed)
    data, want = [], []
    for k in range(n):
        ch = Channel.PVDF if k % 3 else Channel.SINGLETACT
        seq = k - k // 3 - 1 if ch is Channel.PVDF else k // 3
        x = rng.normal(size=(10 if ch is Channel.PVDF else 1, n_taxels)).astype(np.float32)
        t0 = 1_000_000 + 5000 * k
        data.append(encode_frame(ch, seq, 0xBEEF, t0, x))
        want.append(Frame(ch, seq, 0xBEEF, t0, x))
    return data, want


def header(channel: int, n_taxels: int, n_samples: int, version: int = 1, fix_crc: bool = True) -> bytes:
    head = HEADER.pack(SYNC, version, channel, 0, 1, 0, n_taxels, n_samples)
    return head + struct.pack("<H", crc16(head) if fix_crc else crc16(head) ^ 0x0101)


def test_round_trip_keeps_every_value_bit_exact_including_nan_and_inf():
    x = np.array([[0.0, -1.65], [np.nan, np.inf], [-np.inf, 9.99], [1e-30, 3.25]], np.float32)
    data = encode_frame(Channel.PVDF, 7, 0x1234, 2**40 + 3, x)
    assert len(data) == HEADER_SIZE + 4 * x.size + 4
    (ev,) = FrameParser().feed(data)
    assert ev.channel is Channel.PVDF and (ev.seq, ev.session, ev.t0_us) == (7, 0x1234, 2**40 + 3)
    assert ev.samples.tobytes() == x.tobytes()
    assert list(ev.times_us - ev.t0_us) == [0, 500, 1000, 1500]
    st_frame = FrameParser().feed(encode_frame(Channel.SINGLETACT, 0, 0, 40, [2.5]))[0]
    assert st_frame.samples.shape == (1, 1) and list(st_frame.times_us) == [40]


def test_interleaved_channels_round_trip_without_gaps():
    data, want = stream(12)
    parser = FrameParser()
    got = parser.feed(b"".join(data))
    assert all(same_frame(a, b) for a, b in zip(got, want, strict=True))
    assert parser.stats.frames == 12 and parser.stats.gaps == 0 and parser.stats.bytes_discarded == 0


def test_garbage_before_and_between_frames_is_skipped_and_counted():
    data, want = stream(3)
    garbage1, garbage2 = b"\x00\xa5\xa5\x5a\x13hello", bytes(range(200))
    parser = FrameParser()
    events = parser.feed(garbage1 + data[0] + garbage2 + data[1] + data[2])
    assert [type(e) for e in events if not isinstance(e, CrcError)] == [Resync, Frame, Resync, Frame, Frame]
    resyncs = [e.discarded for e in events if isinstance(e, Resync)]
    assert resyncs == [len(garbage1), len(garbage2)]
    assert all(same_frame(a, b) for a, b in zip(frames(events), want, strict=True))
    assert parser.stats.resyncs == 2 and parser.stats.bytes_discarded == len(garbage1) + len(garbage2)


@pytest.mark.parametrize("where", ["header", "samples", "crc"])
def test_corrupted_frame_counts_a_crc_error_and_the_next_frame_still_decodes(where):
    data, want = stream(2)
    pos = {"header": 9, "samples": HEADER_SIZE + 5, "crc": len(data[0]) - 2}[where]
    bad = bytearray(data[0])
    bad[pos] ^= 0x40
    parser = FrameParser()
    events = parser.feed(bytes(bad) + data[1])
    assert CrcError("header" if where == "header" else "frame") in events
    (got,) = frames(events)
    assert same_frame(got, want[1])
    assert parser.stats.crc_errors == 1 and parser.stats.frames == 1


def test_any_single_byte_error_loses_only_its_own_frame():
    data, want = stream(2)
    rng = np.random.default_rng(1)
    for pos in range(len(data[0])):
        bad = bytearray(data[0])
        bad[pos] ^= int(rng.integers(1, 256))
        got = frames(FrameParser().feed(bytes(bad) + data[1]))
        assert len(got) == 1 and same_frame(got[0], want[1]), pos


def test_dropped_frames_are_counted_as_gaps_per_channel():
    data, _ = stream(9)  # ST seq 0,1,2 at k = 0,3,6; PVDF seq 0..5 at the others
    kept = [d for k, d in enumerate(data) if k not in (2, 4, 5)]  # PVDF 1, 2 and 3 lost
    parser = FrameParser()
    gaps = [e for e in parser.feed(b"".join(kept)) if isinstance(e, Gap)]
    assert gaps == [Gap(Channel.PVDF, 4, 3)]
    assert parser.stats.gaps == 1 and parser.stats.frames_missed == 3


def test_sequence_numbers_wrap_around_without_a_gap():
    x = np.zeros((1, 1), np.float32)
    seqs = [65534, 65535, 0, 1, 4]
    parser = FrameParser()
    events = parser.feed(b"".join(encode_frame(Channel.SINGLETACT, s, 9, 10_000 * s, x) for s in seqs))
    assert [e.seq for e in frames(events)] == [65534, 65535, 0, 1, 4]
    assert [e for e in events if isinstance(e, Gap)] == [Gap(Channel.SINGLETACT, 4, 2)]
    wrapped = FrameParser()
    gaps = [e for e in wrapped.feed(encode_frame(1, 65535, 9, 0, x) + encode_frame(1, 3, 9, 0, x)) if isinstance(e, Gap)]
    assert gaps == [Gap(Channel.SINGLETACT, 3, 3)]  # 0, 1, 2 missing across the wrap
    assert encode_frame(1, 65536 + 5, 9, 0, x) == encode_frame(1, 5, 9, 0, x)


def test_new_session_is_a_restart_not_a_gap():
    x = np.zeros((1, 1), np.float32)
    parser = FrameParser()
    events = parser.feed(encode_frame(1, 500, 1, 0, x) + encode_frame(1, 0, 2, 0, x) + encode_frame(1, 1, 2, 0, x))
    assert [type(e) for e in events] == [Frame, Restart, Frame, Frame]
    assert parser.stats.restarts == 1 and parser.stats.gaps == 0


@pytest.mark.parametrize(
    "bad",
    [
        header(Channel.PVDF, 4, MAX_VALUES),  # announces 16 KiB of samples: beyond the bound
        header(Channel.PVDF, 1000, 1),  # too many taxels
        header(Channel.PVDF, 1, 0),  # no samples
        header(Channel.PVDF, 0, 10),  # no taxels
        header(7, 1, 10),  # unknown channel
        header(Channel.PVDF, 1, 10, version=2),  # unknown version
    ],
)
def test_unacceptable_header_is_rejected_without_waiting_for_its_payload(bad):
    data, want = stream(1)
    parser = FrameParser()
    (got,) = frames(parser.feed(bad + data[0]))  # the frame follows at once: no wait for a payload
    assert same_frame(got, want[0])
    assert parser.stats.bad_headers == 1 and parser.stats.bytes_discarded == len(bad)


def test_corrupted_length_field_is_caught_by_the_header_crc():
    data, want = stream(1)
    parser = FrameParser()
    events = parser.feed(header(Channel.PVDF, 1, 1000, fix_crc=False) + data[0])
    assert CrcError("header") in events and same_frame(frames(events)[0], want[0])


def test_parser_buffer_stays_bounded_on_endless_garbage():
    parser = FrameParser()
    rng = np.random.default_rng(2)
    for _ in range(50):
        assert not frames(parser.feed(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()))
        assert len(parser._buf) < 4096 + HEADER_SIZE
    assert parser.stats.bytes_discarded > 50 * 4096 - 5000


def test_encode_frame_rejects_frames_beyond_the_bounds():
    with pytest.raises(ValueError, match="taxels"):
        encode_frame(Channel.PVDF, 0, 0, 0, np.zeros((MAX_VALUES + 1, 1)))
    with pytest.raises(ValueError, match="taxels"):
        encode_frame(Channel.PVDF, 0, 0, 0, np.zeros((0, 1)))
    with pytest.raises(ValueError, match="u64"):
        encode_frame(Channel.PVDF, 0, 0, -1, np.zeros((1, 1)))


def _fault_stream() -> bytes:
    data, _ = stream(8, n_taxels=2, seed=3)
    bad = bytearray(data[3])
    bad[30] ^= 0xFF
    return b"\x5a\xa5junk" + data[0] + data[1] + b"\xa5" + data[2] + bytes(bad) + data[5] + b"\xa5\x5a\x01" + data[6] + data[7]


def _normal(events) -> list:
    return [(type(e).__name__, e.channel, e.seq, e.t0_us, e.samples.tobytes()) if isinstance(e, Frame) else e for e in events]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=len(_fault_stream())), max_size=12))
def test_events_do_not_depend_on_how_the_bytes_are_split(cuts):
    data = _fault_stream()
    whole = FrameParser()
    want = _normal(whole.feed(data))
    bounds = [0, *sorted(cuts), len(data)]
    split = FrameParser()
    got = [e for a, b in zip(bounds, bounds[1:]) for e in _normal(split.feed(data[a:b]))]
    assert got == want and split.stats == whole.stats
    assert whole.stats.frames == 6 and whole.stats.gaps == 2 and whole.stats.crc_errors == 2  # the bad frame, the stray sync


def test_worked_example_in_the_protocol_document_is_what_the_encoder_writes():
    text = DOC.read_text()
    hex_text = re.search(r"<!-- example-frame -->\s*```\s*(.*?)```", text, re.S).group(1)
    example = bytes.fromhex("".join(hex_text.split()))
    want = encode_frame(Channel.PVDF, 0x0102, 0xBEEF, 1_500_000, np.array([[0.25, -0.5], [1.0, 0.125]], np.float32))
    assert example == want
    (ev,) = FrameParser().feed(example)
    assert ev.t0_us == 1_500_000


def test_c_struct_in_the_protocol_document_reads_the_worked_example(tmp_path):
    """Compile the document's C header and decode the example frame with it (needs a C compiler)."""
    import shutil
    import subprocess

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    text = DOC.read_text()
    (tmp_path / "tr.h").write_text(re.search(r"```c\n(.*?)```", text, re.S).group(1))
    example = bytes.fromhex("".join(re.search(r"<!-- example-frame -->\s*```\s*(.*?)```", text, re.S).group(1).split()))
    (tmp_path / "main.c").write_text(
        '#include <stdio.h>\n#include <string.h>\n#include "tr.h"\n'
        f"static const unsigned char frame[] = {{{', '.join(str(b) for b in example)}}};\n"
        "int main(void) { tr_header_t h; float s[4]; memcpy(&h, frame, sizeof h);\n"
        "  memcpy(s, frame + sizeof h, sizeof s);\n"
        '  printf("%u %u %x %llu %u %u %x %g %g %g %g %x %lx", h.channel, h.seq, h.session, (unsigned long long)h.t0_us,\n'
        "         h.n_taxels, h.n_samples, h.header_crc, s[0], s[1], s[2], s[3], tr_crc16(frame, 20),\n"
        "         (unsigned long)tr_crc32(frame, sizeof frame - 4)); return 0; }\n"
    )
    subprocess.run([cc, "-std=c11", "-Wall", "-Werror", "-o", str(tmp_path / "main"), str(tmp_path / "main.c")], check=True)
    out = subprocess.run([str(tmp_path / "main")], check=True, capture_output=True, text=True).stdout
    header_crc, frame_crc = f"{crc16(example[:20]):x}", f"{zlib.crc32(example[:-4]):x}"
    fields = ["2", "258", "beef", "1500000", "2", "2", header_crc, "0.25", "-0.5", "1", "0.125", header_crc, frame_crc]
    assert out.split() == fields
