"""The pure Micromodem NMEA codec: checksums, parsing, typed sentences, line splitting (no ports)."""

from __future__ import annotations

import base64

import pytest

from coex_core import acoustic
from coex_core.errors import DecodeError
from coex_transports.micromodem import nmea
from coex_transports.micromodem.nmea import NmeaError

# Real Micromodem-2 lines (firmware 2.0.27087, GobySoft/goby3#126), from micromodem.md §0 and §5.
REAL_LINES = [
    "$CACFG,CST,1*35",
    "$CCCFG,SRC,0*30",
    "$CACYC,0,0,8,0,0,1*52",
    "$CCTMQ,0*54",
    "$CACFG,info.part_number,201005*2D",
    "$CACFG,MCM,1*32",
    "$CACFG,hwd.1wire.aux1_rom,0000000000000000*71",
]


@pytest.mark.parametrize("line", REAL_LINES)
def test_real_modem_lines_parse_and_rebuild_byte_exact(line: str) -> None:
    s = nmea.parse(line + "\r\n")
    assert s.encode() == (line + "\r\n").encode()
    body, given = line[1:].split("*")
    assert nmea.checksum(body) == given


def test_parse_fields_and_ident() -> None:
    s = nmea.parse(b"$CACFG,info.part_number,201005*2D\r\n")
    assert (s.talker, s.kind, s.ident, s.fields) == ("CA", "CFG", "CACFG", ("info.part_number", "201005"))


def test_checksum_is_optional_but_checked_when_present() -> None:
    assert nmea.parse("$CACFG,CST,1").fields == ("CST", "1")
    assert nmea.parse("$CACFG,CST,1*35").fields == ("CST", "1")
    assert nmea.parse("$CACFG,info.part_number,201005*2d").fields[1] == "201005"  # either case
    with pytest.raises(NmeaError, match="checksum"):
        nmea.parse("$CACFG,CST,1*36")
    with pytest.raises(NmeaError, match="checksum"):
        nmea.parse("$CACFG,CST,1*3")


@pytest.mark.parametrize("bad", [
    "", "CACFG,CST,1", "$", "$CA", "$cacfg,CST,1", "$CACFGX,1", "$CA CF,1", "$CACFG,A$B",
    "$CACFG,A*B*35", b"$CACFG,\xff", "$CACFG,\x01",
])
def test_malformed_lines_raise_nmea_error_which_is_a_decode_error(bad: str | bytes) -> None:
    with pytest.raises(NmeaError) as info:
        nmea.parse(bad)
    assert isinstance(info.value, DecodeError)


def test_overlong_line_rejected() -> None:
    with pytest.raises(NmeaError, match="longer"):
        nmea.parse("$CARXD,1,2,0,1," + "a" * (nmea.MAX_LINE + 2))


def test_format_writes_booleans_as_digits_and_rejects_reserved_characters() -> None:
    assert nmea.format_sentence("CCTDP", [2, 5, False, True, "ab"]) == b"$CCTDP,2,5,0,1,ab*69\r\n"
    with pytest.raises(ValueError):
        nmea.format_sentence("CCCFG", ["A,B", 1])
    with pytest.raises(ValueError):
        nmea.format_sentence("CCCFG", ["A*", 1])


def test_typed_field_access_errors() -> None:
    s = nmea.parse("$CACYC,0,1,2,9,0,3")
    with pytest.raises(NmeaError, match="out of"):
        nmea.parse_cacyc(s)  # rate 9
    with pytest.raises(NmeaError, match="missing"):
        nmea.parse_cacyc(nmea.parse("$CACYC,0,1,2"))
    with pytest.raises(NmeaError, match="not an integer"):
        nmea.parse_cacyc(nmea.parse("$CACYC,0,x,2,1,0,3"))
    with pytest.raises(NmeaError, match="expected"):
        nmea.parse_cacyc(nmea.parse("$CADRQ,0,1,2,1,0,3"))
    with pytest.raises(NmeaError, match="finite"):
        nmea.parse_campr(nmea.parse("$CAMPR,2,1,nan"))


