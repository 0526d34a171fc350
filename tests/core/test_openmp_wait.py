"""The OpenMP wait policy the commands choose before torch starts (executors.configure_openmp_wait)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from articulated_dataset.core import pool as E

SPIN = {"GOMP_SPINCOUNT": str(E.IDLE_MACHINE_SPIN_COUNT)}
PASSIVE = {"OMP_WAIT_POLICY": "PASSIVE"}


@pytest.mark.parametrize("threads, busy, n_cpus, want", [
    (2, 0.0, 2, SPIN),          # idle 2-core machine
    (2, 0.2, 2, SPIN),          # a shell's worth of work: within the tolerance
    (2, 0.3, 2, PASSIVE),       # 1.7 CPUs free for 2 threads
    (2, 1.0, 2, PASSIVE),       # one busy process beside it
    (2, 1.0, 4, SPIN),          # ... on a 4-core machine: 3 free
    (4, 1.0, 4, PASSIVE),
    (1, 0.9, 2, SPIN),          # one thread needs one free CPU
    (1, 1.8, 2, PASSIVE),
    (2, None, 2, PASSIVE),      # unknown load: the safe choice
])
def test_settings_follow_free_cpus(threads, busy, n_cpus, want):
    assert E.openmp_wait_settings(threads, busy, n_cpus) == want


def test_busy_cpus_is_a_share_of_the_machine():
    busy = E.busy_cpus_now(0.05)
    if busy is None:
        pytest.skip("neither /proc/stat nor a load average here")
    assert 0.0 <= busy <= max(os.cpu_count() or 1, os.getloadavg()[0]) + 1e-9


def _child(code: str, **env) -> dict:
    """Run ``code`` (which prints one JSON line) in a fresh interpreter without OpenMP settings but ``env``."""
    base = {k: v for k, v in os.environ.items() if k not in E.OPENMP_WAIT_VARIABLES}
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


CHOOSE = ("import json, os; from articulated_dataset.core.pool import configure_openmp_wait as c; r = c(2); "
          "print(json.dumps({'chosen': r, 'env': {k: os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')}}))")


def test_choice_is_set_in_the_environment():
    r = _child(CHOOSE)
    assert r["chosen"] in (SPIN, PASSIVE)
    for k, v in r["chosen"].items():
        assert r["env"][k] == v


@pytest.mark.parametrize("var, value", [("OMP_WAIT_POLICY", "ACTIVE"), ("GOMP_SPINCOUNT", "5")])
def test_a_users_setting_is_kept(var, value):
    r = _child(CHOOSE, **{var: value})
    assert r["chosen"] == {}
    assert r["env"][var] == value
    assert [k for k, v in r["env"].items() if v is not None] == [var]


@pytest.mark.slow
def test_too_late_once_torch_is_imported():
    pytest.importorskip("torch")
    r = _child("import json, torch; from articulated_dataset.core.pool import configure_openmp_wait as c; "
               "print(json.dumps(c(2)))")
    assert r == {}


@pytest.mark.slow
def test_commands_choose_before_torch_starts():
    """prepare_torch (train, predict, estimate, plan) sets a policy, then torch is imported."""
    pytest.importorskip("torch")
    r = _child("import json, os, sys; from articulated_dataset.cli.options import prepare_torch; "
               "before = 'torch' in sys.modules; prepare_torch(1); "
               "print(json.dumps({'before': before, 'env': [os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')]}))")
    assert r["before"] is False
    assert r["env"] in (["PASSIVE", None], [None, str(E.IDLE_MACHINE_SPIN_COUNT)])
