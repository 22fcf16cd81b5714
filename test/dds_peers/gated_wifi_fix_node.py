"""``wifi_fix_node`` whose radio-map fit waits for a gate file, so a test sees the node while it fits
(deterministically, whatever the machine's load). ``GATE=/path python gated_wifi_fix_node.py
--ros-args ...``: the fit starts once ``/path`` exists; if the file says ``fail``, the fit raises.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from indoor_loc.errors import MapError
from indoor_loc.nodes.wifi_fix_node import main
from indoor_loc.pipeline.wifi_fix_stage import WifiFixStage

_real_fit = WifiFixStage.fit_positioner


def _gated_fit(self, rm):
    gate = Path(os.environ["GATE"])
    while not gate.exists():
        time.sleep(0.02)
    if gate.read_text().strip() == "fail":
        raise MapError("the map's AP table does not match its RSS matrix (test gate)")
    return _real_fit(self, rm)


WifiFixStage.fit_positioner = _gated_fit        # type: ignore[method-assign]

if __name__ == "__main__":
    sys.exit(main(sys.argv))
