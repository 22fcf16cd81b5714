"""Numeric table parsing (PUTMC's sensor files): the compiled reader gives the same arrays, bit for bit, as the line-by-line
reference parser, on hand-made edge cases and on real files, and the same errors on bad input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import dataset

from indoor_loc.datasets import putmc as P
from indoor_loc.datasets import text_table as T
from indoor_loc.errors import DatasetError


def _outcome(fn):
    try:
        return fn()
    except DatasetError as err:
        return str(err)


def _assert_same(tmp_path: Path, text: str, ncols: int) -> None:
    path = tmp_path / "table.map"
    path.write_bytes(text.encode("utf-8"))
    fast = _outcome(lambda: T.read_table(path, ncols))
    ref = _outcome(lambda: T.parse_table_lines(path.read_text(), ncols, path))
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
    # the decimal fast path's borders: Java exponents, signs, points, 2**53, 10**±22, field widths
    "1 8.8500977E-4 -2.746582E-4 1.5E3\n2 -0.0 -0 0.0\n", "1 -.5 .5 5.\n", "-5 1 2 3\n",
    "1 2 3 -\n", "1 2 3 5E-\n", "1 2 3 -.\n", "1 -. 3 4\n", "1 . 3 4\n", "1 1.2.3 3 4\n",
    "1E3 2 3 4\n", "1 1.5E3.2 3 4\n", "1 15E3.2 3 4\n", "1 6E-1.5 3 4\n", "1 1E5E6 3 4\n", "1 -E5 3 4\n",
    "1 E5 3 4\n", "1 5E 3 4\n",
    "1 --5 3 4\n", "1 5- 3 4\n", "1 1-2 3 4\n", "1 2 - 4\n", "1 2 3 4\n- 2 3 4\n",
    "1 9007199254740992 9007199254740993 -9007199254740993\n", "1 0.9007199254740993 3 4\n",
    "1 1E22 1E-22 1.5E21\n", "1 1E23 1E-23 0.0000000000000000000001\n", "1 2E-0000000004 3 4\n",
    "123456789012345678 2 3 4\n", "1234567890123456789 2 3 4\n", "-123456789012345678 2 3 4\n",
    "1 2 3 4 \n", "1 2 3 4\n\n\n", "1 2  3 4\n", "1 2 3 4\n 5 6 7 8\n", "1 2 3\n4\n",
    # one point per value: the i-th point must lie in the i-th value field
    "1 2.5 3 4.5\n2 1.2.3 6.5 7.5\n", "1 2.5.5 3 4.5\n", "1.5 2.5 3 4.5\n", "1 2\n3 4\n5 6.5 7.5 8.5\n",
    "1 .-5 3 4\n", "1 .+5 3 4\n", "1 +.5 3 4\n", "1 -0.0 0.0 -0E3\n", "1 5.E3 .5E-3 -.5E1\n",
    "1 2 3 -\n5 6 7 8\n", "1 2 3 5E-\n5 6 7 8\n", "1 2 3 4\n5 6 7 -\n",    # a sign ending a line
    "1 2 3 4\n99999999999999999999 2 3 4\n", "1 2 3 4\n-9999999999999999999 2 3 4\n",   # wide fields
    "1 2 3 4\n5 0.1234567890123456789012 3 4\n",
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
    stamps, values = T.read_table(tmp_path / "table.map", 6)
    assert stamps.tolist() == t.tolist()
    np.testing.assert_array_equal(values[::4, 0], x[::4, 0])      # the repr-formatted ones round-trip exactly


def test_real_files_match_the_reference_parser(tmp_path):
    root = dataset("putmc")
    folder = P.walk_folders(root)[16]
    for name, ncols in (("acc.map", 4), ("orient.map", 6), ("positions.map", 3)):
        text = (folder / name).read_text()
        _assert_same(tmp_path, text, ncols)
    _assert_same(tmp_path, (root / P.MAP_DIR / "positions.map").read_text(), 3)


_PIECES = ["0", "7", "12", "9007199254740993", "-", ".", "E", "E-", "-0.", "3.25", "E22", "E-23", " ", "  ", "\n"]


def test_decimal_fast_path_accepts_only_what_it_parses_exactly():
    """Seeded texts spliced from number fragments, separators and misplaced signs, points and
    exponents: wherever the fast path returns arrays, the reference parser accepts the text and
    gives the same arrays bit for bit; it declines (None) everything else."""
    rng = np.random.default_rng(20261123)
    taken = declined = 0
    for _ in range(3000):
        fields = []                         # Java-style decimals (upper-case E, no '+'), as published
        for _ in range(int(rng.integers(1, 4))):
            fields.append(str(int(rng.integers(0, 10 ** 12))))
            for _ in range(3):
                v = rng.normal(0, 10) * 10.0 ** int(rng.integers(-12, 12))
                fmt = ["{:.9g}", "{:.7g}", "{:.3E}", "{!r}", "{:.0f}"][int(rng.integers(0, 5))]
                fields.append(fmt.format(v).upper().replace("E+", "E"))
        if rng.random() < 0.6:              # one field spliced from fragments
            fields[int(rng.integers(0, len(fields)))] = "".join(rng.choice(_PIECES, int(rng.integers(1, 4))))
        text = "\n".join(" ".join(fields[i:i + 4]) for i in range(0, len(fields), 4)) + "\n"
        fast = T._parse_table_fast(text.encode(), 4)
        ref = _outcome(lambda t=text: T.parse_table_lines(t, 4))
        if fast is None:
            declined += 1
            continue
        taken += 1
        assert not isinstance(ref, str), f"{text!r}: fast path accepted what the reference refuses: {ref}"
        for a, b in zip(fast, ref):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), repr(text)
    assert taken > 500 and declined > 500, (taken, declined)


def _java_float(rng) -> str:
    """A value written like Java's ``Float.toString``: always one point, an upper-case exponent for
    very small or large magnitudes."""
    v = np.float32(rng.normal(0, 10) * 10.0 ** int(rng.integers(-9, 9)))
    if 1e-3 <= abs(v) < 1e7 or v == 0:
        return np.format_float_positional(v, unique=True, trim="0")
    return np.format_float_scientific(v, unique=True, trim="0", exp_digits=1).upper().replace("E+", "E")


def _mutate(field: str, rng) -> str:
    """One field with a point, sign, exponent marker, digit or separator inserted, dropped or moved."""
    i = int(rng.integers(0, len(field) + 1))
    what = int(rng.integers(0, 4))
    if what == 0:
        return field[:i] + str(rng.choice([".", "-", "E", "E-", "0", "9", " ", ".5"])) + field[i:]
    if what == 1 and len(field) > 1:
        return field[:i] + field[i + 1:]
    if what == 2:
        return field.replace(".", "", 1)
    return field.replace(".", "", 1)[:i] + "." + field.replace(".", "", 1)[i:]


def test_one_point_per_value_path_matches_the_reference_parser():
    """Seeded tables of 3, 4 or 6 columns whose values are written like Java floats (one point each,
    the layout of the published files), some with one or two fields mutated (a point, sign or
    exponent marker added, dropped or moved; two such changes can keep the number of points equal to
    the number of values):
    wherever the fast path returns arrays they are the reference parser's, bit for bit, and every
    unmutated table is accepted."""
    rng = np.random.default_rng(1123)
    taken = declined = 0
    for _ in range(3000):
        ncols = int(rng.choice([3, 4, 6]))
        rows = [[str(int(rng.integers(0, 10 ** 13)))] + [_java_float(rng) for _ in range(ncols - 1)]
                for _ in range(int(rng.integers(1, 5)))]
        mutated = rng.random() < 0.7
        for _ in range(int(rng.integers(1, 3)) if mutated else 0):     # one or two fields
            r, c = int(rng.integers(0, len(rows))), int(rng.integers(0, ncols))
            rows[r][c] = _mutate(rows[r][c], rng)
        text = "".join(" ".join(row) + "\n" for row in rows)
        fast = T._parse_table_fast(text.encode(), ncols)
        if fast is None:
            assert mutated, f"{text!r}: a well-formed table declined"
            declined += 1
            continue
        taken += 1
        ref = _outcome(lambda t=text, n=ncols: T.parse_table_lines(t, n))
        assert not isinstance(ref, str), f"{text!r}: fast path accepted what the reference refuses: {ref}"
        for a, b in zip(fast, ref):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), repr(text)
    assert taken > 1000 and declined > 500, (taken, declined)


def test_all_walks_take_the_fast_path_with_loadtxts_arrays():
    """Every acc.map / orient.map of the 24 walks takes the fast path; on every third walk its
    arrays are numpy loadtxt's, bit for bit."""
    root = dataset("putmc")
    for n, folder in P.walk_folders(root).items():
        for name, ncols in (("acc.map", 4), ("orient.map", 6)):
            raw = (folder / name).read_bytes()
            fast = T._parse_table_fast(raw, ncols)
            assert fast is not None, folder / name
            if n % 3:
                continue
            dtype = np.dtype([("t", np.int64), ("v", np.float64, (ncols - 1,))])
            rows = np.loadtxt(raw.decode().splitlines(), dtype=dtype, comments=None)
            assert fast[0].tobytes() == np.ascontiguousarray(rows["t"]).tobytes(), folder / name
            assert fast[1].tobytes() == np.ascontiguousarray(rows["v"]).tobytes(), folder / name
            assert fast[1].shape == (len(rows), ncols - 1) and fast[1].flags.c_contiguous


