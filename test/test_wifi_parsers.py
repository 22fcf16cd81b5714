"""WiFi ingestion core: iw / nmcli / JSON parsers on captured outputs, and normalisation."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from indoor_loc.errors import ConfigError, ParseError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.normalize import (NormalizeParams, band_of, canonical_bssid, is_locally_administered,
                                       normalize, normalize_report)
from indoor_loc.wifi.parsers import (channel_to_freq_mhz, format_json, iw_unescape_ssid, nmcli_split, parse,
                                     parse_iw, parse_json, parse_nmcli, quality_to_dbm)
from indoor_loc.wifi.types import WifiScan

DATA = Path(__file__).resolve().parent / "data" / "wifi"


def read(name: str) -> str:
    return (DATA / name).read_text(encoding="utf-8")


def rows(scan: WifiScan) -> list[tuple]:
    age = scan.age_ms if scan.age_ms is not None else [math.nan] * len(scan)
    return [(b, s, float(r), float(f), None if math.isnan(a) else float(a))
            for b, s, r, f, a in zip(scan.bssid, scan.ssid, scan.rssi_dbm, scan.freq_mhz, age)]


# ------------------------------------------------------------------------------------------------
# iw
# ------------------------------------------------------------------------------------------------
def test_iw_office_exact_values():
    r = parse_iw(read("iw_scan_office.txt"), stamp_ns=123)
    assert not r.truncated and r.skipped == 0 and r.warnings == ()
    assert r.scan.stamp_ns == 123 and r.scan.source == "iw"
    assert rows(r.scan) == [
        ("3c:37:86:5e:a1:10", "PUT-Staff", -48.0, 2412.0, 24.0),
        ("3c:37:86:5e:a1:14", "PUT-Staff", -61.0, 5180.0, 28.0),
        ("00:1a:2b:3c:4d:5e", "eduroam", -72.0, 2437.0, 112.0),
        ("00:1a:2b:3c:4d:5f", "", -80.0, 2462.0, 96.0),                  # hidden (empty SSID)
        ("da:a1:19:6b:22:01", "Pixel 7 hotspot", -66.0, 5745.0, 40.0),
        ("70:f0:96:d2:e0:62", "Café ☕", -83.0, 2437.0, 140.0),            # UTF-8 from \xNN escapes
    ]


def test_iw6_decimal_freq_6ghz_hidden_nuls_and_repeated_bssid():
    r = parse_iw(read("iw6_scan_6ghz.txt"))
    assert not r.truncated
    assert rows(r.scan) == [
        ("8c:3b:ad:10:20:30", "Lab6E", -67.0, 5955.0, 20.0),
        ("8c:3b:ad:10:20:31", "Lab6E", -74.0, 6115.0, 20.0),
        ("8c:3b:ad:10:20:3f", "Lab6E", -58.0, 5180.0, 36.0),
        ("8c:3b:ad:10:20:40", "", -90.0, 2412.0, 1020.0),               # \x00 x 8 = hidden
        ("8c:3b:ad:10:20:41", " lab\\guest ", -77.5, 2412.0, 31250.0),  # \x20 and \x5c escapes
        ("8c:3b:ad:10:20:30", "Lab6E", -71.0, 5955.0, 2510.0),
    ]
    rep = normalize_report(r.scan)
    assert rep.dropped == {"duplicate": 1}
    assert rep.scan.bssid.count("8c:3b:ad:10:20:30") == 1
    assert rep.scan.as_dict()["8c:3b:ad:10:20:30"] == -67.0          # the strongest of the two
    assert rep.scan.bssid[0] == "8c:3b:ad:10:20:30"                   # at its first position
    stale = normalize_report(r.scan, NormalizeParams(max_age_ms=30000.0))
    assert stale.dropped == {"duplicate": 1, "stale": 1}
    assert "8c:3b:ad:10:20:41" not in stale.scan.bssid
    six = normalize(r.scan, NormalizeParams(bands=["6"]))
    assert six.bssid == ("8c:3b:ad:10:20:30", "8c:3b:ad:10:20:31")


def test_iw_truncated_mid_line_keeps_complete_blocks():
    r = parse_iw(read("iw_scan_truncated.txt"))
    assert r.truncated
    assert any("00:1a:2b:3c:4d:5f" in w for w in r.warnings)
    assert rows(r.scan) == rows(parse_iw(read("iw_scan_office.txt")).scan)[:3]


def test_iw_truncated_at_a_line_boundary_before_the_ssid():
    lines = read("iw_scan_office.txt").splitlines(keepends=True)
    second = [i for i, s in enumerate(lines) if s.startswith("BSS ")][1]
    text = "".join(lines[: second + 6])          # block 2 has freq and signal but no SSID line yet
    r = parse_iw(text)
    assert r.truncated and r.scan.bssid == ("3c:37:86:5e:a1:10",)


def test_iw_every_cut_keeps_a_prefix_of_the_entries():
    """Property: wherever the output is cut, the parser returns the complete entries before the cut
    (a prefix of the full parse) and flags a mid-line cut, or raises ParseError; nothing else."""
    for name in ("iw_scan_office.txt", "iw6_scan_6ghz.txt"):
        text = read(name)
        full = rows(parse_iw(text).scan)
        for cut in range(0, len(text), 23):
            try:
                r = parse_iw(text[:cut])
            except ParseError:
                continue
            got = rows(r.scan)
            assert got == full[: len(got)], (name, cut)
            # a cut exactly at a line boundary after a block's SSID line cannot be told from the end
            assert r.truncated or len(got) == len(full) or text[:cut].endswith("\n") or cut == 0, (name, cut)


def test_iw_percent_signal_missing_fields_and_garbage():
    text = ("BSS 00:11:22:33:44:55(on wlan0)\n\tfreq: 2412\n\tsignal: 70/100\n\tSSID: a\n"
            "BSS 00:11:22:33:44:56(on wlan0)\n\tfreq: 2417\n\tSSID: no-signal\n"
            "BSS 00:11:22:33:44:57(on wlan0)\n\tfreq: 2422\n\tsignal: -60.00 dBm\n\tSSID: c\n")
    r = parse_iw(text)
    assert r.scan.bssid == ("00:11:22:33:44:55", "00:11:22:33:44:57")
    assert r.scan.rssi_dbm.tolist() == [quality_to_dbm(70), -60.0] == [-58.0, -60.0]
    assert r.skipped == 1 and not r.truncated and r.scan.age_ms is None
    assert len(parse_iw("").scan) == 0 and len(parse_iw("\n\n").scan) == 0
    with pytest.raises(ParseError, match="no 'BSS"):
        parse_iw("command failed: Operation not permitted (-1)\n")
    with pytest.raises(ParseError, match="no 'BSS"):
        parse_iw(read("nmcli_terse.txt"))


def test_iw_ssid_unescape():
    assert iw_unescape_ssid(r"Caf\xc3\xa9") == "Café"
    assert iw_unescape_ssid(r"\x00\x00\x00") == ""
    assert iw_unescape_ssid(r"bad\xff") == "bad\ufffd"
    assert iw_unescape_ssid("plain") == "plain"


# ------------------------------------------------------------------------------------------------
# nmcli
# ------------------------------------------------------------------------------------------------
NMCLI_EXPECTED = [
    ("3C:37:86:5E:A1:10", "PUT-Staff", -47.8, 2412.0, None),
    ("3C:37:86:5E:A1:14", "PUT-Staff", -61.0, 5180.0, None),
    ("00:1A:2B:3C:4D:5E", "eduroam", -71.8, 2437.0, None),
    ("00:1A:2B:3C:4D:5F", "", -82.0, 2462.0, None),
    ("DA:A1:19:6B:22:01", "Pixel 7 hotspot", -65.8, 5745.0, None),
    ("70:F0:96:D2:E0:62", "Guest:Lobby", -83.8, 2437.0, None),
    ("8C:3B:AD:10:20:30", "Lab6E", -67.0, 5955.0, None),
    ("8C:3B:AD:10:20:41", "lab\\guest", -77.2, 2412.0, None),
]


@pytest.mark.parametrize("name", ["nmcli_terse.txt", "nmcli_terse_ru.txt", "nmcli_terse_decimal_comma.txt",
                                  "nmcli_multiline_terse.txt", "nmcli_multiline_pretty.txt"])
def test_nmcli_variants_exact_values(name):
    r = parse_nmcli(read(name))
    assert not r.truncated and r.skipped == 0
    assert rows(r.scan) == NMCLI_EXPECTED
    clean = normalize(r.scan)
    assert "da:a1:19:6b:22:01" not in clean.bssid and "3c:37:86:5e:a1:10" in clean.bssid


def test_nmcli_truncated():
    r = parse_nmcli(read("nmcli_terse_truncated.txt"))
    assert r.truncated and r.warnings
    assert rows(r.scan) == NMCLI_EXPECTED[:6]


def test_nmcli_every_cut_keeps_a_prefix():
    for name in ("nmcli_terse.txt", "nmcli_multiline_terse.txt"):
        text = read(name)
        for cut in range(1, len(text), 7):
            try:
                got = rows(parse_nmcli(text[:cut]).scan)
            except ParseError:
                continue
            assert got == NMCLI_EXPECTED[: len(got)], (name, cut)


def test_nmcli_fields_order_channel_fallback_and_errors():
    r = parse_nmcli("MyNet:AA\\:BB\\:CC\\:DD\\:EE\\:01:100:36\n", fields=["SSID", "BSSID", "SIGNAL", "CHAN"])
    assert rows(r.scan) == [("AA:BB:CC:DD:EE:01", "MyNet", -40.0, 5180.0, None)]
    assert any("CHAN" in w for w in r.warnings)
    with pytest.raises(ParseError, match="expected 5"):
        parse_nmcli("a:b:c\nd:e:f\n")
    pretty_table = ("IN-USE  BSSID              SSID       MODE   CHAN  RATE        SIGNAL  BARS  SECURITY\n"
                    "*       3C:37:86:5E:A1:10  PUT-Staff  Infra  1     130 Mbit/s  87      ▂▄▆█  WPA2\n")
    with pytest.raises(ParseError, match="-t"):
        parse_nmcli(pretty_table)
    with pytest.raises(ParseError, match="lacks SIGNAL"):
        parse_nmcli("x\n", fields=["BSSID", "SSID"])
    with pytest.raises(ParseError, match="no record could be read|none of"):
        parse_nmcli("AA\\:BB\\:CC\\:DD\\:EE\\:01:x:2412 MHz:strong:1\n")
    assert nmcli_split(r"a\:b:c\\:d") == ["a:b", "c\\", "d"]


def test_quality_mapping_inverts_networkmanager():
    """Oracle: NetworkManager's nm_wifi_utils_level_to_quality() (clamp to [-100, -40] dBm, scale
    over 60 dB); our inverse must return each dBm within the 0.6 dB quantisation step."""
    def nm_level_to_quality(dbm: int) -> int:
        v = abs(min(max(dbm, -100), -40) + 40)
        return max(0, min(100, 100 - int(100.0 * v / 60.0)))
    for dbm in range(-100, -39):
        assert abs(quality_to_dbm(nm_level_to_quality(dbm)) - dbm) <= 0.6 + 1e-9
    assert quality_to_dbm(0, "half") == -100.0 and quality_to_dbm(100, "half") == -50.0
    assert quality_to_dbm(150) == -40.0 and quality_to_dbm(-5) == -100.0
    with pytest.raises(ParseError, match="mapping"):
        quality_to_dbm(50, "linear")


def test_channels_and_bands():
    assert [channel_to_freq_mhz(c) for c in (1, 6, 13, 14, 36, 149, 165)] == \
        [2412.0, 2437.0, 2472.0, 2484.0, 5180.0, 5745.0, 5825.0]
    assert [channel_to_freq_mhz(c, "6") for c in (1, 2, 33, 233)] == [5955.0, 5935.0, 6115.0, 7115.0]
    assert channel_to_freq_mhz(20) == 0.0
    assert [band_of(f) for f in (2412, 5180, 5895, 5955, 7115, 0, 60480)] == ["2.4", "5", "5", "6", "6", "", ""]


# ------------------------------------------------------------------------------------------------
# JSON
# ------------------------------------------------------------------------------------------------
def test_json_cabot_iw_converter():
    r = parse_json(read("cabot_iw.json"), stamp_ns=5)
    assert r.scan.stamp_ns == 1_700_000_123_250_000_000            # "timestamp" in seconds
    assert rows(r.scan) == [
        ("3c:37:86:5e:a1:10", "PUT-Staff", -48.0, 2412.0, 24.0),
        ("3c:37:86:5e:a1:14", "PUT-Staff", -61.0, 5180.0, 28.0),
        ("00:1a:2b:3c:4d:5f", "", -80.0, 2462.0, 96.0),
        ("8c:3b:ad:10:20:30", "Lab6E", -67.0, 5955.0, 20.0),
    ]


def test_json_cabot_esp32_channels_and_repeats():
    r = parse_json(read("cabot_esp32.json"))
    assert r.scan.stamp_ns == 1_700_000_200_500_000_000
    assert rows(r.scan) == [("00:1A:2B:3C:4D:5E", "eduroam", -71.0, 2437.0, None),
                            ("3C:37:86:5E:A1:10", "PUT-Staff", -52.0, 2412.0, None),
                            ("00:1A:2B:3C:4D:5E", "eduroam", -69.0, 2437.0, None)]
    clean = normalize_report(r.scan)
    assert clean.dropped == {"duplicate": 1}
    assert clean.scan.as_dict() == {"00:1a:2b:3c:4d:5e": -69.0, "3c:37:86:5e:a1:10": -52.0}


def test_json_variants():
    r = parse_json(read("variants_list.json"), stamp_ns=77)
    assert r.scan.stamp_ns == 77 and r.skipped == 2 and len(r.warnings) == 2    # BLE entry ignored silently
    assert rows(r.scan) == [("3C-37-86-5E-A1-14", "PUT-Staff", -63.0, 5180.0, None),
                            ("70:f0:96:d2:e0:62", "Café ☕", -70.0, 2437.0, None),
                            ("8c:3b:ad:10:20:31", "Lab6E", -74.5, 6115.0, None)]
    assert normalize(r.scan).bssid[0] == "3c:37:86:5e:a1:14"


def test_json_errors():
    text = read("cabot_iw.json")
    with pytest.raises(ParseError, match="truncated"):
        parse_json(text[: len(text) // 2])
    with pytest.raises(ParseError, match="no list of access points"):
        parse_json('{"type": "rssi", "timestamp": 1}')
    with pytest.raises(ParseError, match="none of 2"):
        parse_json('[{"ssid": "x"}, 3]')
    with pytest.raises(ParseError, match="object or a list"):
        parse_json("42")
    with pytest.raises(ParseError, match="unknown scan format"):
        parse("", "iwlist")
    assert len(parse_json('{"data": []}').scan) == 0


def test_json_round_trip(rng):
    n = 12
    hexs = rng.integers(0, 256, size=(n, 6))
    scan = WifiScan(stamp_ns=1_700_000_000_123_456_789,
                    bssid=tuple(":".join(f"{x:02x}" for x in h) for h in hexs),
                    rssi_dbm=np.round(rng.uniform(-100, -30, n), 2), freq_mhz=rng.choice([2412., 5180., 5955.], n),
                    ssid=tuple(f"net:{i} ☕\\" if i % 3 else "" for i in range(n)),
                    age_ms=rng.integers(0, 5000, n).astype(float), frame_id="alice/wifi_link", source="iw")
    back = parse_json(format_json(scan)).scan
    assert rows(back) == rows(scan)
    assert (back.stamp_ns, back.frame_id, back.source) == (scan.stamp_ns, scan.frame_id, scan.source)


# ------------------------------------------------------------------------------------------------
# normalisation
# ------------------------------------------------------------------------------------------------
def _scan(entries, age=None) -> WifiScan:
    return WifiScan(stamp_ns=1, bssid=tuple(e[0] for e in entries), rssi_dbm=np.array([e[1] for e in entries]),
                    freq_mhz=np.array([e[2] for e in entries]), ssid=tuple(e[3] for e in entries),
                    age_ms=None if age is None else np.array(age, dtype=float), frame_id="f", source="s")


def test_normalize_reasons_and_counts():
    raw = _scan([("00:1B:CC:00:00:01", -50.0, 2412.0, "a"),
                 ("00-1b-cc-00-00-02", -130.0, 2412.0, "b"),        # below the contract's range
                 ("001b.cc00.0003", 3.0, 2412.0, "c"),               # positive RSSI
                 ("00:1b:cc:00:00:04", math.nan, 2412.0, "d"),
                 ("not-a-mac", -40.0, 2412.0, "e"),
                 ("02:00:00:00:00:05", -45.0, 5180.0, "hotspot"),    # locally administered
                 ("00:1B:CC:00:00:01", -40.0, 5180.0, "a"),          # same BSSID, stronger
                 ("00:1b:cc:00:00:06", -95.0, 2437.0, "weak"),
                 ("00:1b:cc:00:00:07", -60.0, -5.0, "badf"),
                 ("00:1b:cc:00:00:08", -60.0, 2437.0, "x\x00")])
    rep = normalize_report(raw, NormalizeParams(min_rssi_dbm=-90.0))
    assert rep.dropped == {"rssi_range": 2, "nan": 1, "bad_bssid": 1, "random_mac": 1, "duplicate": 1,
                           "weak": 1, "bad_frequency": 1}
    assert rep.n_in == 10 and len(rep.scan) + rep.n_dropped == rep.n_in
    assert rows(rep.scan) == [("00:1b:cc:00:00:01", "a", -40.0, 5180.0, None),
                              ("00:1b:cc:00:00:08", "x", -60.0, 2437.0, None)]
    assert (rep.scan.stamp_ns, rep.scan.frame_id, rep.scan.source) == (1, "f", "s")
    keep = normalize(raw, NormalizeParams(keep_random_macs=True, min_rssi_dbm=-90.0))
    assert "02:00:00:00:00:05" in keep.bssid
    assert canonical_bssid("001b.cc00.0003") == "00:1b:cc:00:00:03" and canonical_bssid("00:1b:cc:0:0:1") is None
    assert is_locally_administered("da:a1:19:6b:22:01") and not is_locally_administered("8c:3b:ad:10:20:30")


def test_normalize_allow_and_deny_lists():
    raw = parse_iw(read("iw_scan_office.txt")).scan
    p = lambda **kw: params_from_dict(NormalizeParams, kw)                      # noqa: E731
    assert normalize(raw, p(ssid_allow=["PUT-*"])).bssid == ("3c:37:86:5e:a1:10", "3c:37:86:5e:a1:14")
    assert normalize_report(raw, p(ssid_allow=["PUT-*"])).dropped == {"random_mac": 1, "ssid_not_allowed": 3}
    assert "00:1a:2b:3c:4d:5e" not in normalize(raw, p(ssid_deny=["edu*"])).bssid
    assert normalize(raw, p(ssid_allow=["put-*"])).bssid == ()                  # SSIDs are case-sensitive
    only = normalize(raw, p(bssid_allow=["3C:37:86:*"]))                        # BSSIDs are not
    assert only.bssid == ("3c:37:86:5e:a1:10", "3c:37:86:5e:a1:14")
    rep = normalize_report(raw, p(bssid_allow=["3c:37:86:*"], bssid_deny=["*:14"]))
    assert rep.scan.bssid == ("3c:37:86:5e:a1:10",) and rep.dropped["bssid_deny"] == 1
    assert normalize(raw, p(bands=["5"], keep_random_macs=True)).bssid == ("3c:37:86:5e:a1:14", "da:a1:19:6b:22:01")


def test_normalize_params_validation():
    with pytest.raises(ConfigError, match="bands"):
        params_from_dict(NormalizeParams, {"bands": ["3"]})
    with pytest.raises(ConfigError, match="min_rssi_dbm"):
        params_from_dict(NormalizeParams, {"min_rssi_dbm": 10.0})
    with pytest.raises(ConfigError, match="max_age_ms"):
        params_from_dict(NormalizeParams, {"max_age_ms": -1.0})
    with pytest.raises(ConfigError, match="unknown"):
        params_from_dict(NormalizeParams, {"min_rssi": -90.0})


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["00:11:22:33:44:55", "00:11:22:33:44:66", "0A:11:22:33:44:77",
                                           "00:11:22:33:44:88", "junk"]),
                          st.one_of(st.floats(-150, 20), st.just(math.nan)), st.sampled_from([2412.0, 5180.0, 5955.0, 0.0]),
                          st.text(max_size=4)), max_size=15))
def test_normalize_invariants(entries):
    """Property: unique lower-case BSSIDs, RSSI in range, counts add up, idempotent."""
    raw = _scan(entries)
    rep = normalize_report(raw)
    out = rep.scan
    assert len(set(out.bssid)) == len(out.bssid)
    assert all(b == b.lower() and canonical_bssid(b) == b for b in out.bssid)
    assert np.all((out.rssi_dbm >= -120) & (out.rssi_dbm <= 0))
    assert len(out) + rep.n_dropped == len(entries)
    again = normalize_report(out)
    assert again.dropped == {} and rows(again.scan) == rows(out)


@settings(max_examples=80, deadline=None)
@given(st.text(max_size=300), st.sampled_from(["iw", "nmcli", "json"]))
def test_parsers_never_raise_anything_but_parse_error(text, fmt):
    try:
        r = parse(text, fmt)
    except ParseError:
        return
    assert len(r.scan.bssid) == len(r.scan.rssi_dbm) == len(r.scan.freq_mhz)
