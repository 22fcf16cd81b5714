"""WiFi positioning method registry: ``make_positioner(name, params) -> Positioner``.

Names: ``wknn`` (:mod:`indoor_loc.wifi.wknn`), ``pathloss`` (:mod:`indoor_loc.wifi.pathloss`),
``coverage`` (:mod:`indoor_loc.wifi.coverage`). Modules are imported lazily, so a method whose
module is missing or broken fails only when it is asked for (with a ConfigError saying so).
"""
from __future__ import annotations

import importlib
from typing import Any, Mapping

from indoor_loc.errors import ConfigError
from indoor_loc.params import params_from_dict
from indoor_loc.wifi.types import Positioner

#: name -> (module, positioner class, params class)
METHODS: dict[str, tuple[str, str, str]] = {
    "wknn": ("indoor_loc.wifi.wknn", "Wknn", "WknnParams"),
    "pathloss": ("indoor_loc.wifi.pathloss", "PathLoss", "PathLossParams"),
    "coverage": ("indoor_loc.wifi.coverage", "CoverageArea", "CoverageParams"),
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
