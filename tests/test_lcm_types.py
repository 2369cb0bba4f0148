"""LCM bindings: generated types are current, the frame_t codec is strict, product conversions."""

from __future__ import annotations

import dataclasses
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from coex_conformance import load_vectors
from coex_core import jsonfmt, wire
from coex_core.errors import DecodeError, EncodeError
from coex_core.messages import FrameHeader, Subgrid, VehicleMode, VehicleStatus
from coex_transports.lcm import (
    FRAME_T_FINGERPRINT,
    FRAME_T_OVERHEAD,
    decode_frame,
    encode_frame,
    frame_t,
    is_frame_t,
    map_level_t,
    regen,
    unpack_event,
    vehicle_status_t,
)
from coex_transports.lcm.products import (
    MapLevelSummary,
    vehicle_status_from_lcm,
    vehicle_status_to_lcm,
)

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ generated code is current
def test_generated_types_are_not_stale() -> None:
    """Regenerate with the wheel's lcm-gen into a temp dir; the committed _types/ must match."""
    assert regen.BINDINGS_DIR == ROOT / "spec" / "bindings"
    assert regen.stale_files() == []


def test_stale_check_detects_a_changed_binding(tmp_path: Path) -> None:
    bindings = tmp_path / "bindings"
    bindings.mkdir()
    text = (regen.BINDINGS_DIR / "coex.lcm").read_text()
    (bindings / "coex.lcm").write_text(text.replace("int64_t origin;", "int64_t origin;\n    int8_t extra;"))
    assert regen.stale_files(regen.TYPES_DIR, bindings) == ["frame_t.py", "frame_t.pyi"]
    # and the script's --check exits 1 on it, 0 on the real bindings
    script = regen.__file__
    bad = subprocess.run([sys.executable, script, "--check", "--bindings", str(bindings)],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "frame_t.py" in bad.stderr
    good = subprocess.run([sys.executable, script, "--check"], capture_output=True, text=True, timeout=60)
    assert good.returncode == 0, good.stderr


def test_regen_writes_an_importable_package(tmp_path: Path) -> None:
    out = tmp_path / "types"
    names = regen.write(out)
    types = ["frame_t", "map_level_t", "nav_t", "points_t", "survey_request_t", "survey_state_t",
             "vehicle_status_t"]
    assert names == sorted(["__init__.py", *(f"{t}.py" for t in types), *(f"{t}.pyi" for t in types)])
    assert regen.stale_files(out) == []
    assert "import coex" not in (out / "frame_t.py").read_text()  # flat types: no absolute imports
    (out / "nav_t.pyi").write_text((out / "nav_t.pyi").read_text().replace("x: float", "x: int"))
    assert regen.stale_files(out) == ["nav_t.pyi"]  # a stub edited by hand is stale


def test_stubs_type_every_field_as_lcm_gen_holds_it() -> None:
    """The typing stub of a made-up lcm-gen class: primitives, a byte array as bytes, numeric and
    string arrays as sequences (one per dimension), a nested type by its class name."""
    source = (
        "class demo_t(object):\n"
        "    __slots__ = ['utime', 'ok', 'name', 'blob', 'xs', 'grid', 'tags', 'inner']\n"
        "    __typenames__ = ['int64_t', 'boolean', 'string', 'byte', 'double', 'float', 'string',"
        " 'coex.nav_t']\n"
        "    __dimensions__ = [None, None, None, ['n'], ['n'], [3, 'm'], ['k'], None]\n"
    )
    text = regen.stub(source)
    body = [line.strip() for line in text.splitlines()]
    for field in ("utime: int", "ok: bool", "name: str", "blob: bytes", "xs: Sequence[float]",
                  "grid: Sequence[Sequence[float]]", "tags: Sequence[str]", "inner: nav_t",
                  "def encode(self) -> bytes: ...", "def decode(data: bytes | BinaryIO) -> demo_t: ..."):
        assert field in body, field
    committed = (regen.TYPES_DIR / "frame_t.pyi").read_text()
    assert "from .nav_t import nav_t" in body
    assert "data: bytes" in committed and "length: int" in committed


def test_lcm_gen_is_the_wheel_binary() -> None:
    import lcm

    assert Path(regen.find_lcm_gen()).parent == Path(lcm.LCM_BIN_DIR)


# ------------------------------------------------------------------ frame_t codec
def test_frame_t_layout_is_the_documented_one() -> None:
    data = encode_frame(b"\x01\x02\x03", utime=1_700_000_000_000_000, origin=42)
    assert data[:8] == FRAME_T_FINGERPRINT
    assert struct.unpack(">qqi", data[8:28]) == (1_700_000_000_000_000, 42, 3)
    assert data[28:] == b"\x01\x02\x03"
    assert len(data) == FRAME_T_OVERHEAD + 3
    # the generated class reads what we write, and we read what it writes
    msg = frame_t.decode(data)
    assert (msg.utime, msg.origin, msg.length, msg.data) == (1_700_000_000_000_000, 42, 3, b"\x01\x02\x03")
    back = decode_frame(msg.encode())
    assert (back.utime, back.origin, back.data) == (1_700_000_000_000_000, 42, b"\x01\x02\x03")


@given(st.binary(max_size=600), st.integers(-(2**63), 2**63 - 1), st.integers(-(2**63), 2**63 - 1))
def test_frame_t_round_trip(frame: bytes, utime: int, origin: int) -> None:
    got = decode_frame(encode_frame(frame, utime=utime, origin=origin))
    assert (got.data, got.utime, got.origin) == (frame, utime, origin)


def test_encode_frame_refuses_bad_input() -> None:
    with pytest.raises(TypeError):
        encode_frame("text")  # type: ignore[arg-type]
    with pytest.raises(EncodeError):
        encode_frame(b"x", utime=2**63)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "shorter"),
        (FRAME_T_FINGERPRINT + bytes(19), "shorter"),
        (bytes(8) + bytes(20), "fingerprint"),
        (FRAME_T_FINGERPRINT + struct.pack(">qqi", 0, 0, -1) + b"abc", "negative"),
        (FRAME_T_FINGERPRINT + struct.pack(">qqi", 0, 0, 5) + b"abc", "disagrees"),
        (FRAME_T_FINGERPRINT + struct.pack(">qqi", 0, 0, 2) + b"abc", "disagrees"),
    ],
)
def test_decode_frame_refuses_malformed(data: bytes, reason: str) -> None:
    """The generated decode would accept some of these (read(-1), short reads, trailing bytes)."""
    with pytest.raises(DecodeError, match=reason):
        decode_frame(data)


