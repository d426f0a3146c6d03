"""ThreadPolicy: one threading policy for torch and numba (thread counts, numba's layer, OpenMP's
wait policy), its environment handling, and its place in TrainConfig / Trainer."""

import json
import os
import subprocess
import sys
import textwrap

import numba
import pytest
import torch

from polargs_plugin import threads as threads_mod
from polargs_plugin.backends.reference.trainer import TrainConfig
from polargs_plugin.threads import ThreadPolicy, available_cores, current_policy, numba_threads


@pytest.fixture
def restore_threads():
    """Put torch's and numba's thread counts (and the applied policy) back after the test."""
    torch_before, numba_before, applied = torch.get_num_threads(), numba.get_num_threads(), threads_mod._applied
    yield
    torch.set_num_threads(torch_before)
    numba.set_num_threads(numba_before)
    threads_mod._applied = applied


def test_defaults_and_validation():
    policy = ThreadPolicy()
    assert (policy.threads, policy.numba_layer, policy.wait_policy) == (None, "workqueue", "passive")
    assert policy.environment() == {"OMP_WAIT_POLICY": "PASSIVE", "NUMBA_THREADING_LAYER": "workqueue"}
    assert ThreadPolicy(numba_layer="default", wait_policy=None).environment() == {}
    with pytest.raises(ValueError, match="threads"):
        ThreadPolicy(threads=0)
    with pytest.raises(ValueError, match="numba_layer"):
        ThreadPolicy(numba_layer="openmp")
    with pytest.raises(ValueError, match="wait_policy"):
        ThreadPolicy(wait_policy="spin")


def test_default_count_is_the_available_cores_capped_by_torch(restore_threads):
    assert available_cores() == len(os.sched_getaffinity(0))
    assert ThreadPolicy(threads=3).resolved_threads() == 3
    torch.set_num_threads(1)  # as a pytest-xdist worker or an ablation cell does
    assert ThreadPolicy().resolved_threads() == 1
    torch.set_num_threads(available_cores())
    assert ThreadPolicy().resolved_threads() == available_cores()


def test_apply_sets_torch_and_numba_counts(restore_threads):
    applied = ThreadPolicy(threads=1).apply()
    assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
    assert applied.threads == applied.numba_threads == 1 and current_policy() is applied
    assert numba_threads() == 1
    limit = numba.config.NUMBA_NUM_THREADS
    applied = ThreadPolicy(threads=limit + 1).apply()
    assert torch.get_num_threads() == limit + 1 and numba.get_num_threads() == limit
    assert applied.numba_threads == limit and any("NUMBA_NUM_THREADS" in n for n in applied.notes)
    # torch lowered after the policy (an ablation cell): numba's kernels follow the lower count
    torch.set_num_threads(1)
    assert numba_threads() == 1


@numba.njit(parallel=True)
def _thread_ids(out):
    for i in numba.prange(out.shape[0]):
        out[i] = numba.get_thread_id()


def test_numba_scheduling_uses_the_policy_and_restores_the_settings(restore_threads):
    """Every numba kernel of the package runs inside numba_scheduling (the rasterizer, SSIM, L_dn,
    nearest-neighbour queries): the policy's count inside, a cap at NUMBA_NUM_THREADS, the chunk
    size inside, and the caller's count and chunk size back afterwards."""
    import numpy as np

    from polargs_plugin.threads import numba_scheduling

    limit = numba.config.NUMBA_NUM_THREADS
    ThreadPolicy(threads=1).apply()
    numba.set_num_threads(limit)
    previous_chunksize = numba.get_parallel_chunksize()
    ids = np.full(64, -1)
    with numba_scheduling(chunksize=4):
        assert numba.get_num_threads() == 1
        assert numba.get_parallel_chunksize() == 4
        _thread_ids(ids)
    assert (ids == 0).all()  # one thread did every iteration
    assert numba.get_num_threads() == limit
    assert numba.get_parallel_chunksize() == previous_chunksize
    with numba_scheduling(threads=limit + 5):
        assert numba.get_num_threads() == limit


