"""Sites and floors of the Microsoft Indoor Location Competition 2.0 data (pure Python, no ROS).

A site directory holds one directory per floor (``floor_info.json``, ``geojson_map.json``,
``floor_image.png``, a ``path_data_files`` directory of traces, :mod:`indoor_loc.datasets.ms_indoor`).
This module names the floors, orders them by level (the naming conventions of malls: ``B1``, ``F3``,
``L2``, ``G``, ``LG`` …, or ``--floor-levels``), reads each floor's extent in metres and lists the
traces that can be scored.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.datasets.ms_indoor import STOREY_HEIGHT_M, trace_id_of
from indoor_loc.errors import ConfigError, DatasetError, MapError

def floor_kind(name: str) -> tuple[str, int] | None:
    """The convention a floor name follows, as (kind, number), or None when it follows none:
    ``("S", n)`` storey n above ground counted with 1 = ground (``F<n>``, ``<n>F``, ``L<n>``),
    ``("G", 0)`` ground (``G``, ``GF``), ``("UG", 0)`` upper ground, ``("LG", n)`` lower ground n
    (``LG``, ``LG<n>``), ``("B", n)`` basement n (``B<n>``, ``<n>B``, ``B<n>F``, ``BF`` = 1),
    ``("P", n)`` parking n (``P<n>``, ``<n>P``), ``("M", n)`` the mezzanine above storey n (``<n>M``;
    ``M`` = ``("M", 0)``, above ground), ``("LM", 0)`` the lower mezzanine just below ground, ``("BM", 0)`` the basement mezzanine
    just above the first basement. A bare number (or ``Level``/``Floor`` and a number) counts storeys:
    ``1`` the first storey, ``0`` ground, ``-1`` the first basement. Case, spaces, ``_`` and (except as
    a sign) ``-`` are ignored."""
    s = re.sub(r"[\s_]", "", name.upper())
    m = re.fullmatch(r"(?:LEVEL|LVL|FLOOR|FL)?(-?\d+)", s)           # "2", "-1", "Level 3", "Floor 0"
    if m:
        n = int(m.group(1))
        return ("S", n) if n > 0 else ("B", -n) if n < 0 else ("G", 0)
    s = s.replace("-", "")
    for pat, kind in ((r"F(\d+)|(\d+)F|L(\d+)", "S"), (r"B(\d+)F?|(\d+)B", "B"), (r"LG(\d*)", "LG"),
                      (r"P(\d+)|(\d+)P", "P"), (r"(\d+)M", "M")):
        m = re.fullmatch(pat, s)
        if m:
            n = int(next((g for g in m.groups() if g), "1"))
            return (kind, n) if n >= 1 else None
    return {"G": ("G", 0), "GF": ("G", 0), "UG": ("UG", 0), "BF": ("B", 1), "M": ("M", 0), "LM": ("LM", 0),
            "BM": ("BM", 0)}.get(s)


def floor_level(name: str) -> float | None:
    """Storey index of one floor name on its own (0 = ground; see :func:`floor_levels` for a site,
    where lower-ground, basement and parking levels stack and ``G`` shifts the storeys): ``B1`` -> -1,
    ``F1``/``1F``/``L1``/``G`` -> 0, ``F3`` -> 2, ``M`` -> 0.5; None for a name of no known convention."""
    got = floor_levels([name])[name]
    return None if got[1].startswith("fallback") else got[0]


def floor_levels(names: list[str], overrides: dict[str, float] | None = None) -> dict[str, tuple[float, str]]:
    """Storey index of each floor of a site (0 = ground, z = index × storey height) and how it was decided.

    The competition's sites name floors in several conventions (:func:`floor_kind`); the indices are:

    - storeys ``F<n>``/``<n>F``/``L<n>``: n − 1 (1 = ground), or n when the site also has ``G``
      (then ``L1`` is the first floor above ground, as in British usage); ``G``: 0; ``UG``: 0.5;
    - below ground the levels stack from the top: lower ground ``LG1``…``LGk`` at −1…−k, then
      basements ``B1``…``Bm`` at −(k+1)…−(k+m), then parking ``P1``… below the lowest basement
      (k, m = the highest numbers present; with neither, ``B1`` = −1 and ``P1`` = −1);
    - mezzanines sit half a storey above their storey: ``M`` = ground + 0.5, ``<n>M`` = storey n + 0.5
      (so ``1M`` = 0.5 where 1 = ground, 1.5 on a site with ``G``); ``LM`` = −0.5 (between ground and
      the first level below); ``BM`` = the first basement + 0.5.

    ``overrides`` ({name: index}) win. A name of no known convention, or one whose index another floor
    already holds, gets the next index above the highest one assigned (in natural name order) — a
    documented fallback, marked ``fallback: …`` so it can be reported and overridden."""
    over = dict(overrides or {})
    kinds = {n: floor_kind(n) for n in names if n not in over}
    have = {k for k in kinds.values() if k}
    top_n = {fam: max((k[1] for k in have if k[0] == fam), default=0) for fam in ("LG", "B")}
    ground_named = ("G", 0) in have
    shift = 0 if ground_named else -1

    def level(kind: tuple[str, int]) -> tuple[float, str]:
        fam, n = kind
        if fam == "S":
            return float(n + shift), ("storey, G = 0" if ground_named else "storey, 1 = ground")
        if fam == "G":
            return 0.0, "ground"
        if fam == "UG":
            return 0.5, "upper ground"
        if fam == "LG":
            return float(-n), "lower ground"
        if fam == "B":
            return float(-(top_n["LG"] + n)), "basement" + (f", below {top_n['LG']} lower-ground level(s)"
                                                             if top_n["LG"] else "")
        if fam == "P":
            return float(-(top_n["LG"] + top_n["B"] + n)), "parking, below ground"
        if fam == "M":
            return (n + shift if n else 0.0) + 0.5, "mezzanine"
        if fam == "LM":
            return -0.5, "lower mezzanine"
        return -(top_n["LG"] + 1) + 0.5, "basement mezzanine"        # BM

    out: dict[str, tuple[float, str]] = {n: (float(v), "set by the user") for n, v in over.items() if n in names}
    taken = {v for v, _ in out.values()}
    rest: list[str] = []
    for n in sorted(kinds, key=_natural):
        k = kinds[n]
        if k is None:
            rest.append(n)
            continue
        v, how = level(k)
        if v in taken:
            rest.append(n)
            continue
        out[n] = (v, how)
        taken.add(v)
    nxt = math.floor(max(taken)) + 1.0 if taken else 0.0
    for n in sorted(rest, key=_natural):
        why = "not a known floor name" if kinds[n] is None else f"its level {level(kinds[n])[0]:g} is another floor's"
        out[n] = (nxt, f"fallback: {why}; placed above the highest floor")
        nxt += 1.0
    return {n: out[n] for n in names}


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name.upper())]


def parse_floor_levels(text: str) -> dict[str, float]:
    """``NAME=LEVEL,...`` (storey indices, 0 = ground; a mezzanine may be fractional) -> {name: level}.
    ConfigError on a malformed entry."""
    out: dict[str, float] = {}
    for tok in (t.strip() for t in text.split(",")):
        if not tok:
            continue
        name, eq, val = tok.partition("=")
        try:
            v = float(val)
        except ValueError:
            v = math.nan
        if not eq or not name.strip() or not math.isfinite(v):
            raise ConfigError(f"--floor-levels: expected NAME=LEVEL (a number), got {tok!r}")
        if name.strip() in out:
            raise ConfigError(f"--floor-levels: floor {name.strip()!r} given twice")
        out[name.strip()] = v
    if len(set(out.values())) < len(out):
        raise ConfigError(f"--floor-levels: two floors at one level in {text!r}")
    return out


#: WGS-84 semi-major axis (m): the competition's floor_info.json sizes are its GeoJSON's lon/lat extent
#: at this radius (equirectangular at the plan's mid latitude; within 1 mm on ms_site2)
_EARTH_A_M = 6378137.0


def geojson_extent_m(path: Path) -> tuple[float, float]:
    """(width, height) m of a floor's GeoJSON plan: its lon/lat bounding box in metres (or the box
    itself when the coordinates are not lon/lat). MapError when unreadable or empty."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise MapError(f"{path}: not a readable GeoJSON file: {err}") from err
    pts: list[tuple[float, float]] = []

    def walk(o) -> None:
        if isinstance(o, list) and len(o) >= 2 and all(isinstance(v, (int, float)) for v in o[:2]):
            pts.append((float(o[0]), float(o[1])))
        elif isinstance(o, list):
            for v in o:
                walk(v)
    for ft in (data.get("features") or []) if isinstance(data, dict) else []:
        geom = ft.get("geometry") if isinstance(ft, dict) else None
        walk(geom.get("coordinates") if isinstance(geom, dict) else None)
    a = np.array(pts, float).reshape(-1, 2)
    a = a[np.isfinite(a).all(axis=1)]
    if len(a) < 2:
        raise MapError(f"{path}: no coordinates in its features")
    lo, hi = a.min(axis=0), a.max(axis=0)
    if np.all(np.abs(a[:, 0]) <= 180) and np.all(np.abs(a[:, 1]) <= 90) and np.all(hi - lo < 0.1):
        k_lat = math.radians(1.0) * _EARTH_A_M
        k_lon = k_lat * math.cos(math.radians(0.5 * (lo[1] + hi[1])))
        return float((hi[0] - lo[0]) * k_lon), float((hi[1] - lo[1]) * k_lat)
    return float(hi[0] - lo[0]), float(hi[1] - lo[1])