def test_decode_frame_refuses_non_bytes() -> None:
    with pytest.raises(DecodeError):
        decode_frame(12)  # type: ignore[arg-type]


def test_is_frame_t() -> None:
    assert is_frame_t(encode_frame(b"a"))
    assert not is_frame_t(vehicle_status_to_lcm(_status()).encode())


@given(st.binary(max_size=120))
def test_receive_path_raises_only_decode_error(noise: bytes) -> None:
    for data in (noise, FRAME_T_FINGERPRINT + noise, encode_frame(noise)):
        try:
            unpack_event(data)
        except DecodeError:
            pass


def test_unpack_event_gives_the_coex_frame() -> None:
    status = _status()
    header = FrameHeader(src=1, dst=0, seq=7, crc=True)
    packet = wire.pack([status], 64, header)
    lcm_frame, frame = unpack_event(encode_frame(packet, utime=5, origin=9))
    assert lcm_frame.data == packet and lcm_frame.utime == 5
    assert frame.header == header
    assert frame.messages == (status,)


# ------------------------------------------------------------------ decoded product types
def _status(altitude: float | None = 12.5) -> VehicleStatus:
    return VehicleStatus(stamp=4000, x=-120.5, y=33.0, depth=2503.7, altitude=altitude, heading=87.5,
                         speed=1.2, battery=77, mode=VehicleMode.SURVEY, faults=3)


@pytest.mark.parametrize("altitude", [12.5, None])
def test_vehicle_status_round_trip(altitude: float | None) -> None:
    status = _status(altitude)
    msg = vehicle_status_to_lcm(status, utime=123)
    decoded = vehicle_status_t.decode(msg.encode())
    assert decoded.mode_name == "SURVEY" and decoded.utime == 123
    assert decoded.has_altitude is (altitude is not None)
    assert vehicle_status_from_lcm(decoded) == status


def test_vehicle_status_vectors_round_trip() -> None:
    for vector in load_vectors("messages"):
        if vector["type"] != "VehicleStatus":
            continue
        status = jsonfmt.from_json({"type": "VehicleStatus", **vector["fields"]})
        assert vehicle_status_from_lcm(vehicle_status_t.decode(vehicle_status_to_lcm(status).encode())) == status


def _subgrid() -> Subgrid:
    vector = next(v for v in load_vectors("messages") if v["type"] == "Subgrid")
    sub = jsonfmt.from_json({"type": "Subgrid", **vector["fields"]})
    assert isinstance(sub, Subgrid)
    return sub


def test_map_level_summary() -> None:
    base = dataclasses.replace(_subgrid(), level=1, resolution=1.0, side=8, mask=None, stamp=10)
    z = {(0, 0): -10.0, (1, 0): -12.0, (0, 2): -9.0}
    summary = MapLevelSummary(decoder=lambda s: [z[(s.ix, s.iy)], math.nan])
    for (ix, iy) in z:
        summary.add(dataclasses.replace(base, ix=ix, iy=iy, stamp=10 + ix + iy))
    summary.add(dataclasses.replace(base, ix=0, iy=0, stamp=50, mask=(1 << 63) | 1))  # newer, 2 cells
    summary.add(dataclasses.replace(base, level=0, ix=-1, iy=-1))
    assert summary.levels() == [0, 1]
    level1 = map_level_t.decode(summary.summary(1, utime=7).encode())
    assert (level1.utime, level1.level, level1.resolution) == (7, 1, 2.0)
    assert level1.subgrids == 3 and level1.cells == 2 + 64 + 64
    assert (level1.x_min, level1.x_max, level1.y_min, level1.y_max) == (0.0, 32.0, 0.0, 48.0)
    assert (level1.z_min, level1.z_max) == (-12.0, -9.0)
    assert level1.newest_stamp == 50
    level0 = summary.summary(0)
    assert (level0.x_min, level0.x_max, level0.resolution) == (-8.0, 0.0, 1.0)
    assert len(summary.summaries()) == 2


def test_map_level_summary_without_depths() -> None:
    def broken(_s: Subgrid) -> list[float]:
        raise ValueError("undecodable")

    summary = MapLevelSummary(decoder=broken)
    summary.add(_subgrid())
    out = summary.summary(_subgrid().level)
    assert math.isnan(out.z_min) and math.isnan(out.z_max) and out.subgrids == 1


def test_map_level_summary_finds_the_bathymetry_decoder_through_the_registry() -> None:
    """The transport never imports the bathymetry plugin; with it installed, the default
    summary still has depths (the plugin's decoder, reached through its entry point)."""
    from coex_plugins.bathymetry import decode_subgrid

    sub = _subgrid()
    summary = MapLevelSummary()
    summary.add(sub)
    out = summary.summary(sub.level)
    z = np.asarray(decode_subgrid(sub), float)
    assert (out.z_min, out.z_max) == (float(np.nanmin(z)), float(np.nanmax(z)))
