"""Fit once, load everywhere: the fitted state of a WiFi positioner saved beside its radio map.

Fitting the powed k-NN (:mod:`indoor_loc.wifi.powed_knn`) to a large map takes seconds to tens of seconds
(its interpolated grid, the path-loss field in the floor plans and the leave-walks-out calibration), and
every ``wifi_fix_node`` started on the same map would spend it again. A :class:`FitStore` saves what the
positioning needs after the fit (:meth:`PowedKnn.fitted_state`: the grid's values, the σ tables, the AP
weights, the floor detection's home floors, …) as one file of plain arrays (a JSON header, then the raw
bytes; no pickled objects) and loads it back, bit for bit, at the next start. The grid's values, most of
the file, are not copied but mapped read-only from the file, so the nodes of several users on one map
share one copy in memory (and the system may drop and re-read those pages under pressure).

The file is used only when it was made for the same inputs: its **key** is a SHA-256 over the format
version, the radio map's files (the manifest and the files it names), the floor plans' files
(``map.yaml`` and ``geojson_map.json`` of each floor), the positioner's parameters, the source code of
the modules that compute the fit, and the numpy/scipy versions. A file whose key differs (stale) or that
cannot be read (truncated, a CRC-32 mismatch, inconsistent with the map) is refused with a log line saying why,
the positioner is fitted, and the file replaced. Files are written to a temporary name in the same
directory and renamed, so a reader never sees half a file and two processes fitting at once leave one
whole file (a file is never rewritten in place: a node that has one mapped keeps reading the version it
loaded). A directory that cannot be written is logged and the fit is simply not saved.

Location: ``<cache directory>/wifi_fit_<name>.fit``, where the cache directory defaults to
``<radio map>/fit_cache`` and the name is a hash of the map's path and the parameters, so maps and
parameter sets sharing one directory do not overwrite each other. Beside it, ``wifi_map_<name>.fit`` holds
the radio map's arrays as read from its files (keyed by those files and the code), so a start with a saved
fit parses neither the map's CSV nor the floor plans. Parts of a positioner other than
powed k-NN (WKNN, coverage areas, path loss; a chain's primary) fit in well under a second and are
fitted as usual.
"""
from __future__ import annotations

import ctypes
import dataclasses
import hashlib
import importlib
import json
import mmap
import os
import re
import struct
import tempfile
import threading
import time
import weakref
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from indoor_loc.errors import ConfigError, MapError
from indoor_loc.wifi.powed_knn import PowedKnn
from indoor_loc.wifi.radiomap import APS_FILE, FINGERPRINTS_FILE, MANIFEST, read_manifest
from indoor_loc.wifi.types import Positioner, RadioMap
from indoor_loc.wifi.walkable import load_floor_plans

FORMAT = "indoor_loc.wifi_fit"
FORMAT_VERSION = 2
#: the default cache directory, inside the radio map's directory
CACHE_DIRNAME = "fit_cache"
#: modules whose code decides the fitted state: editing any of them changes the key
CODE_MODULES = ("indoor_loc.wifi.powed_knn", "indoor_loc.wifi.radio_field", "indoor_loc.wifi.pathloss",
                "indoor_loc.wifi.types", "indoor_loc.wifi.walkable", "indoor_loc.wifi.radiomap",
                "indoor_loc.wifi.fit_store")

#: log(level, text) with level "info" or "warning"
Log = Callable[[str, str], None]


def _no_log(level: str, text: str) -> None:
    pass