@dataclass(frozen=True)
class FloorInfo:
    """One floor directory: ``width_m``/``height_m`` the plan's extent (NaN when unknown), ``level`` the
    storey index (:func:`floor_levels`; ``level_rule`` how it was decided), ``notes`` what was odd."""
    name: str
    directory: Path
    width_m: float
    height_m: float
    level: float
    trace_files: tuple[Path, ...]
    level_rule: str = ""
    notes: tuple[str, ...] = ()
    plan_directory: Path | None = None

    @property
    def plans(self) -> Path:
        """Where the floor's ``floor_info.json``, ``geojson_map.json`` and ``floor_image.png`` are."""
        return self.plan_directory or self.directory

    def z_m(self, storey_height_m: float = STOREY_HEIGHT_M) -> float:
        return self.level * storey_height_m


def list_traces(directory: Path) -> list[Path]:
    """Trace files in a directory (``.txt`` and ``.txt.gz``; a ``.txt`` wins over its ``.gz``),
    sorted by id (ids are time-ordered)."""
    files: dict[str, Path] = {}
    for p in sorted(Path(directory).iterdir()):
        if p.is_file() and (p.name.endswith(".txt.gz") or p.name.endswith(".txt")):
            tid = trace_id_of(p)
            if tid not in files or p.suffix == ".txt":
                files[tid] = p
    return [files[k] for k in sorted(files)]