def test_legacy_sentences() -> None:
    assert nmea.parse_cacyc(nmea.parse("$CACYC,0,1,2,5,1,8")) == nmea.CycleInit(1, 2, 5, True, 8)
    assert nmea.parse_cadrq(nmea.parse("$CADRQ,123456,1,2,0,256,3")) == nmea.DataRequest(1, 2, False, 256, 3)
    rxd = nmea.parse_carxd(nmea.parse("$CARXD,2,1,0,1,DEADbeef"))
    assert rxd == nmea.RxData(2, 1, False, 1, bytes.fromhex("deadbeef"))
    assert nmea.parse_carxd(nmea.parse("$CARXD,2,1,0,3,")).data == b""
    with pytest.raises(NmeaError, match="hex"):
        nmea.parse_carxd(nmea.parse("$CARXD,2,1,0,1,abc"))
    assert nmea.parse_caack(nmea.parse("$CAACK,2,1,3,1")) == nmea.Ack(2, 1, 3, True)
    assert nmea.parse_carev(nmea.parse("$CAREV,120000,INIT,2.0.27087")).ident == "INIT"
    err = nmea.parse_caerr(nmea.parse("$CAERR,120000,DATA_TIMEOUT,2,host too slow"))
    assert (err.module, err.number) == ("DATA_TIMEOUT", "2")
    assert nmea.parse_campr(nmea.parse("$CAMPR,2,1,0.6667")) == nmea.PingReply(2, 1, 0.6667)


def test_rate_tables_match_the_reference_note() -> None:
    assert nmea.RATES is acoustic.RATES  # one rate table: the driver and the channel model share it
    assert [(r.frame_bytes, r.frames) for r in nmea.RATES.values()] == [
        (32, 1), (64, 3), (64, 3), (256, 2), (256, 2), (256, 8), (32, 6)]
    assert {k: v.max_bytes for k, v in nmea.FDP_RATES.items()} == {1: 192, 3: 512, 5: 2048}


def _cst_v6(**kw: object) -> str:
    base: dict[str, object] = dict(version=6, mode=0, toa="20250101120000.250000", toa_mode=3, mfd=(120, 10, 100, 150),
                                   agn=0, shift=(0, 0, 0, 0), rate=5, src=2, dest=1, psk_error=0, ptype=3,
                                   nframes=8, nbad=0, rss=170, snr_in=12.5, snr_out=18.25, snr_sym=17.0,
                                   mse=-12.0, dqf=100, dop=-0.4, noise=70, carrier=10000, bw=2000)
    base.update(kw)
    f = [base["version"], base["mode"], base["toa"], base["toa_mode"], *base["mfd"], base["agn"],  # type: ignore[misc]
         *base["shift"], base["rate"], base["src"], base["dest"], base["psk_error"], base["ptype"],  # type: ignore[misc]
         base["nframes"], base["nbad"], base["rss"], base["snr_in"], base["snr_out"], base["snr_sym"],
         base["mse"], base["dqf"], base["dop"], base["noise"], base["carrier"], base["bw"]]
    return nmea.format_sentence("CACST", f).decode()


def test_cacst_version_6_7_8_and_micromodem1() -> None:
    v6 = nmea.parse_cacst(nmea.parse(_cst_v6()))
    assert len(nmea.parse(_cst_v6()).fields) == 30
    assert (v6.version, v6.mode, v6.rate, v6.src, v6.dest, v6.frames, v6.bad_frames) == (6, 0, 5, 2, 1, 8, 0)
    assert (v6.snr_in, v6.snr_out, v6.doppler, v6.carrier, v6.bandwidth) == (12.5, 18.25, -0.4, 10000, 2000)
    v7 = nmea.parse_cacst(nmea.parse(_cst_v6(version=7)))
    assert (v7.version, v7.snr_out) == (7, 18.25)
    s8 = nmea.parse(_cst_v6(version=8, mode=1, nbad=2, psk_error=3))
    s8 = nmea.Sentence(s8.talker, s8.kind, (*s8.fields, "17", "5", "8", "2"))
    v8 = nmea.parse_cacst(s8)
    assert (v8.version, v8.mode, v8.bad_frames, v8.psk_error) == (8, 1, 2, 3)
    assert v8.extra == {"seq": 17, "data_rate": 5, "data_frames": 8, "bad_data_frames": 2}
    # Micromodem-1: no VERSION field, HHMMSS.ss time
    mm1 = nmea.parse(_cst_v6())
    mm1 = nmea.Sentence("CA", "CST", ("0", "120000.25", *mm1.fields[3:]))
    v0 = nmea.parse_cacst(mm1)
    assert (v0.version, v0.mode, v0.toa, v0.rate, v0.frames, v0.snr_out) == (0, 0, "120000.25", 5, 8, 18.25)
    with pytest.raises(NmeaError, match="fields"):
        nmea.parse_cacst(nmea.Sentence("CA", "CST", tuple(nmea.parse(_cst_v6()).fields[:25])))


