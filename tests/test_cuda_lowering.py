"""What the library's compiled programs become on a GPU, checked on this CPU (issue 44, item 1).

JAX lowers a program for CUDA without a GPU (``jit(f).trace(*args).lower(lowering_platforms=("cuda",))``). The
StableHLO text then shows what would run per matrix or on the host there:

* a cuSOLVER call on matrices with a side above ``CUSOLVER_BATCHED_MAX`` (32): cuSOLVER's batched Jacobi SVD and
  eigen solvers cover small matrices only, so a batch of larger ones becomes a loop of single-matrix calls;
* a host callback (``xla_ffi_python_gpu_callback`` and kin): the device waits on Python every call.

Each program is lowered at a batch of 1,000 (the shapes that matter are the matrices', not the batch's).
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import pytest

import selfid_jax as sj
from selfid_jax.identify import estimator as E
from selfid_jax.identify import refine as RF
from selfid_jax.identify.step import sample_step

CUSOLVER_BATCHED_MAX = 32
HOST = ("callback", "host")
B = 1000


def offenders(f, *args) -> list[str]:
    """The custom calls of ``f(*args)`` lowered for CUDA that run per matrix or on the host, one line each."""
    text = jax.jit(f).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
    found = []
    for line in text.splitlines():
        m = re.search(r"custom_call @([\w.]+)|call_target_name = \"([^\"]+)\"", line)
        if not m:
            continue
        target = m.group(1) or m.group(2)
        if any(h in target for h in HOST):
            found.append(f"host callback {target}")
        elif "cusolver" in target or "cublas" in target:
            shapes = re.findall(r"tensor<((?:\d+x)+)[a-z]", line)
            dims = [tuple(int(d) for d in s.strip("x").split("x")) for s in shapes]
            big = [d for d in dims if len(d) >= 3 and max(d[-2:]) > CUSOLVER_BATCHED_MAX]  # (batch, rows, cols)
            if big:
                found.append(f"{target} on {'x'.join(map(str, big[0]))}")
    return sorted(set(found))


def _state(n, m, capacity):
    state = E.init(n, m, capacity=capacity)
    key = jax.random.key(0)
    for k in range(capacity or 4):
        a, b = jax.random.normal(jax.random.fold_in(key, k), (2, max(n, m)))
        state = E.update(state, a[:n], b[:m])
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (B, *jnp.shape(x))), state)


@pytest.mark.parametrize("method, loss", [("closed_form", "l2"), ("optax", "l2"), ("optax", "huber")])
def test_the_self_id_step_runs_on_the_device(method, loss):
    """The per-sample step of Algorithm 1 and fit, every refinement, vmapped over 1,000 estimators (6 x 3, a
    64-sample buffer where the method reads one)."""
    capacity = 64 if RF.needs_samples(method, loss) else 0
    state = _state(6, 3, capacity)
    options = (("loss", loss),) if loss != "l2" else ()

    def step(s, d, v):
        return sample_step(s, d, v, 0.0, 0.05, method=method, options=options)

    assert offenders(jax.vmap(step), state, jnp.ones((B, 6)), jnp.ones((B, 3))) == []


def test_the_buffered_closed_form_solves_small_gram_matrices():
    """refine.closed_form on a 64-sample buffer: was pinv(V^T), a cuSOLVER SVD of a 3 x 64 matrix per estimator
    (cusolver_gesvdj_ffi on 1000x3x64 here, a loop of single-matrix SVDs on a GPU); now the Gram form
    (V^T V is 3 x 3)."""
    theta, V, J0 = jnp.ones((B, 64, 6)), jnp.ones((B, 64, 3)), jnp.zeros((B, 6, 3))
    assert offenders(jax.vmap(RF.closed_form), theta, V, J0) == []


def test_algorithm_1_runs_on_the_device():
    """sj.self_identify vmapped over 1,000 runs of a 3-actuator arm (12 iterations)."""
    A = jnp.array([[0.2, 0.05, 0.0], [-0.04, 0.15, 0.02], [0.01, 0.0, 0.1]])

    observe = sj.stateless(lambda key, d: A @ d)

    def run(key, m_a):
        return sj.self_identify(observe, key, m_a, 1e-6, n_act=3, task_dim=3, iters=12)

    keys = jax.random.split(jax.random.key(0), B)
    assert offenders(jax.vmap(run), keys, jnp.full((B,), 0.05)) == []
