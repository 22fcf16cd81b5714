"""Every topic a stage reads or writes is in the message contract (``indoor_loc/contract.py``), with
the contract's message type and QoS role, for every stage built from a simulated world's params."""
from __future__ import annotations

from pathlib import Path

import pytest

from indoor_loc.commands import contract as contract_cmd
from indoor_loc.contract import TOPICS, USER_TOPICS
from indoor_loc.params import load_params_file, params_for_node, params_from_dict
from indoor_loc.pipeline.registry import STAGES, stage_class


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from indoor_loc.commands.sim import generate
    from indoor_loc.sim.scenario import SimConfig
    out = tmp_path_factory.mktemp("contract_world")
    generate(out, SimConfig(walkers=1, duration_s=10.0, seed=3), quiet=True)
    return out


#: every stage with its world's params, and the parameters that change a stage's ports
CASES = [(name, {}) for name in sorted(STAGES)] + [
    ("backend", {"wifi_source": "fix"}), ("pf", {"wifi_update": "scan", "radiomap": "radiomap"})]


@pytest.mark.parametrize(("name", "overrides"), CASES,
                         ids=[n + "".join(f"-{v}" for v in o.values()) for n, o in CASES])
def test_every_port_of_every_stage_is_in_the_contract(world, name, overrides):
    cls = stage_class(name)
    values = params_for_node(load_params_file(world / "params.yaml"), cls.NODE_NAME, "/walker0")
    values = {**values, **{k: str(world / v) if k == "radiomap" else v for k, v in overrides.items()}}
    stage = cls(params_from_dict(cls.PARAMS, values), namespace="" if cls.MULTI_USER else "/walker0")
    ports = [*stage.inputs(), *stage.outputs()]
    user_ports = list(stage.user_outputs()) if cls.MULTI_USER else []
    assert ports or user_ports
    for port, table in [*((p, TOPICS) for p in ports), *((p, USER_TOPICS) for p in user_ports)]:
        assert port.topic in table, f"{name}: {port.topic} is not in the contract"
        spec = table[port.topic]
        assert (port.type, port.qos) == (spec.type, spec.qos), f"{name}: {port.topic}"


def test_contract_command_prints_the_per_user_topics(capsys):
    assert contract_cmd.main(None) == 0
    out = capsys.readouterr().out
    for name in [*TOPICS, *USER_TOPICS]:
        assert f"| `{name}` |" in out