def test_well_formed_files_take_the_compiled_path(tmp_path, monkeypatch):
    path = tmp_path / "acc.map"
    path.write_text("1 0.9073181 2.792282 9.2113495\n2 0.93640137 2.8675385 9.338776\n")
    expected = T.parse_table_lines(path.read_text(), 4, path)

    def refuse(*_args, **_kw):
        raise AssertionError("fell back to the line-by-line parser")

    monkeypatch.setattr(T, "parse_table_lines", refuse)
    stamps, values = T.read_table(path, 4)
    assert stamps.tobytes() == expected[0].tobytes() and values.tobytes() == expected[1].tobytes()


def test_walk_events_hops_are_the_online_stepometers():
    """walk_events gives the whole walk to the stepometer in one call; its hops are those of the
    online path fed one sample at a time (the first 8000 samples of walk 16, ≈ 40 s): the same hop
    times, step counts equal to 1e-12."""
    from dataclasses import replace

    from indoor_loc.backend.putmc_events import walk_events
    from indoor_loc.imu.stepometer import Stepometer

    ds = P.Putmc(dataset("putmc"))
    w = ds.walk(16)
    w = replace(w, acc_t=w.acc_t[:8000], acc=w.acc[:8000])
    sm = Stepometer()
    hops = [h for t, a in zip(w.acc_t.tolist(), w.acc) for h in sm.update(t, a)] + sm.finish()
    ev = walk_events(w)
    assert len(hops) > 10
    assert ev.t_start.tolist() == [h.t_start_ns for h in hops]
    assert ev.t_end.tolist() == [h.t_end_ns for h in hops]
    # the per-sample path resamples with other floating-point operations: step counts agree to ~1e-15
    np.testing.assert_allclose(ev.steps, [h.steps for h in hops], rtol=1e-12, atol=0)


def test_find_all_gives_numpys_offsets_on_either_side_of_few():
    rng = np.random.default_rng(5)
    data = bytes(rng.choice(np.frombuffer(b"0123456789E .", np.uint8), 5000).tolist())
    b = np.frombuffer(data, np.uint8)
    want = np.flatnonzero(b == ord("E"))
    assert 300 < len(want) < 600
    for few in (0, 1, len(want) - 1, len(want), 10_000):
        assert T._find_all(data, b, ord("E"), few).tolist() == want.tolist(), few
    assert T._find_all(b"1 2\n", np.frombuffer(b"1 2\n", np.uint8), ord("E")).tolist() == []
