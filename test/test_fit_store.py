"""Saved fits of the WiFi positioner (indoor_loc.wifi.fit_store): loaded bit for bit, refused when stale or
corrupt, and the wifi_fix stage / `indoor-loc radiomap fit` using them."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml

from indoor_loc.params import params_from_dict
from indoor_loc.pipeline.wifi_fix_stage import WifiFixParams, WifiFixStage
from indoor_loc.wifi.fit_store import FitStore, fit_positioner, read_arrays, read_header, write_arrays
from indoor_loc.wifi.powed_knn import PowedKnn
from indoor_loc.wifi.powed_knn_params import PowedKnnParams
from indoor_loc.wifi.radiomap import add_fingerprints, empty_radiomap, load_radiomap, save_radiomap
from indoor_loc.wifi.types import WifiScan
from indoor_loc.wifi.walkable import load_floor_plans

SIZE = (40.0, 24.0)
FLOORS = {"F1": 0.0, "F2": 5.0}
N_APS = 24


def _write_plans(root: Path) -> Path:
    """Both floors' plans in the importer's layout: the outline with one shop in it."""
    def poly(x0, y0, x1, y1):
        return {"type": "Feature", "properties": {},
                "geometry": {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}}
    for name, z in FLOORS.items():
        d = root / name
        d.mkdir(parents=True)
        (d / "map.yaml").write_text(yaml.safe_dump({"floor": name, "z_m": z, "width_m": SIZE[0],
                                                    "height_m": SIZE[1], "frame_id": "map"}))
        feats = [poly(0, 0, 400, 240), poly(150, 150, 250, 240)]
        (d / "geojson_map.json").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return root


def _world(seed: int = 5):
    """Log-distance APs on two floors (a slab costs 15 dB) and a scan maker with cached readings (ages)."""
    rng = np.random.default_rng(seed)
    ap = np.column_stack([rng.uniform(0, SIZE[0], N_APS), rng.uniform(0, SIZE[1], N_APS)])
    ap_z = np.where(np.arange(N_APS) % 2 == 0, 0.0, 5.0)
    p0 = rng.uniform(-40, -30, N_APS)
    bssids = [f"02:00:00:00:03:{i:02x}" for i in range(N_APS)]

    def scans(xy, z, t0):
        d = np.sqrt(((xy[:, None, :] - ap[None]) ** 2).sum(-1) + 1.0)
        r = p0[None] - 30 * np.log10(d) - 15 * (np.abs(ap_z[None] - z) > 0) + rng.normal(0, 4, (len(xy), N_APS))
        out = []
        for i, row in enumerate(r):
            c = np.flatnonzero(row > -95)
            out.append(WifiScan(stamp_ns=t0 + i * 1_000_000_000, bssid=tuple(bssids[j] for j in c),
                                rssi_dbm=row[c], freq_mhz=np.full(len(c), 2437.0),
                                age_ms=rng.choice([0.0, 0.0, 1500.0, 9000.0], len(c))))
        return out
    return rng, scans


def _site(tmp_path: Path):
    """A two-floor radio map directory (walks at y = 4 and 10 per floor) and its floor plans; test scans
    off the walks (north of them, where only the plan-bounded field reaches)."""
    rng, scans = _world()
    rm = empty_radiomap()
    t = 0
    xs = np.arange(1.0, SIZE[0], 1.5)
    for name, z in FLOORS.items():
        for j, y in enumerate((4.0, 10.0)):
            pts = np.column_stack([xs, np.full(len(xs), y)])
            rm = add_fingerprints(rm, pts, scans(pts, z, t), f"{name}_walk{j}", z_m=z, floors={name: z})
            t += 100 * 10**9
    save_radiomap(rm, tmp_path / "radiomap")
    plans = _write_plans(tmp_path / "floors")
    test = []
    for z in FLOORS.values():
        pts = np.column_stack([rng.uniform(1, SIZE[0] - 1, 12), rng.uniform(2, 16, 12)])
        test += scans(pts, z, t)
        t += 100 * 10**9
    return tmp_path / "radiomap", plans, test


def _params(mapdir: Path, plans: Path, **kw) -> WifiFixParams:
    return params_from_dict(WifiFixParams, {"radiomap": str(mapdir), "method": "powed", "floor_plans": str(plans),
                                            "powed": {"field_weight": 0.05}, **kw})


def _fixes(pos, scans):
    return [pos.locate(s) for s in scans]


def _assert_same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.ok, x.reason) == (y.ok, y.reason)
        assert np.array_equal(x.xy, y.xy, equal_nan=True) and np.array_equal(x.cov, y.cov, equal_nan=True)
        assert (x.z, x.z_var) == (y.z, y.z_var)
        if x.ok:
            assert x.info["floor_p"] == y.info["floor_p"] and x.info["offset_db"] == y.info["offset_db"]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return _site(tmp_path_factory.mktemp("fitstore"))


def _logger():
    lines: list[tuple[str, str]] = []
    return lines, lambda level, text: lines.append((level, text))


def test_saved_fit_gives_the_fixes_of_a_fresh_fit_bit_for_bit(site, tmp_path, monkeypatch):
    mapdir, plans, scans = site
    rm = load_radiomap(mapdir)
    walkable, _ = load_floor_plans(plans)
    fresh = PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable).fit(rm)     # keeps its fit data
    assert fresh._prior is not None and len(fresh._floors) == 2 and len(fresh._views) == 4
    expect = _fixes(fresh, scans)
    assert sum(f.ok for f in expect) == len(scans)
    assert any(r >= fresh._n_map for f in expect for r in f.info["rows"])     # grid candidates are used
    assert len({f.z for f in expect}) == 2 and any(f.info["offset_db"] != 0 for f in expect)

    store = FitStore(mapdir, plans, tmp_path / "cache")
    lines, log = _logger()
    fitted = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store, log)
    assert fitted._prior is None and fitted._vals == []               # fit data released after the fit
    assert [lv for lv, _ in lines] == ["info"] * 3 and "saved the fitted radio map" in lines[1][1]
    assert "saved the radio map's arrays" in lines[2][1]
    _assert_same(_fixes(fitted, scans), expect)

    monkeypatch.setattr(PowedKnn, "fit", lambda self, rm: pytest.fail("fitted instead of loaded"))
    lines, log = _logger()
    loaded = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store, log)
    assert len(lines) == 1 and "loaded the fitted radio map" in lines[0][1]
    _assert_same(_fixes(loaded, scans), expect)
    assert loaded.calibration == fresh.calibration and loaded.calibration["scans"] > 10
    # twin views share their grid values after the load as after the fit
    assert loaded._views[2].parts[0][0] is not loaded._views[3].parts[0][0]
    assert len({id(rd) for v in loaded._views for rd, _, _ in v.parts}) == \
        len({id(rd) for v in fitted._views for rd, _, _ in v.parts})


def test_changed_map_plans_or_params_are_not_served_the_old_fit(site, tmp_path):
    mapdir, plans, scans = site
    work = tmp_path / "site"
    import shutil
    shutil.copytree(mapdir, work / "radiomap")
    shutil.copytree(plans, work / "floors")
    mapdir, plans = work / "radiomap", work / "floors"
    walkable, _ = load_floor_plans(plans)
    store = FitStore(mapdir, plans)                      # default: beside the map
    rm = load_radiomap(mapdir)
    fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store)
    files = sorted((mapdir / "fit_cache").glob("wifi_fit_*.fit"))
    assert len(files) == 1
    # other parameters: another file, fitted afresh
    lines, log = _logger()
    fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05, k=3), walkable=walkable), rm, store, log)
    assert "fitted the radio map" in lines[0][1] and len(list((mapdir / "fit_cache").glob("wifi_fit_*.fit"))) == 2
    # an edited plan: the saved fit is stale
    gj = plans / "F2" / "geojson_map.json"
    gj.write_text(gj.read_text().replace("150, 150", "160, 150"))
    lines, log = _logger()
    store = FitStore(mapdir, plans)
    walkable, _ = load_floor_plans(plans)
    pos = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store, log)
    assert "is stale" in lines[0][1] and "fitted the radio map" in lines[1][1]
    _assert_same(_fixes(pos, scans),
                 _fixes(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable).fit(rm), scans))
    # a grown map (same directory): stale again
    rm2 = add_fingerprints(rm, [[20.0, 7.0]], scans[:1], "more", z_m=0.0)
    save_radiomap(rm2, mapdir)
    lines, log = _logger()
    fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), load_radiomap(mapdir),
                   FitStore(mapdir, plans), log)
    assert "is stale" in lines[0][1]


def _fitting(site, tmp_path):
    """(map, test scans, a store in tmp_path/cache, a maker of the plan-bounded powed k-NN) on ``site``."""
    mapdir, plans, scans = site
    walkable, _ = load_floor_plans(plans)

    def make():
        return PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable)
    return load_radiomap(mapdir), scans, FitStore(mapdir, plans, tmp_path / "cache"), make


def _rewrite(path: Path, edit=None) -> None:
    """Write the saved file ``path`` again with its arrays (``edit(meta, arrays)`` first): a new file
    renamed over the old one, as the store writes."""
    meta, data = read_header(path)
    arrays = {k: np.array(v) for k, v in read_arrays(meta, data).items()}
    meta = {k: v for k, v in meta.items() if k not in ("arrays", "data_bytes", "crc32")}
    del data
    if edit is not None:
        edit(meta, arrays)
    tmp = path.with_suffix(".new")
    with open(tmp, "wb") as fh:
        write_arrays(fh, meta, arrays)
    tmp.replace(path)


@pytest.mark.parametrize("damage", ["truncated", "garbage", "bit_flip", "inconsistent", "wrong_format", "nested_header"])
def test_a_corrupt_saved_fit_is_refused_and_replaced(site, tmp_path, damage):
    rm, scans, store, make = _fitting(site, tmp_path)
    expect = _fixes(fit_positioner(make(), rm, store), scans)
    path = store.path(make(), 0)
    blob = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(blob[: len(blob) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00" * 100)
    elif damage == "bit_flip":                        # one bit of the grid's values: the checksum differs
        flipped = bytearray(blob)
        flipped[len(blob) - 1000] ^= 0x10
        path.write_bytes(bytes(flipped))
    elif damage == "nested_header":                   # a header nested beyond the JSON parser's depth
        header = b"[" * 100_000 + b"]" * 100_000
        path.write_bytes(blob[:16] + struct.pack("<Q", len(header)) + header)
    elif damage == "inconsistent":                    # the right key, but arrays that do not fit the map
        _rewrite(path, lambda meta, arrays: arrays.update(home=arrays["home"][:-1]))
    else:
        _rewrite(path, lambda meta, arrays: meta.update(version=99))
    lines, log = _logger()
    pos = fit_positioner(make(), rm, store, log)
    assert lines[0][0] == "warning" and str(path) in lines[0][1] and "refused" in lines[0][1]
    assert "fitted the radio map" in lines[1][1] and "saved" in lines[2][1]
    _assert_same(_fixes(pos, scans), expect)
    lines, log = _logger()
    _assert_same(_fixes(fit_positioner(make(), rm, store, log), scans), expect)    # the replacement loads
    assert "loaded" in lines[0][1]


def test_an_unwritable_cache_directory_is_logged_and_the_fit_still_used(site, tmp_path):
    mapdir, plans, scans = site
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    rm = load_radiomap(mapdir)
    lines, log = _logger()
    pos = fit_positioner(PowedKnn(PowedKnnParams()), rm, FitStore(mapdir, "", blocker / "cache"), log)
    assert lines[-1][0] == "warning" and "could not write the fit cache" in lines[-1][1]
    _assert_same(_fixes(pos, scans), _fixes(PowedKnn(PowedKnnParams()).fit(rm), scans))
    assert list(tmp_path.glob("**/*.tmp")) == []


def test_wifi_fix_stage_loads_the_saved_fit_and_gives_the_same_fixes(site, tmp_path, capsys):
    """Offline and live the stage fits the configured map once; a second stage loads it (fit_cache), one with
    fit_cache false neither reads nor writes it; a chain (WKNN + powed fallback) caches its powed part."""
    from msg_adapters.wifi_scan import scan_to_msg
    mapdir, plans, scans = site
    cache = tmp_path / "cache"

    def run(**kw):
        st = WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache), **kw))
        out = [st.process("wifi/scan", scan_to_msg(s), s.stamp_ns) for s in scans]   # the clock: the scans' time
        return [o[0][1] for o in out if o], capsys.readouterr().err
    plain, err = run(fit_cache=False)
    assert err == "" and not cache.exists()
    first, err = run()
    assert "saved the fitted radio map" in err and len(list(cache.glob("wifi_fit_*.fit"))) == 1
    second, err = run()
    assert "loaded the fitted radio map" in err and "fitted the radio map (" not in err
    diag = WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache))).extra_diagnostics()
    assert diag["fit.cache"].startswith(f"loaded {cache}/wifi_fit_")
    assert len(plain) == len(scans)
    for a, b, c in zip(plain, first, second):
        assert a.pose == b.pose == c.pose
    chain, err = run(method="wknn", fallback="powed")
    assert "saved" in err and len(list(cache.glob("wifi_fit_*.fit"))) == 2
    again, err = run(method="wknn", fallback="powed")
    assert "loaded" in err and [m.pose for m in again] == [m.pose for m in chain]


def test_a_start_with_a_saved_fit_parses_neither_map_nor_plans(site, tmp_path, monkeypatch, capsys):
    """The map's arrays saved from its files equal load_radiomap's; a stage whose fit is saved reads them and
    leaves the plans unparsed (it loads them if a fit is needed after all), with the same fixes."""
    from indoor_loc.pipeline import wifi_fix_stage
    from indoor_loc.wifi import fit_store
    from msg_adapters.wifi_scan import scan_to_msg
    mapdir, plans, scans = site
    cache = tmp_path / "cache"
    first = WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache)))
    assert "saved the radio map's arrays" in capsys.readouterr().err
    rm, saved = load_radiomap(mapdir), FitStore(mapdir, plans, cache).load_map()
    assert saved is not None
    for f in ("positions", "rssi_dbm", "freq_mhz", "scan_ids", "stamps_ns", "z_m", "age_ms"):
        a, b = getattr(rm, f), getattr(saved, f)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), f
    for f in ("bssids", "ssids", "source", "frame_id", "floors"):
        assert getattr(rm, f) == getattr(saved, f), f

    def refuse(*args, **kw):
        raise AssertionError("parsed although saved")
    monkeypatch.setattr(wifi_fix_stage, "load_radiomap", refuse)
    monkeypatch.setattr(wifi_fix_stage, "load_floor_plans", refuse)
    monkeypatch.setattr(fit_store, "load_floor_plans", refuse)
    second = WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache)))
    assert second.walkable is None and second.extra_diagnostics()["floor_plans"] == "2"
    msgs = [scan_to_msg(s) for s in scans]
    assert [second.process("wifi/scan", m, i) for i, m in enumerate(msgs)] == \
        [first.process("wifi/scan", m, i) for i, m in enumerate(msgs)]
    # other parameters: no saved fit, so the plans are parsed (a fit needs them)
    with pytest.raises(AssertionError, match="parsed although saved"):
        WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache), powed={"field_weight": 0.05, "k": 5}))
    # a fit needed after start-up (a refit) loads the deferred plans
    with pytest.raises(AssertionError, match="parsed although saved"):
        second.fit_positioner(second.radio_map, refit=True)
    # the saved fit damaged after a start that deferred the plans: refused, refitted within the plans
    monkeypatch.undo()
    third = WifiFixStage(_params(mapdir, plans, fit_cache_dir=str(cache)), fit_now=False)
    assert third._plans_deferred
    (fit,) = cache.glob("wifi_fit_*.fit")
    blob = bytearray(fit.read_bytes())
    blob[-100] ^= 1
    fit.unlink()
    fit.write_bytes(bytes(blob))
    pos = third.fit_positioner(third.radio_map)
    assert "checksum mismatch" in capsys.readouterr().err
    walkable, _ = load_floor_plans(plans)
    _assert_same(_fixes(pos, scans), _fixes(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable).fit(rm),
                                            scans))


def test_radiomap_fit_command_fits_ahead_of_time(site, tmp_path, capsys):
    from indoor_loc.cli import main
    mapdir, plans, _ = site
    params = tmp_path / "params.yaml"
    cache = tmp_path / "cache"
    params.write_text(yaml.safe_dump({"/**/wifi_fix_node": {"ros__parameters": {
        "radiomap": str(mapdir), "method": "powed", "floor_plans": str(plans), "fit_cache_dir": str(cache),
        "powed": {"field_weight": 0.05}}}}))
    assert main(["radiomap", "fit", "--params", str(params)]) == 0
    out = capsys.readouterr()
    assert "saved the fitted radio map" in out.out and len(list(cache.glob("wifi_fit_*.fit"))) == 1
    assert main(["radiomap", "fit", "--params", str(params)]) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(["radiomap", "fit", "--params", str(params), "--refit"]) == 0
    assert "saved the fitted radio map" in capsys.readouterr().out
    params.write_text(yaml.safe_dump({"/**/wifi_fix_node": {"ros__parameters": {"radiomap": str(mapdir),
                                                                                  "fit_cache": False}}}))
    assert main(["radiomap", "fit", "--params", str(params)]) == 2
    assert "fit_cache" in capsys.readouterr().err


def test_the_store_bounds_a_fit_by_its_plans_and_refuses_a_bounded_fit_without_them(site, tmp_path):
    """A part without a walkable area fitted with a store that has plans is bounded by them (a start with a
    saved fit leaves the plans unparsed, and a damaged file then needs a fit); the other way round the fit
    would be saved under a key without plans: ConfigError, nothing written."""
    from indoor_loc.errors import ConfigError
    mapdir, plans, scans = site
    rm = load_radiomap(mapdir)
    walkable, _ = load_floor_plans(plans)
    expect = _fixes(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable).fit(rm), scans)
    pos = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05)), rm, FitStore(mapdir, plans, tmp_path / "a"))
    assert pos.walkable is not None
    _assert_same(_fixes(pos, scans), expect)
    with pytest.raises(ConfigError, match="wrong key"):
        fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm,
                       FitStore(mapdir, "", tmp_path / "b"))
    assert not (tmp_path / "b").exists()                 # nothing was written


def _same_value(a, b, where: str) -> None:
    """a and b hold the same values (arrays bit for bit, sparse matrices by their arrays, objects by their
    attributes)."""
    from scipy import sparse
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), where
    elif sparse.issparse(a) or sparse.issparse(b):
        assert sparse.issparse(a) and sparse.issparse(b) and a.shape == b.shape, where
        a, b = sparse.csr_matrix(a), sparse.csr_matrix(b)
        for f in ("data", "indices", "indptr"):
            _same_value(getattr(a, f), getattr(b, f), f"{where}.{f}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same_value(x, y, f"{where}[{i}]")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same_value(a[k], b[k], f"{where}[{k!r}]")
    elif hasattr(a, "__dict__") and not callable(a):
        assert type(a) is type(b), where
        _same_value(vars(a), vars(b), where)
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"


def test_a_loaded_fit_holds_every_attribute_of_a_fitted_one(site, tmp_path):
    """Every attribute the positioner keeps after a fit (and release_fit_data) is restored by a load with the
    same value: state added to the fit but not to fitted_state()/load_fitted_state() fails here."""
    mapdir, plans, _ = site
    rm = load_radiomap(mapdir)
    walkable, _ = load_floor_plans(plans)
    store = FitStore(mapdir, plans, tmp_path / "cache")
    fitted = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store)
    loaded = fit_positioner(PowedKnn(PowedKnnParams(field_weight=0.05), walkable=walkable), rm, store)
    assert store.loaded
    a, b = vars(fitted), vars(loaded)
    assert a.keys() == b.keys()
    for k in a:
        if k in ("radio_map", "walkable"):
            assert a[k] is b[k] if k == "radio_map" else (a[k] is not None and b[k] is not None)
            continue
        _same_value(a[k], b[k], k)


def test_loads_of_one_file_share_one_mapping(site, tmp_path):
    """Stages of several users in one process (one walk per namespace) map a saved fit once: their arrays
    are views of the same memory, so the process's resident size counts those pages once; a file
    replaced under the same name is mapped anew."""
    rm, scans, store, make = _fitting(site, tmp_path)

    def grid_values(pos):
        return [rd.val for v in pos._views for rd, _, _ in v.parts]
    expect = _fixes(fit_positioner(make(), rm, store), scans)      # (a positioner learns its device offset)
    a, b = (fit_positioner(make(), rm, store) for _ in range(2))
    assert any(x.size for x in grid_values(a))
    assert all(np.shares_memory(x, y) for x, y in zip(grid_values(a), grid_values(b)) if x.size)
    _assert_same(_fixes(a, scans), expect)

    _rewrite(store.path(make(), 0))                   # as the store replaces a file: a new inode
    c = fit_positioner(make(), rm, store)
    assert not any(np.shares_memory(x, y) for x, y in zip(grid_values(a), grid_values(c)) if x.size)
    _assert_same(_fixes(c, scans), expect)


def test_damaged_saved_map_arrays_are_replaced_at_the_next_fit(site, tmp_path):
    """The map arrays' file is checked only when read: one refused there (a damaged byte) is written
    again by the next fit, even though the fit itself was loaded, and read at the start after."""
    rm, scans, store, make = _fitting(site, tmp_path)
    mapdir, plans, _ = site
    fit_positioner(make(), rm, store)
    path = store.map_path()
    blob = bytearray(path.read_bytes())
    blob[-8] ^= 0x10
    path.write_bytes(bytes(blob))

    again = FitStore(mapdir, plans, tmp_path / "cache")
    lines, log = _logger()
    assert again.load_map(log) is None and "unreadable" in lines[0][1] and not again.map_is_current()
    fit_positioner(make(), rm, again, log)
    assert any("loaded the fitted radio map" in t for _, t in lines)
    assert any("saved the radio map's arrays" in t for _, t in lines) and again.map_is_current()
    back = FitStore(mapdir, plans, tmp_path / "cache").load_map()
    assert back is not None and np.array_equal(back.rssi_dbm, rm.rssi_dbm, equal_nan=True)