def test_formatted_cacst_and_caxst_parse_back() -> None:
    line = nmea.format_cacst(1735732800.5, mode=1, rate=1, src=2, dest=1, psk_error=3, packet_type=3,
                             frames=3, bad_frames=1, snr_in=9.0, snr_out=12.0, doppler=0.3)
    s = nmea.parse(line)
    assert len(s.fields) == 30
    cst = nmea.parse_cacst(s)
    assert (cst.version, cst.mode, cst.frames, cst.bad_frames, cst.snr_out, cst.doppler) == (6, 1, 3, 1, 12.0, 0.3)
    assert cst.toa == "20250101120000.500000"
    x = nmea.parse(nmea.format_caxst(1735732800.0, mode=0, rate=5, src=1, dest=2, ack=False, frames_expected=8,
                                     frames_sent=8, packet_type=3, nbytes=2048))
    assert len(x.fields) == 16
    xst = nmea.parse_caxst(x)
    assert (xst.version, xst.date, xst.mode, xst.rate, xst.frames_sent, xst.nbytes) == (6, "20250101", 0, 5, 8, 2048)
    mm1 = nmea.parse_caxst(nmea.Sentence("CA", "XST", x.fields[1:]))
    assert (mm1.version, mm1.date, mm1.rate, mm1.nbytes) == (0, "20250101", 5, 2048)


def test_cardp_goby_layout_with_per_frame_crc_flags() -> None:
    frames = [nmea.FdpFrame(True, 4, b"\x01\x02\x03\x04"), nmea.FdpFrame(False, 3, b""), nmea.FdpFrame(True, 1, b"\xff")]
    line = nmea.format_cardp(2, 1, 5, False, (), frames)
    assert line.startswith(b"$CARDP,2,1,5,0,0,,1;4;01020304;0;3;;1;1;ff*")
    rdp = nmea.parse_cardp(nmea.parse(line))
    assert (rdp.src, rdp.dest, rdp.rate, rdp.mini, rdp.data) == (2, 1, 5, (), tuple(frames))
    b64 = nmea.format_sentence("CARDP", [2, 1, 5, 0, 0, "", "1;3;" + base64.b64encode(b"abc").decode()])
    assert nmea.parse_cardp(nmea.parse(b64), base64data=True).data[0].data == b"abc"
    for bad in ("$CARDP,2,1,5,0,0,,1;4", "$CARDP,2,1,5,0,0,,2;1;ff", "$CARDP,2,1,5,0,0,,1;x;ff", "$CARDP,2,1,5,0,0,ff"):
        with pytest.raises(NmeaError):
            nmea.parse_cardp(nmea.parse(bad))


def test_line_splitter_handles_split_reads_garbage_and_overlong_lines() -> None:
    sp = nmea.LineSplitter(max_line=64)
    assert sp.feed(b"$CACFG,C") == []
    assert sp.pending() == 8
    assert sp.feed(b"ST,1*35\r\n\r\n$CAT") == [b"$CACFG,CST,1*35"]
    assert sp.feed(b"XF*41\rjunk$CATXP\n#M1$CACFG,A,1\n") == [b"$CATXF*41", b"$CATXP", b"$CACFG,A,1"]
    assert sp.garbage_bytes == len(b"junk") + len(b"#M1")
    assert sp.feed(b"\x00\x01 noise\r\n") == [b""]
    assert sp.feed(b"$" + b"A" * 100 + b"\r\n$CATXF\r\n") == [b"$CATXF"]
    assert sp.overlong == 1
    assert sp.pending() == 0