def test_apply_environment_on_a_mapping():
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    notes = ThreadPolicy().apply_environment(env, override=False)
    assert env == {"OMP_WAIT_POLICY": "ACTIVE", "NUMBA_THREADING_LAYER": "workqueue"} and notes == []
    ThreadPolicy().apply_environment(env)
    assert env["OMP_WAIT_POLICY"] == "PASSIVE"


def test_late_environment_is_reported(monkeypatch):
    # torch is imported in this test process: OMP_WAIT_POLICY cannot reach its OpenMP runtime
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.delenv("NUMBA_THREADING_LAYER", raising=False)
    notes = ThreadPolicy().apply_environment()
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE" and any("OMP_WAIT_POLICY" in n for n in notes)
    assert ThreadPolicy(wait_policy=None).apply_environment() == []


def _run(*pieces: str, **env) -> dict:
    """Run the dedented pieces as one script in a fresh interpreter; its last line of output as JSON."""
    clean = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    code = "\n".join(textwrap.dedent(p) for p in pieces)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**clean, **env}, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


_KERNEL = """
    import numpy as np
    @numba.njit(parallel=True)
    def bump(a):
        for i in numba.prange(a.shape[0]):
            a[i] += 1.0
    bump(np.zeros(64))
"""


@pytest.mark.slow
def test_policy_applied_in_a_fresh_process_selects_the_layer_and_counts():
    out = _run(
        """
        import json, os, numba, torch
        from polargs_plugin.threads import ThreadPolicy
        applied = ThreadPolicy(threads=1).apply()
        """, _KERNEL, """
        print(json.dumps({"layer": numba.threading_layer(), "torch": torch.get_num_threads(),
                          "numba": numba.get_num_threads(), "wait": os.environ.get("OMP_WAIT_POLICY"),
                          "notes": applied.notes}))
        """
    )
    assert out["layer"] == "workqueue" and out["torch"] == 1 and out["numba"] == 1
    assert out["wait"] == "PASSIVE"
    assert any("torch was imported" in n for n in out["notes"])  # torch came first in this script


@pytest.mark.slow
def test_layer_already_started_is_reported_not_changed():
    out = _run(
        """
        import json, numba
        numba.config.THREADING_LAYER = "workqueue"
        """, _KERNEL, """
        from polargs_plugin.threads import ThreadPolicy
        applied = ThreadPolicy(numba_layer="omp").apply()
        print(json.dumps({"layer": numba.threading_layer(), "notes": applied.notes}))
        """
    )
    assert out["layer"] == "workqueue" and any("already 'workqueue'" in n for n in out["notes"])


@pytest.mark.slow
def test_environment_before_torch_gives_no_note():
    out = _run(
        """
        import importlib.util, json, os, sys
        # threads.py alone, without the package (whose __init__ imports torch)
        spec = importlib.util.spec_from_file_location("threads_only", %r)
        mod = sys.modules["threads_only"] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        notes = mod.ThreadPolicy().apply_environment()
        import torch
        print(json.dumps({"notes": notes, "wait": os.environ["OMP_WAIT_POLICY"], "torch": "torch" in sys.modules}))
        """ % threads_mod.__file__
    )
    assert out == {"notes": [], "wait": "PASSIVE", "torch": True}


def test_train_config_round_trip_with_a_policy():
    cfg = TrainConfig.cpu(threads=ThreadPolicy(threads=1, numba_layer="omp", wait_policy=None), log_every=5)
    data = cfg.to_dict()
    assert data["threads"] == {"threads": 1, "numba_layer": "omp", "wait_policy": None}
    assert TrainConfig.from_dict(json.loads(json.dumps(data))) == cfg
    assert TrainConfig.from_dict({k: v for k, v in data.items() if k != "threads"}).threads == ThreadPolicy()
    assert TrainConfig.from_dict({**data, "threads": cfg.threads}) == cfg  # a policy object passes through


def test_trainer_applies_its_policy(restore_threads, synthetic_views):
    from polargs_plugin.backends.reference.trainer import Trainer

    views = synthetic_views("glossy_plane_sphere", num_views=2, width=16, height=16)
    trainer = Trainer(views, TrainConfig.cpu(num_init_points=50, init_resolution=16, progress=False,
                                             threads=ThreadPolicy(threads=1)))
    assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
    assert trainer.threads is current_policy() and trainer.threads.threads == 1