def _hash_files(h: Any, root: Path, files: list[Path]) -> None:
    for f in files:
        h.update(str(f.relative_to(root)).encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        h.update(b"\0")


def map_files(map_dir: Path) -> list[Path]:
    """The files a radio map directory is read from: its manifest and the files it names."""
    files = read_manifest(map_dir).get("files") or {}
    out = [map_dir / MANIFEST]
    for name in sorted({files.get("aps", APS_FILE), files.get("fingerprints", FINGERPRINTS_FILE)}):
        if (map_dir / name).is_file():
            out.append(map_dir / name)
    return out


def plan_files(floor_plans: Path) -> list[Path]:
    """The files :func:`indoor_loc.wifi.walkable.load_floor_plans` reads under ``floor_plans``."""
    metas = [floor_plans / "map.yaml"] if (floor_plans / "map.yaml").is_file() else \
        sorted(floor_plans.glob("*/map.yaml"))
    return [f for m in metas for f in (m, m.parent / "geojson_map.json") if f.is_file()]


def code_digest() -> str:
    """SHA-256 of the source of :data:`CODE_MODULES` and the numpy/scipy versions."""
    import scipy
    h = hashlib.sha256(f"numpy {np.__version__} scipy {scipy.__version__}".encode())
    for name in CODE_MODULES:
        src = getattr(importlib.import_module(name), "__file__", None)
        h.update(name.encode() + b"\0")
        if src:
            h.update(Path(src).read_bytes())
    return h.hexdigest()


def _leaves(pos: Positioner) -> list[Positioner]:
    """The positioners a chain is made of (itself when it is no chain), in fitting order."""
    if hasattr(pos, "primary") and hasattr(pos, "fallback"):
        return _leaves(pos.primary) + _leaves(pos.fallback)
    return [pos]


class FitStore:
    """Saved fits of positioners on the radio map in ``map_dir`` (with the floor plans in ``floor_plans``,
    "" = none), in ``cache_dir`` (default ``map_dir/fit_cache``); and the radio map itself as read from its
    files, so that a start with a saved fit need not parse the map's CSV either."""

    def __init__(self, map_dir: str | Path, floor_plans: str | Path = "", cache_dir: str | Path = "") -> None:
        self.map_dir = Path(map_dir).expanduser().resolve()
        self.floor_plans = Path(floor_plans).expanduser().resolve() if str(floor_plans) else None
        self.cache_dir = Path(cache_dir).expanduser() if str(cache_dir) else self.map_dir / CACHE_DIRNAME
        self._map_digest: str | None = None
        self._inputs: str | None = None
        #: the files loaded and written by this store
        self.loaded: list[Path] = []
        self.saved: list[Path] = []
        #: the saved map arrays were refused as unreadable by :meth:`load_map`: the next fit replaces them
        self.map_refused = False

    def map_digest(self) -> str:
        """SHA-256 of the format, the code and the map's files (computed once)."""
        if self._map_digest is None:
            h = hashlib.sha256(f"{FORMAT} {FORMAT_VERSION}\0{code_digest()}\0".encode())
            _hash_files(h, self.map_dir, map_files(self.map_dir))
            self._map_digest = h.hexdigest()
        return self._map_digest

    def inputs_digest(self) -> str:
        """SHA-256 of the map's and plans' files and the fitting code (computed once)."""
        if self._inputs is None:
            h = hashlib.sha256(f"{self.map_digest()}\0plans\0".encode())
            if self.floor_plans is not None:
                _hash_files(h, self.floor_plans, plan_files(self.floor_plans))
            self._inputs = h.hexdigest()
        return self._inputs

    def _settings(self, part: PowedKnn, index: int) -> str:
        return json.dumps({"part": index, "method": part.name, "plans": self.floor_plans is not None,
                           "params": dataclasses.asdict(part.params)}, sort_keys=True)

    def key(self, part: PowedKnn, index: int) -> str:
        """The key a saved fit of ``part`` (the ``index``-th part of its chain) must carry."""
        return hashlib.sha256(f"{self.inputs_digest()}\0{self._settings(part, index)}".encode()).hexdigest()

    def path(self, part: PowedKnn, index: int) -> Path:
        """Where the fit of ``part`` is saved: named by the map's path and the parameters."""
        name = hashlib.sha256(f"{self.map_dir}\0{self.floor_plans}\0{self._settings(part, index)}".encode())
        return self.cache_dir / f"wifi_fit_{name.hexdigest()[:16]}.fit"

    def map_path(self) -> Path:
        """Where the radio map's arrays are saved: named by the map's path."""
        return self.cache_dir / f"wifi_map_{hashlib.sha256(str(self.map_dir).encode()).hexdigest()[:16]}.fit"

    def is_current(self, pos: Positioner) -> bool:
        """Whether every powed k-NN part of ``pos`` has a saved fit with its key (the header only is read;
        the data are checked when loaded)."""
        for index, part in enumerate(_leaves(pos)):
            if isinstance(part, PowedKnn):
                try:
                    meta, _ = read_header(self.path(part, index))
                except (OSError, ValueError):
                    return False
                if meta.get("key") != self.key(part, index):
                    return False
        return True

    # ------------------------------------------------------------------------------------------
    def _open(self, path: Path, key: str, log: Log, then: str = "fitting again"
              ) -> tuple[dict[str, Any], memoryview] | None:
        """The header and data of ``path`` when it exists and carries ``key``, else None (logged unless the
        file does not exist). ValueError/OSError when it is unreadable."""
        if not path.is_file():
            return None
        meta, data = read_header(path)
        if meta.get("format") != FORMAT or meta.get("version") != FORMAT_VERSION:
            log("warning", f"fit cache {path}: format {meta.get('format')!r} version {meta.get('version')!r}, "
                           f"expected {FORMAT!r} {FORMAT_VERSION}: refused, {then}")
            return None
        if meta.get("key") != key:
            log("info", f"fit cache {path} is stale (the radio map, floor plans, parameters or code "
                        f"changed since it was written): {then}")
            return None
        return meta, data

    def load(self, part: PowedKnn, index: int, rm: RadioMap, log: Log = _no_log) -> bool:
        """Load the saved fit of ``part`` into it; False (with a log line saying why, unless there is
        simply none) when there is none or it is refused."""
        path = self.path(part, index)
        t0 = time.monotonic()
        try:
            opened = self._open(path, self.key(part, index), log)
            if opened is None:
                return False
            part.load_fitted_state(rm, read_arrays(*opened))
        except (OSError, ValueError, KeyError, TypeError, MapError) as err:
            log("warning", f"fit cache {path} is unreadable ({type(err).__name__}: {err}): refused, fitting again")
            return False
        log("info", f"loaded the fitted radio map from {path} in {time.monotonic() - t0:.1f} s")
        self.loaded.append(path)
        return True

    def load_map(self, log: Log = _no_log) -> RadioMap | None:
        """The radio map as :func:`~indoor_loc.wifi.radiomap.load_radiomap` reads it from its files, from the
        saved copy made of the same files and code; None (logged when refused) without one."""
        path = self.map_path()
        try:
            opened = self._open(path, self.map_digest(), log, "reading the radio map's files")
            if opened is None:
                return None
            meta, data = opened
            a = read_arrays(meta, data)
            m = meta["map"]
            return RadioMap(positions=a["positions"], bssids=list(m["bssids"]), rssi_dbm=a["rssi_dbm"],
                            freq_mhz=a["freq_mhz"], ssids=list(m["ssids"]), scan_ids=a["scan_ids"],
                            stamps_ns=a["stamps_ns"], source=list(m["source"]), frame_id=str(m["frame_id"]),
                            z_m=a["z_m"], floors={str(k): float(v) for k, v in m["floors"].items()},
                            age_ms=a["age_ms"] if "age_ms" in a else None)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            log("warning", f"fit cache {path} is unreadable ({type(err).__name__}: {err}): refused, reading the "
                           f"radio map's files")
            self.map_refused = True
            return None

    def map_is_current(self) -> bool:
        """Whether the saved map arrays carry the map's key (the header only is read) and were not refused."""
        if self.map_refused:
            return False
        try:
            meta, _ = read_header(self.map_path())
        except (OSError, ValueError):
            return False
        return bool(meta.get("key") == self.map_digest())

    def save(self, part: PowedKnn, index: int, log: Log = _no_log) -> Path | None:
        """Write the fit of ``part`` atomically; None (logged) when the directory cannot be written."""
        return self._write(self.path(part, index), self.key(part, index), {}, part.fitted_state(), log,
                           "the fitted radio map")

    def save_map(self, rm: RadioMap, log: Log = _no_log) -> Path | None:
        """Write the radio map read from ``map_dir``'s files (``rm``), for :meth:`load_map`."""
        arrays = {"positions": rm.positions, "rssi_dbm": rm.rssi_dbm, "freq_mhz": rm.freq_mhz, "scan_ids": rm.scan_ids,
                  "stamps_ns": rm.stamps_ns, "z_m": rm.z_m}
        if rm.age_ms is not None:
            arrays["age_ms"] = rm.age_ms
        meta = {"map": {"bssids": list(rm.bssids), "ssids": list(rm.ssids), "source": list(rm.source),
                        "frame_id": rm.frame_id, "floors": dict(rm.floors)}}
        out = self._write(self.map_path(), self.map_digest(), meta, arrays, log, "the radio map's arrays")
        if out is not None:
            self.map_refused = False
        return out

    def _write(self, path: Path, key: str, extra: dict[str, Any], arrays: dict[str, np.ndarray], log: Log,
               what: str) -> Path | None:
        meta = {"format": FORMAT, "version": FORMAT_VERSION, "key": key, **extra,
                "radiomap": str(self.map_dir), "floor_plans": str(self.floor_plans or ""),
                "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        tmp = None
        try:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=".tmp", dir=self.cache_dir)
            with os.fdopen(fd, "wb") as fh:
                write_arrays(fh, meta, arrays)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o644)                       # mkstemp's 0600: other users' nodes read it too
            os.replace(tmp, path)
        except OSError as err:
            log("warning", f"could not write the fit cache in {self.cache_dir} ({err}): {what} not saved")
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
            return None
        log("info", f"saved {what} to {path}")
        self.saved.append(path)
        return path


