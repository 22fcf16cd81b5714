"""Whitespace tables of numbers whose first column is an integer stamp in ns (the PUTMC ``*.map``
sensor files): a vectorised decimal reader, numpy's ``loadtxt``, and a line-by-line reference parser
that names the offending line. Pure parsing, no ROS."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from indoor_loc.errors import DatasetError


def read_text(path: Path) -> str:
    """The text of ``path``; a :class:`DatasetError` naming it when it cannot be read."""
    try:
        return Path(path).read_text()
    except OSError as err:
        raise DatasetError(f"cannot read {path}: {err}") from err


def read_table(path: Path, ncols: int) -> tuple[np.ndarray, np.ndarray]:
    """A whitespace table whose first column is int ns: (stamps (N,) int64, values (N, ncols-1)).

    Three readers, each giving the same arrays bit for bit where it accepts a text: the decimal fast
    path :func:`_parse_table_fast` (the published files: single spaces, Java-style decimals), then
    numpy's compiled ``loadtxt`` on the lines from ``str.splitlines`` (it converts numbers as
    ``int``/``float`` do), then :func:`parse_table_lines`, which names the offending line of a text
    no reader accepts."""
    try:
        raw = Path(path).read_bytes()
    except OSError as err:
        raise DatasetError(f"cannot read {path}: {err}") from err
    if ncols >= 2:
        fast = _parse_table_fast(raw, ncols)
        if fast is not None:
            return fast
    text = read_text(path)
    if ncols >= 2 and text.isascii() and text and not text.isspace():
        dtype = np.dtype([("t", np.int64), ("v", np.float64, (ncols - 1,))])
        try:
            rows = np.loadtxt(text.splitlines(), dtype=dtype, comments=None, ndmin=1)
        except ValueError:
            pass        # a malformed line: the line-by-line parser below says which one
        else:
            stamps = np.ascontiguousarray(rows["t"])
            values = np.ascontiguousarray(rows["v"]).reshape(len(rows), ncols - 1)
            if not np.all(np.isfinite(values)):
                raise DatasetError(f"{path}: non-finite values")
            return stamps, values
    return parse_table_lines(text, ncols, path)


#: bytes the decimal fast path of :func:`read_table` handles; any other byte sends a file to loadtxt
_FAST_BYTES = b"0123456789.-E \n"
#: with '.' deleted, turns the exponent marker into a separator ("-8.85E-4" -> "-885 -4") and any
#: byte outside ``_FAST_BYTES`` into 'x', on which ``np.fromstring`` fails
_FAST_STRIP = bytes(b if b in _FAST_BYTES else ord("x") for b in range(256)).replace(b"E", b" ")
_FAST_MAX_FIELD = 18                #: bytes per field: at most 18 digits, below 2**63 as an int64
_FAST_LAST_FIELD = re.compile(rb"-?(\d+\.?\d*|\.\d+)(E-?\d+)?")
#: 10**0 … 10**22, each exact in float64 (5**22 < 2**53)
_POW10 = np.array([float(10 ** i) for i in range(23)])
_FAST_MAX_MANTISSA = float(2 ** 53)


def _parse_table_fast(data: bytes, ncols: int) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`read_table`'s fast path for plain decimal tables; ``None`` for any text outside it.

    Handles fields of at most 18 bytes separated by single spaces, one ``\n`` per line, integer
    stamps, and values ``[-]digits[.digits][E[-]digits]`` whose digits without the point make an
    integer M < 2**53 and whose point and exponent scale it by 10**-k, |k| ≤ 22. There M and 10**|k|
    are exact in float64, so one IEEE division (multiplication) is the correctly rounded conversion:
    bit for bit what ``float()`` and ``np.loadtxt`` give (Clinger's fast path: W. D. Clinger, "How
    to read floating point numbers accurately", PLDI 1990). numpy parses the integers
    (``np.fromstring`` on the text with the points removed and the exponent markers turned into
    separators); a malformed field either makes it fail or changes the number of integers it
    finds, and the checks here catch the rest (several points or markers in a field, a point in
    the stamp column or in an exponent or just before a sign, a sign at the very end).

    In the published files every value has exactly one point; then the i-th point belongs to the
    i-th value field, which is checked (each point between the separators around its field) and
    gives the digits after it without a search. Other texts locate each point's field by a search."""
    if not data or data[0] in b" \n":
        return None
    if not data.endswith(b"\n") or data.endswith((b" \n", b"\n\n")):
        data = data.rstrip(b" \n") + b"\n"
    b = np.frombuffer(data, np.uint8)
    sep = np.flatnonzero(b <= 32)                        # the byte after each field: ' ' or '\n'
    n_tok = len(sep)
    n_lines, rest = divmod(n_tok, ncols)
    if rest or not _FAST_LAST_FIELD.fullmatch(data, data.rfind(b" ") + 1, len(data) - 1):
        return None
    grid = sep.reshape(n_lines, ncols)
    if not (b[grid] == _line_ends(ncols)).all():        # ncols-1 spaces then '\n' on every line
        return None
    # fields of at most 18 bytes (an empty one gives no integer: the count below declines it)
    if sep[0] > _FAST_MAX_FIELD or (n_tok > 1 and np.diff(sep).max() > _FAST_MAX_FIELD + 1):
        return None
    before, after = grid[:, :-1], grid[:, 1:]            # the separators around each value field
    dot = np.flatnonzero(b == 46)                        # decimal points
    if len(dot) and (b[dot + 1] == 45).any():            # ".-5": without its point, "-5" would parse
        return None
    if len(dot) == before.size:                          # one per value field, in order?
        at = dot.reshape(before.shape)
        k = after - at                                   # value = mantissa * 10**-k …
        k -= 1                                           # … k: the digits after the point
        if k.min() < 0 or not (at > before).all():       # each point inside its field
            return None
        dot_of = np.arange(before.size)                  # value field -> index of its point
    else:
        t_dot = np.searchsorted(sep, dot)
        if np.any(np.diff(t_dot) == 0) or np.any(t_dot % ncols == 0):
            return None
        kf = np.zeros(n_tok, np.int64)
        kf[t_dot] = sep[t_dot] - dot - 1
        k = kf.reshape(n_lines, ncols)[:, 1:].copy()
        dot_of = np.full(n_tok, -1, np.int64)
        dot_of[t_dot] = np.arange(len(dot))
        dot_of = dot_of.reshape(n_lines, ncols)[:, 1:].ravel()
    ex = _find_all(data, b, ord("E"))                    # exponent markers
    t_ex = np.searchsorted(sep, ex)
    if np.any(np.diff(t_ex) == 0) or np.any(t_ex % ncols == 0):
        return None
    try:
        ints = np.fromstring(data.translate(_FAST_STRIP, b"."), dtype=np.int64, sep=" ")
    except ValueError:
        return None
    if len(ints) != n_tok + len(ex):
        return None
    kv = k.reshape(-1)
    up, scale_up = np.zeros(0, np.intp), np.zeros(0)     # fields with 10**-k, k < 0: multiplied
    if len(ex):
        slot = t_ex + np.arange(1, len(ex) + 1)          # the exponents, each after its field
        expo = ints[slot]
        ints = np.delete(ints, slot)
        vi = t_ex - t_ex // ncols - 1                    # value-field index of each marked field
        di = dot_of[vi]
        pointed = di >= 0
        if len(dot) and np.any(pointed & (dot[di] > ex)):    # a point in the exponent
            return None
        ke = kv[vi] - np.where(pointed, sep[t_ex] - ex, 0) - expo   # … not counting "E-4" as digits
        if np.any(ke < 1 - len(_POW10)) or np.any(ke >= len(_POW10)):
            return None
        kv[vi] = np.maximum(ke, 0)
        up, scale_up = vi[ke < 0], _POW10[-ke[ke < 0]]
    table = ints.reshape(n_lines, ncols)
    values = table[:, 1:].astype(np.float64)
    if len(values) and (values.max() >= _FAST_MAX_MANTISSA or values.min() <= -_FAST_MAX_MANTISSA):
        return None                                      # (float rounding keeps M >= 2**53 at or above it)
    np.divide(values, _POW10[k], out=values)
    vflat = values.reshape(-1)
    vflat[up] *= scale_up                                # divided by 10**0 above: exact
    zero = np.flatnonzero(vflat == 0)                    # a zero keeps its sign: "-0.0" gives -0.0
    if len(zero):
        minus = b[sep[zero + zero // (ncols - 1)] + 1] == 45     # the field's first byte
        vflat[zero[minus]] = -0.0
    return np.ascontiguousarray(table[:, 0]), values


def _line_ends(ncols: int) -> np.ndarray:
    """The separator bytes of one table line: ``ncols - 1`` spaces, then ``\n``."""
    return np.array([32] * (ncols - 1) + [10], np.uint8)


def _find_all(data: bytes, b: np.ndarray, char: int, few: int = 256) -> np.ndarray:
    """Offsets of every byte ``char`` in ``data`` (``b``: its uint8 view): by ``bytes.find`` while
    there are at most ``few``, which skips a pass over the whole text, else by numpy."""
    out: list[int] = []
    i = data.find(char)
    while i >= 0 and len(out) < few:
        out.append(i)
        i = data.find(char, i + 1)
    return np.array(out, dtype=np.intp) if i < 0 else np.flatnonzero(b == char)


def parse_table_lines(text: str, ncols: int, path: Path | str = "<text>") -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_table`'s reference parser, line by line in Python: blank lines skipped, the
    first column converted by ``int``, the others by ``float``; errors name the line."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    tok = " ".join(lines).split()
    if len(tok) != ncols * len(lines):
        for i, ln in enumerate(lines):
            if len(ln.split()) != ncols:
                raise DatasetError(f"{path}: line {i + 1}: expected {ncols} columns, got {ln!r}")
    arr = np.array(tok, dtype=object).reshape(len(lines), ncols) if lines else np.empty((0, ncols), dtype=object)
    try:
        stamps = np.array([int(s) for s in arr[:, 0]], dtype=np.int64)
        values = arr[:, 1:].astype(np.float64)
    except (ValueError, OverflowError) as err:
        raise DatasetError(f"{path}: not a table of numbers: {err}") from err
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: non-finite values")
    return stamps, values
