"""Shared fixtures: dataset location, per-test ROS domain, seeded RNG."""
from __future__ import annotations

import itertools
import os
import signal
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
from hypothesis import settings

# Property tests are derandomised (a fixed seed per test) so a run does not depend on luck;
# HYPOTHESIS_PROFILE=explore searches afresh when hunting for new counterexamples.
settings.register_profile("default", derandomize=True, deadline=None, print_blob=True)
settings.register_profile("explore", deadline=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

ROOT = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("INDOOR_LOC_DATASETS", ROOT.parent / "shared" / "datasets"))

# DDS traffic stays on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


def dataset(name: str) -> Path:
    """Path of a shared dataset, or skip the test with a clear reason when it is absent."""
    p = DATASETS / name
    if not p.exists():
        pytest.skip(f"dataset {name!r} not found at {p} (set INDOOR_LOC_DATASETS or put ../shared beside the repo)")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


#: ROS domain ids of one xdist worker (a two-worker run uses 24 from INDOOR_LOC_DOMAIN_BASE, so
#: bases 25 apart never share one), and this worker's turn through them (starting where the
#: process id says, so two runs one after the other do not begin on the same domain).
_DOMAINS_PER_WORKER = 12
_DOMAIN_TURN = itertools.count(os.getpid() % _DOMAINS_PER_WORKER)
_MARKS = itertools.count()


#: Environment variable that marks the processes a DDS test started (children inherit it, and so do
#: their children, also when a bring-up puts them in process groups of their own).
_TEST_MARK = "INDOOR_LOC_TEST_PROCESS"


def _processes_marked(mark: str) -> list[int]:
    """Live processes (other than this one) whose environment holds ``_TEST_MARK=mark`` (Linux /proc)."""
    needle = f"{_TEST_MARK}={mark}".encode()
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if needle in (d / "environ").read_bytes().split(b"\0"):
                found.append(int(d.name))
        except OSError:
            continue
    return found


@pytest.fixture
def ros_domain(monkeypatch) -> Iterator[int]:
    """A ROS_DOMAIN_ID of its own for a test that talks DDS, so parallel runs don't cross-talk.
    Child processes inherit it through the environment. A process the test started and left
    running (a test that failed before it could stop it) is killed when the test ends, with a
    warning, so it cannot talk to a later test that gets the same domain."""
    # INDOOR_LOC_DOMAIN_BASE moves the whole range, so suites run side by side on one machine
    # (e.g. two checkouts) do not share domains; each xdist worker takes its own 12 ids, in turn:
    # a domain is used again only 12 DDS tests later, so a process a previous test left still
    # stopping (or a participant still being forgotten by DDS) cannot talk to the next test.
    first = int(os.environ.get("INDOOR_LOC_DOMAIN_BASE", "1"))
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    base = first + (int(worker[2:]) if worker[2:].isdigit() else 0) * _DOMAINS_PER_WORKER
    # Fast DDS refuses domain ids above 232 (its port numbers overflow): wrap into 1..232.
    domain = 1 + (base - 1 + next(_DOMAIN_TURN) % _DOMAINS_PER_WORKER) % 232
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    mark = f"{os.getpid()}-{domain}-{next(_MARKS)}"
    monkeypatch.setenv(_TEST_MARK, mark)
    yield domain
    if not Path("/proc/self/environ").exists():
        return
    left = _processes_marked(mark)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if left:
        warnings.warn(f"killed {len(left)} process(es) the test left running in ROS domain {domain}: {left}",
                      stacklevel=1)
