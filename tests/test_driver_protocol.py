"""The sans-I/O protocol layer: golden frames, conversions, and the frame decoder.

Golden frames are typed in from ``shared/optotune-lens-driver-4.md``; reply frames are
built with an independent bitwise CRC-16/ARC written here, not with the code under test.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.driver_frames import ref_crc
from tdfd.driver import protocol as p
from tdfd.errors import (
    ChecksumError,
    DeviceErrorReply,
    ForbiddenCommandError,
    LensRangeError,
    ProtocolError,
    TdfdError,
    UnsupportedFirmwareError,
)



def ref_reply(prefix: bytes, data: bytes = b"") -> bytes:
    body = prefix + data
    c = ref_crc(body)
    return body + bytes([c & 0xFF, c >> 8]) + b"\r\n"


# --------------------------------------------------------------------------- golden


def test_crc_check_value() -> None:
    assert p.crc16_arc(b"123456789") == 0xBB3D
    assert ref_crc(b"123456789") == 0xBB3D  # the test's own reference agrees with the facts


def test_crc_of_start() -> None:
    assert p.crc16_arc(b"Start") == 0xA5EA


def test_crc_is_not_modbus() -> None:
    assert p.crc16_arc(b"123456789") != 0x4B37  # CRC-16/MODBUS check value (init 0xFFFF)


def test_golden_set_current_frame() -> None:
    assert p.encode_set_current(0x04B2) == bytes.fromhex("41 77 04 B2 26 93")
    assert p.with_crc(bytes.fromhex("41 77 04 B2")) == bytes.fromhex("41 77 04 B2 26 93")


def test_golden_current_example_100_ma_of_292() -> None:
    raw = p.current_ma_to_raw(100.0, 292.0)
    assert raw == 1402
    assert p.encode_set_current(raw) == bytes.fromhex("41 77 05 7A 26 95")


def test_golden_current_default_max() -> None:
    assert p.current_ma_to_raw(100.0, 292.84) == 1398
    assert p.max_current_raw_to_ma(29284) == pytest.approx(292.84)


def test_golden_focal_power_type_a() -> None:
    raw = p.focal_power_dpt_to_raw(3.0, "A")
    assert raw == 1600
    assert p.encode_set_focal_power(raw) == bytes.fromhex("50 77 44 41 06 40 00 00 30 2C")


def test_golden_handshake() -> None:
    assert p.encode_start() == b"Start"
    assert p.decode_frame(b"Ready\r\n") == p.Frame(b"Ready", b"")


# --------------------------------------------------------------------------- builders


BUILDERS = [
    (p.encode_get_firmware_type, b"H"),
    (p.encode_get_firmware_version, b"V"),
    (p.encode_get_serial_number, b"X"),
    (p.encode_get_device_id, b"IR" + bytes(8)),
    (lambda: p.encode_set_current(-1398), b"Aw\xfa\x8a"),
    (p.encode_get_current, b"Ar\x00\x00"),
    (p.encode_get_max_current, b"CrMA\x00\x00"),
    (p.encode_get_upper_current_limit, b"CrUA\x00\x00"),
    (p.encode_get_lower_current_limit, b"CrLA\x00\x00"),
    (p.encode_current_mode, b"MwDA"),
    (p.encode_focal_power_mode, b"MwCA"),
    (p.encode_get_mode, b"MMA"),
    (lambda: p.encode_set_temperature_limits(640, 320), b"PwTA\x02\x80\x01\x40"),
    (lambda: p.encode_set_focal_power(-200), b"PwDA\xff\x38\x00\x00"),
    (p.encode_get_focal_power, b"PrDA\x00\x00\x00\x00"),
    (p.encode_get_temperature, b"TCA"),
    (p.encode_get_status, b"Sr"),
]


@pytest.mark.parametrize(("build", "body"), BUILDERS, ids=[b.decode("latin1")[:4] for _, b in BUILDERS])
def test_every_builder(build, body: bytes) -> None:  # noqa: ANN001
    frame = build()
    c = ref_crc(body)
    assert frame == body + bytes([c & 0xFF, c >> 8])
    spec = p.command_spec_for(frame)
    assert spec is not None and spec.length == len(frame)


def test_every_command_has_a_builder_and_no_reset() -> None:
    built = {p.command_spec_for(b()).name for b, _ in BUILDERS} | {b"Start"}
    assert built == set(p.COMMANDS)
    assert b"RESET" not in p.COMMANDS
    assert not [name for name in p.__all__ if "reset" in name.lower()]


@pytest.mark.parametrize("payload", [b"RESET", b"RESETxx", b"reset"])
def test_reset_cannot_be_framed(payload: bytes) -> None:
    with pytest.raises(ForbiddenCommandError):
        p.with_crc(payload)


def test_reply_prefixes() -> None:
    assert p.reply_prefix_for(p.encode_start()) == b"Ready"
    assert p.reply_prefix_for(p.encode_set_current(1)) is None
    assert p.reply_prefix_for(p.encode_set_focal_power(1)) is None
    assert p.reply_prefix_for(p.encode_set_temperature_limits(1, 0)) == b"PT"
    with pytest.raises(ProtocolError):
        p.reply_prefix_for(b"Q")


# --------------------------------------------------------------------------- conversions


def test_negative_current_is_signed() -> None:
    assert p.encode_set_current(p.current_ma_to_raw(-100.0, 292.84))[2:4] == bytes.fromhex("FA 8A")
    assert p.unpack_i16(bytes.fromhex("FA 8A")) == -1398
    assert p.current_raw_to_ma(-1398, 292.84) == pytest.approx(-99.973, abs=1e-3)


def test_current_range_is_an_error_not_a_clamp() -> None:
    assert p.current_ma_to_raw(292.84, 292.84) == 4095
    assert p.current_ma_to_raw(-292.84, 292.84) == -4095
    for bad in (292.92, -300.0, float("nan"), float("inf")):
        with pytest.raises(LensRangeError):
            p.current_ma_to_raw(bad, 292.84)
    with pytest.raises(LensRangeError):
        p.encode_set_current(4096)
    with pytest.raises(LensRangeError):
        p.current_ma_to_raw(1.0, 0.0)


def test_rounding_is_half_away_from_zero() -> None:
    assert p.round_half_away(0.5) == 1
    assert p.round_half_away(-0.5) == -1
    assert p.round_half_away(1.4999) == 1


def test_focal_power_encodings() -> None:
    assert p.focal_power_dpt_to_raw(-5.0, "A") == 0
    assert p.focal_power_dpt_to_raw(15.475, "A") == 4095
    for fw in "BCE":
        assert p.focal_power_dpt_to_raw(3.0, fw) == 600
        assert p.focal_power_dpt_to_raw(-2.5, fw) == -500
        assert p.focal_power_raw_to_dpt(-500, fw) == -2.5
    assert p.focal_power_raw_to_dpt(1600, "A") == 3.0
    with pytest.raises(UnsupportedFirmwareError):
        p.focal_power_dpt_to_raw(1.0, "F")
    with pytest.raises(UnsupportedFirmwareError):
        p.focal_power_raw_to_dpt(1, "F")
    with pytest.raises(LensRangeError):
        p.focal_power_dpt_to_raw(1000.0, "B")
    with pytest.raises(LensRangeError):
        p.focal_power_dpt_to_raw(float("nan"), "A")


def test_temperature_encodings() -> None:
    assert p.temperature_c_to_raw(25.0) == 400
    assert p.temperature_raw_to_c(400) == 25.0
    assert p.temperature_raw_to_c(-16) == -1.0
    assert p.temperature_raw_to_c(4095) is None


@given(st.integers(-0x8000, 0x7FFF))
def test_i16_round_trip(value: int) -> None:
    assert p.unpack_i16(p.pack_i16(value)) == value
    assert p.pack_i16(value) == struct.pack(">h", value)


@given(st.floats(-292.84, 292.84))
def test_current_round_trip_within_half_lsb(current_ma: float) -> None:
    raw = p.current_ma_to_raw(current_ma, 292.84)
    assert abs(p.current_raw_to_ma(raw, 292.84) - current_ma) <= 0.5 * 292.84 / 4095 + 1e-9


@given(st.binary(max_size=64))
def test_crc_matches_reference(data: bytes) -> None:
    assert p.crc16_arc(data) == ref_crc(data)


# --------------------------------------------------------------------------- decoding


def test_decode_each_reply_kind() -> None:
    assert p.decode_frame(ref_reply(b"H", b"A")) == p.Frame(b"H", b"A")
    version = p.decode_frame(ref_reply(b"V", bytes([1, 8, 0x07, 0xE5, 0, 3])))
    assert str(p.parse_firmware_version(version)) == "1.8.2021.3"
    assert p.decode_frame(ref_reply(b"CMA", b"\x72\x64")).data == b"\x72\x64"
    mca = p.decode_frame(ref_reply(b"MCA", bytes([0]) + struct.pack(">hh", 1500, 0)))
    limits = p.parse_focal_power_limits(mca, "A")
    assert (limits.min_dpt, limits.max_dpt) == (-5.0, 2.5)
    status = p.parse_status(p.decode_frame(ref_reply(b"S", bytes([0x84, 0, 0, 0]))))
    assert status.flags == p.StatusFlags.NO_TEMPERATURE_LIMITS | p.StatusFlags.TEMPERATURE_OUTSIDE_USER_LIMITS


def test_decode_error_replies() -> None:
    err = p.decode_frame(ref_reply(b"E", b"\x02"))
    assert err == p.ErrorFrame(2)
    exc = err.to_exception()
    assert isinstance(exc, DeviceErrorReply) and exc.code == 2
    bare = p.decode_frame(b"N\r\n")
    assert bare == p.ErrorFrame(1, bare=True) and bare.to_exception().code == 1


def test_decode_bad_crc_and_bad_frames() -> None:
    good = ref_reply(b"A", b"\x05\x7a")
    bad = good[:3] + bytes([good[3] ^ 1]) + good[4:]
    with pytest.raises(ChecksumError):
        p.decode_frame(bad)
    with pytest.raises(ProtocolError):
        p.decode_frame(good[:-1])
    with pytest.raises(ProtocolError):
        p.decode_frame(good + b"x")
    with pytest.raises(ProtocolError):
        p.decode_frame(good[:-2] + b"\n\r")
    with pytest.raises(ProtocolError):
        p.decode_frame(b"")


def _value_with_newline_in_crc() -> int:
    for value in range(-0x8000, 0x8000):
        body = b"A" + struct.pack(">h", value)
        c = ref_crc(body)
        if 0x0A in (c & 0xFF, c >> 8):
            return value
    raise AssertionError("unreachable")


def test_newline_bytes_in_data_and_crc_do_not_split_frames() -> None:
    value = _value_with_newline_in_crc()
    frames = [ref_reply(b"A", b"\x0a\x0d"), ref_reply(b"A", struct.pack(">h", value)), ref_reply(b"TCA", b"\x0d\x0a")]
    decoder = p.FrameDecoder()
    out = []
    for byte in b"".join(frames):  # byte by byte
        out += decoder.feed(bytes([byte]))
    assert out == [p.decode_frame(f) for f in frames]
    assert p.unpack_i16(out[1].data) == value
    assert decoder.discarded == 0


def test_decoder_resynchronises_after_garbage_and_bad_crc() -> None:
    good = ref_reply(b"PD", b"\x06\x40")
    corrupted = ref_reply(b"A", b"\x00\x01")[:-3] + b"\x00\r\n"
    decoder = p.FrameDecoder()
    frames = decoder.feed(b"\x00\xffMC" + corrupted + good + b"N\r\n")
    assert frames == [p.Frame(b"PD", b"\x06\x40"), p.ErrorFrame(1, bare=True)]
    errors = decoder.pop_errors()
    assert any(isinstance(e, ChecksumError) for e in errors)
    assert all(isinstance(e, ProtocolError) for e in errors)
    assert decoder.pop_errors() == []


def test_decoder_prefers_a_complete_frame_over_a_stale_partial() -> None:
    decoder = p.FrameDecoder()
    # "IR" would need 14 bytes; the valid 'N' error reply inside them wins
    assert decoder.feed(b"IR\x00N\r\n") == [p.ErrorFrame(1, bare=True)]


def test_decoder_needed_counts_bytes() -> None:
    decoder = p.FrameDecoder()
    assert decoder.needed() == 3
    assert decoder.feed(b"CM") == []
    assert decoder.needed() == 6  # "CMA" needs 7 more, but the "M" could start a 7-byte "MDA"
    assert decoder.feed(ref_reply(b"CMA", b"\x72\x64")[2:]) == [p.Frame(b"CMA", b"\x72\x64")]
    assert decoder.needed() == 3
    assert decoder.feed(b"E") == []
    assert decoder.needed() == 5
    assert decoder.reset() == b"E"


# --------------------------------------------------------------------------- fuzzing

_ALL_REPLIES = st.one_of(
    st.sampled_from([b"Ready\r\n", b"N\r\n"]),
    st.builds(
        lambda prefix, data: ref_reply(prefix, data[: p.REPLY_DATA_LENGTHS[prefix]].ljust(p.REPLY_DATA_LENGTHS[prefix], b"\0")),
        st.sampled_from(sorted(p.REPLY_DATA_LENGTHS)),
        st.binary(min_size=8, max_size=8),
    ),
)

_fuzz = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_fuzz
@given(st.lists(st.binary(max_size=40), max_size=12))
def test_fuzz_feed_never_raises(chunks: list[bytes]) -> None:
    decoder = p.FrameDecoder()
    for chunk in chunks:
        for frame in decoder.feed(chunk):
            assert isinstance(frame, (p.Frame, p.ErrorFrame))
        assert decoder.needed() >= 1
        assert len(decoder.pending) < 16  # never hoards bytes
    for error in decoder.pop_errors():
        assert isinstance(error, ProtocolError)


@_fuzz
@given(st.binary(max_size=30))
def test_fuzz_decode_frame_raises_only_protocol_errors(data: bytes) -> None:
    try:
        frame = p.decode_frame(data)
    except ProtocolError:
        return
    except TdfdError as exc:  # pragma: no cover - would be a bug
        raise AssertionError(f"unexpected {type(exc).__name__}") from exc
    assert isinstance(frame, (p.Frame, p.ErrorFrame))
    assert frame.to_bytes() == data


@_fuzz
@given(st.binary(max_size=60), st.lists(_ALL_REPLIES, min_size=1, max_size=5), st.integers(1, 20))
def test_fuzz_frames_after_garbage_are_found(garbage: bytes, replies: list[bytes], chunk: int) -> None:
    stream = garbage + b"".join(replies)
    decoder = p.FrameDecoder()
    found = []
    for i in range(0, len(stream), chunk):
        found += decoder.feed(stream[i : i + chunk])
    expected = [p.decode_frame(r) for r in replies]
    assert found[-len(expected) :] == expected
    assert decoder.pending == b""


@_fuzz
@given(st.lists(_ALL_REPLIES, min_size=1, max_size=6), st.data())
def test_fuzz_any_chunking_of_valid_replies_decodes_exactly(replies: list[bytes], data: st.DataObject) -> None:
    stream = b"".join(replies)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    decoder = p.FrameDecoder()
    found = []
    last = 0
    for cut in [*cuts, len(stream)]:
        found += decoder.feed(stream[last:cut])
        last = cut
    assert found == [p.decode_frame(r) for r in replies]
    assert decoder.discarded == 0


# --------------------------------------------------------------------------- the reply reader (expected length)

_INNER = [b"N\r\n", b"Ready\r\n", ref_reply(b"E", b"\x01")[:6]]


def test_reply_reader_decodes_by_the_expected_length() -> None:
    x = ref_reply(b"X", b"AN\r\nBCDE")  # a serial number holding a bare error reply
    assert p.ReplyReader(b"X").feed(x) == [p.Frame(b"X", b"AN\r\nBCDE")]
    ir = ref_reply(b"IR", b"Ready\r\n\x00")
    assert p.ReplyReader(b"IR").feed(ir) == [p.Frame(b"IR", b"Ready\r\n\x00")]
    # the stream decoder, fed as the bytes arrive, takes the inner frame: the reason the reader exists
    decoder = p.FrameDecoder()
    assert decoder.feed(x[:3]) + decoder.feed(x[3:6]) == [p.ErrorFrame(1, bare=True)]


def test_reply_reader_byte_by_byte_and_needed() -> None:
    x = ref_reply(b"X", b"N\r\nReady")
    reader = p.ReplyReader(b"X")
    assert reader.needed() == 3
    found = []
    for i, byte in enumerate(x):
        found += reader.feed(bytes([byte]))
        if i < len(x) - 1:
            assert found == [] and reader.needed() == len(x) - i - 1
    assert found == [p.Frame(b"X", b"N\r\nReady")]


def test_reply_reader_consumes_other_frames_whole() -> None:
    stale = ref_reply(b"IR", b"xN\r\nyyyy")  # a late reply to an earlier command, with an inner frame
    error = ref_reply(b"E", b"\x03")
    reply = ref_reply(b"A", bytes.fromhex("05 7A"))
    reader = p.ReplyReader(b"A")
    assert reader.feed(b"\x00\x13" + stale + error + reply) == [
        p.Frame(b"IR", b"xN\r\nyyyy"),
        p.ErrorFrame(3),
        p.Frame(b"A", bytes.fromhex("05 7A")),
    ]
    assert reader.discarded == 2 and reader.pending == b""


def test_reply_reader_bad_crc_of_the_expected_reply_is_consumed_whole() -> None:
    bad = bytearray(ref_reply(b"X", b"N\r\nabcde"))
    bad[-3] ^= 0xFF
    reader = p.ReplyReader(b"X")
    assert reader.feed(bytes(bad)) == []
    assert [type(e) for e in reader.errors] == [ChecksumError]
    assert reader.pending == b""


def test_reply_reader_finish_finds_a_short_frame_behind_a_stray_prefix_byte() -> None:
    reader = p.ReplyReader(b"X")
    error = ref_reply(b"E", b"\x01")
    assert reader.feed(b"X" + error) == []  # could still be a 13-byte X reply
    assert reader.finish() == [p.ErrorFrame(1)]


def test_reply_reader_refuses_unknown_prefixes() -> None:
    with pytest.raises(ProtocolError):
        p.ReplyReader(b"Q")


@_fuzz
@given(
    st.sampled_from(sorted(k for k in p.REPLY_DATA_LENGTHS if k != b"E")),
    st.data(),
    st.lists(_ALL_REPLIES, max_size=3),
    st.binary(max_size=12),
)
def test_fuzz_reply_reader_finds_the_expected_reply_whatever_its_payload(
    prefix: bytes, data: st.DataObject, before: list[bytes], garbage: bytes
) -> None:
    n = p.REPLY_DATA_LENGTHS[prefix]
    inner = data.draw(st.sampled_from(_INNER + [b""]))
    payload = (data.draw(st.binary(max_size=n)) + inner)[:n].ljust(n, b"\0")
    reply = ref_reply(prefix, payload)
    before = [r for r in before if not r.startswith(prefix)]  # a same-prefix reply would be taken first
    # garbage may not end in a (partial) frame start swallowing what follows
    stream = garbage + b"\0" * 8 + b"".join(before) + reply
    reader = p.ReplyReader(prefix)
    found = []
    chunk = data.draw(st.integers(1, 9))
    for i in range(0, len(stream), chunk):
        found += reader.feed(stream[i : i + chunk])
    assert p.Frame(prefix, payload) in found
    assert found[-1] == p.Frame(prefix, payload)