# ----------------------------------------------------------------------------------------------
# the file: MAGIC, the header's length (8 bytes, little-endian), the header (JSON: the caller's metadata,
# each array's dtype, shape and offset, the data's length and CRC-32), then the arrays' bytes, each
# starting at a multiple of ALIGN bytes
# ----------------------------------------------------------------------------------------------
MAGIC = b"indoor_loc.fit\n\0"
ALIGN = 64
#: arrays left in the file's mapping instead of copied (read only; the processes that load one file share
#: its pages): the values and rows of the grid's inverted indexes, most of the file
SHARED = re.compile(r"part\d+_(row|val)")


#: one read-only mapping per file per process while any array uses it (by device, inode, size and modification
#: time: files are replaced by renaming, never rewritten in place), so the stages of many users in one process
#: (``indoor-loc run`` with one walk per namespace) share one mapping, and the process's resident size counts
#: its pages once instead of once per stage
_MAPPED: "weakref.WeakValueDictionary[tuple[int, int, int, int], mmap.mmap]" = weakref.WeakValueDictionary()
_MAPPED_LOCK = threading.Lock()


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def write_arrays(fh: Any, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Write ``meta`` and ``arrays`` (numeric, bool or str; no objects) to the binary file ``fh``."""
    table: dict[str, dict[str, Any]] = {}
    flat: list[tuple[memoryview, int]] = []
    crc, offset = 0, 0
    for name, a in arrays.items():
        a = np.asarray(a)
        a = a if a.flags.c_contiguous else a.copy(order="C")       # (ascontiguousarray makes 0-d arrays 1-d)
        if a.dtype.hasobject:
            raise ValueError(f"array {name!r} holds Python objects")
        table[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset}
        raw = memoryview(a.reshape(-1).view(np.uint8).data)
        pad = _aligned(len(raw)) - len(raw)
        crc = zlib.crc32(b"\0" * pad, zlib.crc32(raw, crc))
        flat.append((raw, pad))
        offset += len(raw) + pad
    header = json.dumps({**meta, "arrays": table, "data_bytes": offset, "crc32": crc}).encode()
    fh.write(MAGIC + struct.pack("<Q", len(header)) + header + b"\0" * (_aligned(24 + len(header)) - 24 - len(header)))
    for raw, pad in flat:
        fh.write(raw)
        fh.write(b"\0" * pad)


def read_header(path: Path) -> tuple[dict[str, Any], memoryview]:
    """(the header, the data as a read-only mapping of the file). ValueError when the file is not one of
    these or its length does not match its header (truncated)."""
    with open(path, "rb") as fh:
        head = fh.read(24)
        if len(head) < 24 or head[:16] != MAGIC:
            raise ValueError("not a saved fit (wrong magic bytes)")
        n = struct.unpack("<Q", head[16:])[0]
        if n > 1 << 24:
            raise ValueError(f"header of {n} bytes")
        try:
            meta = json.loads(fh.read(n))
        except RecursionError as err:                 # a header nested beyond the parser's depth
            raise ValueError(f"header unreadable: {err}") from err
        if not isinstance(meta, dict):
            raise ValueError("header is not a mapping")
        start = _aligned(24 + n)
        size = os.fstat(fh.fileno()).st_size
        if size != start + int(meta.get("data_bytes", -1)):
            raise ValueError(f"{size} bytes, the header describes {start + int(meta.get('data_bytes', 0))}")
        st = os.fstat(fh.fileno())
        ident = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
        with _MAPPED_LOCK:
            mm = _MAPPED.get(ident)
            if mm is None:
                mm = _MAPPED[ident] = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    return meta, memoryview(mm)[start:]


def read_arrays(meta: dict[str, Any], data: memoryview) -> dict[str, np.ndarray]:
    """The arrays of a file read by :func:`read_header`, after checking the data's CRC-32 (ValueError when it
    differs): those matching :data:`SHARED` as read-only views of the mapping, the others copied."""
    if zlib.crc32(data) != meta.get("crc32"):
        raise ValueError("checksum mismatch (the file was damaged)")
    out: dict[str, np.ndarray] = {}
    for name, spec in meta["arrays"].items():
        dtype, shape = np.dtype(spec["dtype"]), tuple(int(v) for v in spec["shape"])
        count = int(np.prod(shape, dtype=np.int64))
        if dtype.hasobject or spec["offset"] + count * dtype.itemsize > len(data):
            raise ValueError(f"array {name!r} ({spec}) is outside the data")
        a = np.frombuffer(data, dtype, count, int(spec["offset"])).reshape(shape) if count else np.zeros(shape, dtype)
        out[name] = a if SHARED.fullmatch(name) else a.copy()
    return out


def fit_positioner(pos: Positioner, rm: RadioMap, store: FitStore | None = None, log: Log = _no_log, *,
                   refit: bool = False) -> Positioner:
    """``pos.fit(rm)``, except that with a ``store`` each powed k-NN part is loaded from its saved fit when
    one matches (unless ``refit``), and a part fitted is saved (bounded by the store's floor plans, read
    here when the part has none yet). Powed k-NN parts then drop what only the
    fit needed (:meth:`PowedKnn.release_fit_data`). The fixes are those of ``pos.fit(rm)``."""
    for index, part in enumerate(_leaves(pos)):
        if not isinstance(part, PowedKnn):
            part.fit(rm)
            continue
        if store is not None and not refit and store.load(part, index, rm, log):
            continue
        if store is not None and store.floor_plans is not None and part.walkable is None:
            part.walkable = load_floor_plans(store.floor_plans)[0]     # not parsed while a saved fit served
        if store is not None and store.floor_plans is None and part.walkable is not None:
            raise ConfigError("a positioner bounded by floor plans and a fit store without them: its fit would be "
                              "saved under the wrong key")
        t0 = time.thread_time()
        part.fit(rm)
        part.release_fit_data()
        if store is not None:
            log("info", f"fitted the radio map ({rm.n_scans} scans) in {time.thread_time() - t0:.1f} s CPU")
            store.save(part, index, log)
    if store is not None and not store.map_is_current():
        store.save_map(rm, log)
    release_free_memory()
    return pos


def release_free_memory() -> None:
    """Hand the heap's free pages back to the system (glibc ``malloc_trim``; elsewhere nothing): the fit's
    temporaries, freed, otherwise stay in the process's resident memory."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