_FLOOR_FILES = ("floor_info.json", "geojson_map.json", "floor_image.png")


@dataclass(frozen=True)
class Site:
    """A site directory: its floors sorted by level, the subdirectories that are not floors and the
    directory plan files were taken from (None: the floors' own)."""
    floors: list[FloorInfo]
    ignored: tuple[str, ...] = ()
    metadata: Path | None = None


def read_site(site_dir: str | Path, *, levels: dict[str, float] | None = None,
              metadata: str | Path | None = None) -> Site:
    """The floors of a site directory. A floor is a subdirectory holding ``path_data_files/``, trace
    files, ``floor_info.json`` or ``geojson_map.json``, or named as a floor (:func:`floor_kind`; an
    empty ``F5/`` is a floor without walks); its walks are ``path_data_files/*.txt[.gz]`` (or
    the trace files in it). Its plan files (``floor_info.json``, ``geojson_map.json``,
    ``floor_image.png``) are in it or, when it has none, in ``metadata/<floor>/`` — by default, for a
    site directory ``…/train/<site>`` (the competition's Kaggle layout), ``…/metadata/<site>`` when it
    exists. Its extent comes from ``floor_info.json`` (``map_info.width/height``), else from the GeoJSON
    plan's lon/lat extent (:func:`geojson_extent_m`), else NaN; each fallback and an empty floor is a
    note. ``levels`` ({name: storey index}) override :func:`floor_levels`; naming a floor the site does
    not have is a ConfigError. DatasetError if the directory is missing or holds no floor."""
    site = Path(site_dir)
    if not site.is_dir():
        raise DatasetError(f"site directory {site} does not exist")
    if metadata is None and site.resolve().parent.name in ("train", "test"):
        guess = site.resolve().parent.parent / "metadata" / site.resolve().name
        metadata = guess if guess.is_dir() else None
    meta = Path(metadata) if metadata is not None else None
    if meta is not None and not meta.is_dir():
        raise DatasetError(f"metadata directory {meta} does not exist")
    found: list[tuple[str, Path, Path, float, float, tuple[Path, ...], list[str]]] = []
    ignored = []
    dirs = {d.name: d for d in sorted(site.iterdir())}
    if meta is not None:
        for d in sorted(meta.iterdir()):
            dirs.setdefault(d.name, d)
    for name in sorted(dirs):
        d = dirs[name]
        if not d.is_dir() or name.startswith(".") or name == "__MACOSX":
            continue
        pdf = d / "path_data_files"
        direct = list_traces(d)
        plans = d
        if meta is not None and not any((d / f).is_file() for f in _FLOOR_FILES) and (meta / name).is_dir():
            plans = meta / name
        if not (pdf.is_dir() or direct or any((plans / f).is_file() for f in _FLOOR_FILES)
                or floor_kind(name) is not None):
            ignored.append(name)
            continue
        notes: list[str] = []
        if plans != d:
            notes.append(f"plan files from {plans}")
        traces = tuple(list_traces(pdf)) if pdf.is_dir() else tuple(direct)
        if pdf.is_dir() and direct:
            notes.append(f"{len(direct)} trace file(s) beside path_data_files/ not read (the walks are in it)")
        if not traces:
            notes.append("no walks (" + ("empty path_data_files/" if pdf.is_dir() else "no path_data_files/") + ")")
        w = h = math.nan
        info, gj = plans / "floor_info.json", plans / "geojson_map.json"
        if info.is_file():
            try:
                mi = json.loads(info.read_text())["map_info"]
                w, h = float(mi["width"]), float(mi["height"])
                if not (w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
                    raise ValueError(f"width {w}, height {h}")
            except (OSError, ValueError, KeyError, TypeError) as err:
                notes.append(f"floor_info.json unreadable (expected map_info.width/height > 0: {err})")
                w = h = math.nan
        else:
            notes.append("no floor_info.json")
        if not math.isfinite(w) and gj.is_file():
            try:
                w, h = geojson_extent_m(gj)
                notes.append(f"extent {w:.2f} × {h:.2f} m from the GeoJSON plan's lon/lat extent")
            except MapError as err:
                notes.append(f"extent unknown: {err}")
        elif not math.isfinite(w):
            notes.append("extent unknown (no floor_info.json, no geojson_map.json): no plan in the map frame")
        found.append((name, d, plans, w, h, traces, notes))
    if not found:
        raise DatasetError(f"{site}: no floor directories (path_data_files/, floor_info.json…) found")
    names = [f[0] for f in found]
    over = dict(levels or {})
    bad = [n for n in over if n not in names]
    if bad:
        raise ConfigError(f"--floor-levels: no floor(s) {bad}; the site has {names}")
    lv = floor_levels(names, over)
    floors = [FloorInfo(n, d, w, h, lv[n][0], traces, lv[n][1], tuple(notes), plans)
              for n, d, plans, w, h, traces, notes in found]
    return Site(sorted(floors, key=lambda f: f.level), tuple(ignored), meta)


def site_floors(site_dir: str | Path, *, levels: dict[str, float] | None = None,
                metadata: str | Path | None = None) -> list[FloorInfo]:
    """The floors of a site directory sorted by level (:func:`read_site`)."""
    return read_site(site_dir, levels=levels, metadata=metadata).floors
