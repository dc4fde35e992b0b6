"""Garbage and arbitrary split points between valid frames: every frame after the garbage is
recovered, nothing raises. One property test per parser."""

from __future__ import annotations

import dataclasses
import itertools

from hypothesis import assume, given, settings
from hypothesis import strategies as st
from strategies import dwm_shell_epochs, dwm_tlv_epochs, nlink_epochs, wit_streams

from drivers import PARSERS, ImuSample, dwm1001, dwm1001_tlv, nlink, wit
from drivers.base import _mask, _scan_loop, _scan_numpy
from drivers.layout import sum8

# garbage rich in the bytes that start or look like frames of the formats under test
_TRICKY = st.sampled_from([0x55, 0x55, 0x01, 0x51, 0x52, 0x40, 0x49, 0x0D, 0x0A,
                           *b"DIST,POS,AN0"])
garbage = st.lists(st.integers(0, 255) | _TRICKY, max_size=40).map(bytes)


def _is_subsequence(needles: list, haystack: list) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


def _spurious_fixed(stream: bytes, length: int, known: set[int], real: set[int]) -> bool:
    """Does any window that is not a real frame pass header, type and checksum?"""
    return any(
        stream[p] == 0x55 and stream[p + 1] in known and p not in real
        and sum8(stream[p : p + length - 1]) == stream[p + length - 1]
        for p in range(len(stream) - length + 1))


def _run(driver: str, chunks: list[bytes], garbages: list[bytes], cuts: list[int]):
    stream, starts = b"", []
    for g, c in zip(garbages, chunks, strict=True):
        stream += g
        starts.append(len(stream))
        stream += c
    parser = PARSERS[driver]()
    bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    frames = []
    for a, b in itertools.pairwise(bounds):
        frames += parser.feed(stream[a:b], 0)
    frames += parser.flush()
    assert parser.stats.bytes_in == len(stream)
    return stream, starts, frames, parser


cuts_st = st.lists(st.integers(0, 10_000), max_size=12)


@settings(max_examples=150)
@given(wit_streams(max_size=6), st.data(), cuts_st)
def test_wit_recovers_after_garbage(samples, data, cuts) -> None:
    garbages = [data.draw(garbage) for _ in samples]
    cycles = [wit.encode(s) for s in samples]
    stream, starts, frames, _ = _run("wit", cycles, garbages, cuts)
    packet_starts = {s + k for s, c in zip(starts, cycles, strict=True)
                     for k in range(0, len(c), wit.PACKET_LEN)}
    assume(not _spurious_fixed(stream, wit.PACKET_LEN, set(wit.KNOWN_TYPES), packet_starts))
    assert _is_subsequence(samples, frames)


@settings(max_examples=150)
@given(st.lists(nlink_epochs(), min_size=1, max_size=5), st.data(), cuts_st)
def test_nlink_recovers_after_garbage(epochs, data, cuts) -> None:
    garbages = [data.draw(garbage) for _ in epochs]
    stream, starts, frames, parser = _run("nlink", [nlink.encode(e) for e in epochs],
                                          garbages, cuts)
    assume(not _spurious_fixed(stream, nlink.FRAME_LEN, {nlink.MARK_TAG_FRAME0}, set(starts)))
    assert _is_subsequence(epochs, frames)
    assert parser.stats.frames == len(epochs)


@settings(max_examples=150)
@given(st.lists(dwm_shell_epochs(), min_size=1, max_size=5), st.data(), cuts_st)
def test_dwm1001_shell_recovers_after_garbage(epochs, data, cuts) -> None:
    # garbage ends at a line break or glues onto the next line's start: both must be survived
    garbages = [data.draw(garbage) for _ in epochs]
    _, _, frames, _ = _run("dwm1001", [dwm1001.encode(e) for e in epochs], garbages, cuts)
    assert _is_subsequence(epochs, frames)


@settings(max_examples=150)
@given(st.lists(dwm_tlv_epochs(), min_size=1, max_size=5), st.data(), cuts_st)
def test_dwm1001_tlv_recovers_after_garbage(epochs, data, cuts) -> None:
    garbages = [data.draw(garbage) for _ in epochs]
    # a spurious response needs the whole "status ok, position" prefix inside the garbage
    assume(all(dwm1001_tlv._OK_POS[:4] not in g for g in garbages))
    _, _, frames, _ = _run("dwm1001-tlv", [dwm1001_tlv.encode(e) for e in epochs],
                           garbages, cuts)
    assert _is_subsequence(epochs, frames)


@given(st.lists(nlink_epochs(), min_size=2, max_size=4), st.integers(0, 10_000))
def test_frames_carry_the_receive_time_of_their_last_byte(epochs, cut) -> None:
    stream = b"".join(nlink.encode(e) for e in epochs)
    cut %= len(stream)
    parser = nlink.NlinkParser()
    frames = parser.feed(stream[:cut], 100) + parser.feed(stream[cut:], 200)
    ends = [(k + 1) * nlink.FRAME_LEN for k in range(len(epochs))]
    assert frames == [dataclasses.replace(e, t_ns=100 if end <= cut else 200)
                      for e, end in zip(epochs, ends, strict=True)]



_valid = st.sampled_from([
    wit.encode(ImuSample(0, (0.0, 0.0, 9.80665), (0.0, 0.01, 0.0), 25.0)),
    wit.encode_packet(wit.ANGLE, {"angle_deg": (1.0, 2.0, 3.0)}),
])


@settings(max_examples=300)
@given(st.lists(garbage | _valid | _valid.map(lambda b: b[:7]), max_size=40).map(b"".join))
def test_small_and_large_scanners_agree(stream: bytes) -> None:
    """The plain loop (live reads) and the numpy scan (replays) are the same algorithm."""
    known = frozenset(wit.KNOWN_TYPES)
    assert _scan_loop(stream, wit.PACKET_LEN, 0x55, known) == _scan_numpy(
        stream, wit.PACKET_LEN, 0x55, _mask(known))
