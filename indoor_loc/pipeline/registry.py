"""Which stages exist: ``--nodes`` names of ``indoor-loc run`` / bring-up -> stage classes.

Each entry is ``name: "module:Class"`` (imported lazily so a missing optional dependency of one
stage does not break the others).
"""
from __future__ import annotations

import importlib

from indoor_loc.errors import ConfigError

STAGES: dict[str, str] = {
    "imu": "indoor_loc.pipeline.imu_stage:ImuStage",
    "wifi": "indoor_loc.pipeline.wifi_fix_stage:WifiFixStage",
    "wifi_scan": "indoor_loc.pipeline.wifi_scan_stage:WifiScanStage",
    "pdr_kf": "indoor_loc.pipeline.pdr_kf_stage:PdrKfStage",
    "backend": "indoor_loc.pipeline.backend_stage:BackendStage",
    "pf": "indoor_loc.pipeline.pf_stage:PfStage",
}


def stage_class(name: str) -> type:
    try:
        target = STAGES[name]
    except KeyError as err:
        raise ConfigError(f"unknown node {name!r}; expected one of {sorted(STAGES)}") from err
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)
