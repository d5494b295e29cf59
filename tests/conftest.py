"""Fixtures shared by the test modules (see tests/README.md).

- ``one_thread``: one torch intra-op thread while a module runs. Opt in per module with
  ``pytestmark = pytest.mark.usefixtures("one_thread")``: on two cores shared with other
  jobs, two threads made small batched solves 10-100x slower when the other core was busy
  (and only ~30 % faster when it was idle).
- ``rx160``, ``ur10``: the shipped robots with their parameters frozen
  (``requires_grad_(False)``), one per test module so a test that edits one cannot leak
  into another module.
- the seed sweep (``@pytest.mark.sweep``) is left out unless ``-m sweep`` asks for it.
- ``pin``: pinocchio, the FK / Jacobian / gravity oracle. Only a test that asks for it is
  skipped where pinocchio is not installed (a module-level ``importorskip`` would
  silently skip the module's gradient tests too).
"""

from __future__ import annotations

from collections.abc import Iterator
from types import ModuleType

import pytest
import torch

from hybrid_pk import Robot
from tests.helpers import RUN_SEED


def pytest_report_header(config: pytest.Config) -> str:
    return f"hidden-effect tests: HYBRID_PK_TEST_SEED={RUN_SEED} (set it to replay this run)"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The seed sweep (``@pytest.mark.sweep``) runs only when asked for: ``-m sweep``."""
    if "sweep" in (config.option.markexpr or ""):
        return
    sweep = [item for item in items if item.get_closest_marker("sweep")]
    if sweep:
        config.hook.pytest_deselected(items=sweep)
        items[:] = [item for item in items if not item.get_closest_marker("sweep")]


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _frozen(name: str) -> Robot:
    robot = Robot.from_urdf(name)
    robot.requires_grad_(False)
    return robot


@pytest.fixture(scope="module")
def rx160() -> Robot:
    """The shipped Stäubli RX160, parameters frozen."""
    return _frozen("rx160")


@pytest.fixture(scope="module")
def ur10() -> Robot:
    """The shipped UR10, parameters frozen."""
    return _frozen("ur10")


@pytest.fixture(scope="session")
def pin() -> ModuleType:
    """pinocchio (dev extra ``pin``); the requesting test skips where it is missing."""
    return pytest.importorskip("pinocchio")
