"""Freed memory handed back to the system during long fits (benchmark.core.memory)."""

from __future__ import annotations

import sys

import pytest
import torch

from benchmark.core import memory
from benchmark.protocols import step_rules
from benchmark.run.backends import common


def test_release_works_on_glibc_linux_and_is_a_no_op_elsewhere(monkeypatch):
    if sys.platform.startswith("linux"):
        import platform

        if platform.libc_ver()[0] == "glibc":
            assert memory.release_free_memory() is True
    monkeypatch.setattr(memory, "_trim", False)  # a C library without malloc_trim
    assert memory.release_free_memory() is False


def test_the_optimiser_releases_every_release_every_steps_and_its_values_do_not_change(monkeypatch):
    calls = []
    monkeypatch.setattr(step_rules, "release_free_memory", lambda: calls.append(1) or True)

    def fit():
        x = torch.tensor([3.0, -2.0], requires_grad=True)
        step_rules.optimise("test", [x], 2 * memory.RELEASE_EVERY + 7, 0.05, 0.1,
                            lambda step: ((x - 1.0).square().sum(), lambda: {}))
        return x.detach().clone()

    with_release = fit()
    assert len(calls) == 2
    monkeypatch.setattr(step_rules, "RELEASE_EVERY", 10 ** 9)
    assert torch.equal(fit(), with_release)


@pytest.mark.parametrize("fails", [False, True])
def test_a_worker_releases_after_each_unit_even_a_failed_one(monkeypatch, fails):
    calls = []
    monkeypatch.setattr(common, "release_free_memory", lambda: calls.append(1) or True)

    def execute(unit):
        if fails:
            raise ValueError("bad unit")
        return {"unit_id": unit}

    reply = common.execute_unit(execute, "u1")
    assert reply[0] == ("error" if fails else "ok")
    assert calls == [1]
