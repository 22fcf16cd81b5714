"""WiFi positioning method registry: ``make_positioner(name, params) -> Positioner``.

Names: ``wknn`` (:mod:`indoor_loc.wifi.wknn`), ``pathloss`` (:mod:`indoor_loc.wifi.pathloss`),
``coverage`` (:mod:`indoor_loc.wifi.coverage`), ``powed`` (:mod:`indoor_loc.wifi.powed_knn`: ages, AP
weights, floor detection). Modules are imported lazily, so a method whose
module is missing or broken fails only when it is asked for (with a ConfigError saying so).
"""
from __future__ import annotations

import importlib
from typing import Any, Mapping

from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.measurements import Fix
from indoor_loc.wifi.types import Positioner, RadioMap, WifiScan

#: name -> (module, positioner class, params class)
METHODS: dict[str, tuple[str, str, str]] = {
    "wknn": ("indoor_loc.wifi.wknn", "Wknn", "WknnParams"),
    "pathloss": ("indoor_loc.wifi.pathloss", "PathLoss", "PathLossParams"),
    "coverage": ("indoor_loc.wifi.coverage", "CoverageArea", "CoverageParams"),
    "powed": ("indoor_loc.wifi.powed_knn", "PowedKnn", "PowedKnnParams"),
}


def _load(name: str) -> tuple[type, type]:
    try:
        module, cls, pcls = METHODS[name]
    except KeyError as err:
        raise ConfigError(f"unknown WiFi positioning method {name!r}; expected one of {sorted(METHODS)}") from err
    try:
        mod = importlib.import_module(module)
        return getattr(mod, cls), getattr(mod, pcls)
    except (ImportError, AttributeError) as err:
        raise ConfigError(f"WiFi method {name!r} is not available ({module}.{cls}): {err}") from err


def params_class(name: str) -> type:
    """The Params dataclass of method ``name`` (ConfigError if unknown/unavailable)."""
    return _load(name)[1]


def available_methods() -> list[str]:
    """Registered methods whose module imports."""
    out = []
    for name in METHODS:
        try:
            _load(name)
        except ConfigError:
            continue
        out.append(name)
    return out


def make_params(name: str, params: Mapping[str, Any] | None = None) -> Any:
    """The validated Params object of method ``name`` from a dict (unknown keys -> ConfigError)."""
    return params_from_dict(params_class(name), dict(params or {}))


def make_positioner(name: str, params: Any = None) -> Positioner:
    """An unfitted positioner ``name`` built from ``params``: its Params object, or a dict of its
    Params fields (unknown keys -> ConfigError)."""
    cls, pcls = _load(name)
    if isinstance(params, pcls):
        return cls(params)
    return cls(params_from_dict(pcls, dict(params or {})))


#: The WKNN setting measured best on PUTMC (``indoor-loc bench wifi``: 2.64 m mean against the paper
#: setting's 2.86 m; RMS of RSS differences over shared APs, more than 60 % shared both ways, k = 3).
WKNN_BEST = {"k": 3, "shared_threshold": 0.6, "shared_strict": True, "error_type": "rms"}


class FallbackPositioner(Positioner):
    """``primary`` first; a scan it declines goes to ``fallback`` (e.g. WKNN, then powed k-NN, which
    positions any scan sharing one AP with the map). A fallback fix carries
    ``info["fallback_from"]`` = the primary's reason; if both decline, the fallback's reason is
    returned prefixed ``fallback_``."""

    def __init__(self, primary: Positioner, fallback: Positioner) -> None:
        self.primary = primary
        self.fallback = fallback
        self.name = f"{primary.name}+{fallback.name}"

    def fit(self, radio_map: RadioMap) -> "FallbackPositioner":
        self.primary.fit(radio_map)
        self.fallback.fit(radio_map)
        return self

    def locate(self, scan: WifiScan) -> Fix:
        fix = self.primary.locate(scan)
        if fix.ok:
            return fix
        fb = self.fallback.locate(scan)
        if fb.ok:
            fb.info["fallback_from"] = fix.reason
            return fb
        from dataclasses import replace
        return replace(fb, reason=f"fallback_{fb.reason}")


def make_chain(name: str, params: Any = None, fallback: str = "",
               fallback_params: Any = None) -> Positioner:
    """``make_positioner(name, params)``, wrapped in a :class:`FallbackPositioner` when ``fallback``
    names a method ("" = none)."""
    pos = make_positioner(name, params)
    if not fallback:
        return pos
    return FallbackPositioner(pos, make_positioner(fallback, fallback_params))


def recommended_params(rm: RadioMap, floor_plans: str = "") -> dict[str, Any]:
    """``wifi_fix_node`` parameters the importers and ``radiomap build`` write for radio map ``rm``:
    powed k-NN when the map carries reading ages or several floors (phone traces with cached
    results, multi-storey sites: ``indoor-loc bench wifi --dataset ms_site2``), else the best WKNN
    measured on PUTMC with powed k-NN as fallback, so every scan sharing an AP with the map gets a fix
    (``indoor-loc bench wifi``: 347 of 347 PUTMC scans, 2.65 m mean). With ``floor_plans`` (a
    directory of floor plans, as ``indoor-loc import ms-indoor`` writes) powed k-NN also extrapolates
    its radio map inside the plans with the path-loss field (``field_weight``
    :data:`~indoor_loc.wifi.radio_field.PLAN_FIELD_WEIGHT`; ms_site2: better on every floor)."""
    import numpy as np
    from indoor_loc.wifi.radio_field import PLAN_FIELD_WEIGHT
    several_floors = len(np.unique(np.asarray(rm.z_m, float))) > 1
    field: dict[str, Any] = {"floor_plans": floor_plans} if floor_plans else {}
    powed = {"field_weight": PLAN_FIELD_WEIGHT} if floor_plans else None
    if rm.age_ms is not None or several_floors:
        return {"method": "powed", **field, **({"powed": powed} if powed else {})}
    return {"method": "wknn", "fallback": "powed", "wknn": dict(WKNN_BEST), **field,
            **({"powed": powed} if powed else {})}
