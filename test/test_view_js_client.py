"""The live view with the protocol's own reference client, ``@foxglove/ws-protocol`` from npm (what
Lichtblick and Foxglove build on), decoding every payload with ``@foxglove/rosmsg2-serialization``:
both subprotocol names, every channel subscribed the moment it is advertised, a 2D pose estimate
published, the global localisation service called and a parameter read (``test/js/foxglove_client.cjs``).

The npm packages are installed once per environment into ``<sys.prefix>/share/indoor_loc_test_npm``
(the venv); without ``node``/``npm`` or the npm registry the test is skipped and says why."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_view_protocol import start_view_and_pf

HERE = Path(__file__).parent
NPM_DIR = Path(os.environ.get("INDOOR_LOC_TEST_NPM_DIR", Path(sys.prefix) / "share" / "indoor_loc_test_npm"))
PACKAGES = ["@foxglove/ws-protocol@0.8.0", "@foxglove/rosmsg@5.0.5", "@foxglove/rosmsg2-serialization@3.1.0",
            "ws@8.23.0"]


@pytest.fixture(scope="module")
def node_modules() -> Path:
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are not installed: the @foxglove/ws-protocol client test needs them "
                    "(Debian/Ubuntu: sudo apt install nodejs npm)")
    modules = NPM_DIR / "node_modules"
    if not all((modules / p.rpartition("@")[0] / "package.json").is_file() for p in PACKAGES):
        NPM_DIR.mkdir(parents=True, exist_ok=True)
        try:
            subprocess.run(["npm", "install", "--prefix", str(NPM_DIR), "--no-audit", "--no-fund", "--silent",
                            *PACKAGES], check=True, timeout=300, capture_output=True, text=True)
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as err:
            pytest.skip(f"npm could not install {PACKAGES} into {NPM_DIR} (offline?): "
                        f"{getattr(err, 'stderr', '') or err}")
    return modules


@pytest.mark.timeout(150)
@pytest.mark.parametrize("subprotocol", ["foxglove.websocket.v1", "foxglove.sdk.v1"])
def test_reference_client_subscribes_decodes_publishes_and_calls(ros_domain, tmp_path, node_modules, subprotocol):
    pf, view, url = start_view_and_pf(tmp_path)
    try:
        run = subprocess.run(["node", str(HERE / "js" / "foxglove_client.cjs"), url, subprotocol, "90"],
                             capture_output=True, text=True, timeout=120,
                             env={**os.environ, "NODE_PATH": str(node_modules)})
    finally:
        view.stop()
        pf.stop()
    assert run.returncode == 0, f"{run.stdout}\n{run.stderr}\n{view.output()}"
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["subprotocol"] == subprotocol
    assert {"clientPublish", "services", "parameters"} <= set(out["capabilities"])
    assert out["statuses"] == [] and out["decodeErrors"] == []       # no "Unknown channel ID", all decoded
    for topic in ("/view/building", "/alice/pf/pose", "/diagnostics"):
        assert out["received"].get(topic, 0) >= 1, (topic, out["received"])
    assert set(out["received"]) <= set(out["channels"])
    assert out["published"] >= 1 and out["poseSeen"] is not None       # initialpose re-initialised tll_pf
    assert out["serviceResponse"] == {"callId": 7, "encoding": "cdr", "bytes": out["serviceResponse"]["bytes"]}
    assert out["parameters"] == [{"name": "/alice/tll_pf.n_particles", "value": 300}]
