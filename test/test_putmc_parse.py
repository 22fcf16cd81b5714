"""PUTMC table parsing: the compiled reader gives the same arrays, bit for bit, as the line-by-line
reference parser, on hand-made edge cases and on real files, and the same errors on bad input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import dataset

from indoor_loc.datasets import putmc as P
from indoor_loc.errors import DatasetError


def _outcome(fn):
    try:
        return fn()
    except DatasetError as err:
        return str(err)


def _assert_same(tmp_path: Path, text: str, ncols: int) -> None:
    path = tmp_path / "table.map"
    path.write_bytes(text.encode("utf-8"))
    fast = _outcome(lambda: P.read_table(path, ncols))
    ref = _outcome(lambda: P.parse_table_lines(path.read_text(), ncols, path))
    if isinstance(ref, str):
        assert fast == ref, repr(text)
        return
    assert not isinstance(fast, str), f"{text!r}: {fast}"
    for a, b in zip(fast, ref):
        assert a.dtype == b.dtype and a.shape == b.shape, repr(text)
        assert a.tobytes() == b.tobytes(), repr(text)


EDGE_CASES = [
    "1 0.9073181 2.792282 9.2113495\n2 -0.043036975 1e-5 -0.0\n",
    "1 2 3 4",                                   # no final newline
    "1 2 3 4\n\n   \n\t\n5 6 7 8\n",                # blank and whitespace-only lines
    "1 2 3 4\r\n5 6 7 8\r\n",                      # CRLF
    "1 2 3 4\r5 6 7 8\r",                          # CR only
    "1 2\v3 4\n",                                  # vertical tab: a line break for str.splitlines
    "1 2 3 4\f5 6 7 8\n", "1 2 3 4\x1c5 6 7 8\n",
    "  1\t2   3 4  \n",                            # mixed separators
    "1 2 3\n", "1 2 3 4 5\n", "1 2 3 4\n5 6 7\n",  # wrong column counts
    "1.0 2 3 4\n", "1e3 2 3 4\n", "1_0 2 3 4\n",   # stamps that are not plain integers
    "+1 .5 5. 1E3\n", "-7 +0.25 -.5 1.5e-7\n",
    "1 2_0 3 4\n", "1 0x10 3 4\n", "1 2, 3 4\n", "1 2 3 4 # note\n",
    "1 nan 3 4\n", "1 inf 3 4\n", "1 1e400 3 4\n",  # non-finite values
    "99999999999999999999 2 3 4\n",              # stamp beyond int64
    "1 \u0663 3 4\n", "1\u00a02 3 4\n", "1 2 3 4\u2028",   # non-ASCII digits, spaces, line breaks
    "1 0.1000000000000000055511151231257827 2.2250738585072011e-308 4.9e-324\n",
    "", "\n\n", "   \n",
]


@pytest.mark.parametrize("text", EDGE_CASES)
def test_edge_cases_match_the_reference_parser(tmp_path, text):
    _assert_same(tmp_path, text, 4)


def test_random_numbers_round_trip_bit_for_bit(tmp_path):
    rng = np.random.default_rng(7)
    x = rng.normal(0, 10, (500, 5)) * 10.0 ** rng.integers(-12, 12, (500, 5))
    t = np.cumsum(rng.integers(1, 10**7, 500)) + 352112530908
    fmts = ["{!r}", "{:.9g}", "{:.17g}", "{:.3e}"]
    lines = [f"{ti} " + " ".join(fmts[(i + j) % 4].format(v) for j, v in enumerate(row.tolist()))
             for i, (ti, row) in enumerate(zip(t, x))]
    _assert_same(tmp_path, "\n".join(lines) + "\n", 6)
    stamps, values = P.read_table(tmp_path / "table.map", 6)
    assert stamps.tolist() == t.tolist()
    np.testing.assert_array_equal(values[::4, 0], x[::4, 0])      # the repr-formatted ones round-trip exactly


def test_real_files_match_the_reference_parser(tmp_path):
    root = dataset("putmc")
    folder = P.walk_folders(root)[16]
    for name, ncols in (("acc.map", 4), ("orient.map", 6), ("positions.map", 3)):
        text = (folder / name).read_text()
        _assert_same(tmp_path, text, ncols)
    _assert_same(tmp_path, (root / P.MAP_DIR / "positions.map").read_text(), 3)


def test_well_formed_files_take_the_compiled_path(tmp_path, monkeypatch):
    path = tmp_path / "acc.map"
    path.write_text("1 0.9073181 2.792282 9.2113495\n2 0.93640137 2.8675385 9.338776\n")
    expected = P.parse_table_lines(path.read_text(), 4, path)

    def refuse(*_args, **_kw):
        raise AssertionError("fell back to the line-by-line parser")

    monkeypatch.setattr(P, "parse_table_lines", refuse)
    stamps, values = P.read_table(path, 4)
    assert stamps.tobytes() == expected[0].tobytes() and values.tobytes() == expected[1].tobytes()


def test_walk_events_two_chunk_feed_matches_one_call():
    """walk_events feeds the stepometer in two chunks (cheaper); the hops are those of one call."""
    from indoor_loc.backend.putmc_events import walk_events
    from indoor_loc.imu.stepometer import Stepometer

    ds = P.Putmc(dataset("putmc"))
    w = ds.walk(16)
    sm = Stepometer()
    hops = sm.update_many(w.acc_t, w.acc) + sm.finish()
    ev = walk_events(w)
    assert len(hops) > 10
    assert ev.t_start.tolist() == [h.t_start_ns for h in hops]
    assert ev.t_end.tolist() == [h.t_end_ns for h in hops]
    assert ev.steps.tolist() == [float(h.steps) for h in hops]
