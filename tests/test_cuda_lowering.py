"""What the library's compiled programs become on a GPU, checked on this CPU (issue 44, item 1).

JAX lowers a program for CUDA without a GPU (``jit(f).trace(*args).lower(lowering_platforms=("cuda",))``). The
StableHLO text then shows what would run per matrix or on the host there:

* a cuSOLVER call on matrices with a side above ``CUSOLVER_BATCHED_MAX`` (32): cuSOLVER's batched Jacobi SVD and
  eigen solvers cover small matrices only, so a batch of larger ones becomes a loop of single-matrix calls;
* a host callback (``xla_ffi_python_gpu_callback`` and kin): the device waits on Python every call.

Each program is lowered at a batch of 1,000 (the shapes that matter are the matrices', not the batch's), as the
library runs it at scale (the Model O's MJX settle at the hands' tests' batch of 16, to share their trace): the
self-ID step and Algorithm 1, the follow loop, a chunk of the valid-region map (ideal, servo and dynamic plants),
the ablation's estimators (E-KM included), the Model O's settle and the articulated rollout, with short horizons
(lowering does not unroll a scan or a while loop, so the horizon does not change the program's calls).

The host-bound backends are known and asserted as such: the Model O's ``native`` backend and the articulated
rollout's ``native`` backend (the shipped ``configs/articulated/articulated.yaml``: its spring grasp runs on native
MuJoCo only) step MuJoCo on the host through ``jax.pure_callback``. A CPU-only JAX cannot lower a host callback
for CUDA (it needs the GPU client), so :func:`offenders` finds callbacks in the program's jaxpr as well.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import subjaxprs

import selfid_jax as sj
from selfid_jax.identify import estimator as E
from selfid_jax.identify import refine as RF
from selfid_jax.identify.step import sample_step

# a CI check of what a GPU would run, not a behaviour a change to the numerics would break: the slow tier (13 s of
# tracing and lowering, 25 s with the MJX programs)
pytestmark = pytest.mark.slow

CUSOLVER_BATCHED_MAX = 32
HOST = ("callback", "host")
B = 1000


def _host_primitives(jaxpr) -> set[str]:
    """Names of the host-callback primitives (``pure_callback``, ``io_callback``, ...) anywhere in ``jaxpr``."""
    found = {f"host callback {e.primitive.name}" for e in jaxpr.eqns if any(h in e.primitive.name for h in HOST)}
    for sub in subjaxprs(jaxpr):
        found |= _host_primitives(sub)
    return found


def offenders(f, *args) -> list[str]:
    """The custom calls of ``f(*args)`` lowered for CUDA that run per matrix or on the host, one line each.

    Host callbacks are read off the jaxpr too: without a GPU, lowering one for CUDA raises (``the platform for
    the specified backend cpu is different from the lowering platform cuda``); a program that has one is then
    reported by its callbacks alone. An already jitted ``f`` is traced as it is (its trace cache: a test that
    called it with the same shapes in this process has traced it already)."""
    traced = (f if hasattr(f, "trace") else jax.jit(f)).trace(*args)
    host = _host_primitives(traced.jaxpr.jaxpr)
    try:
        text = traced.lower(lowering_platforms=("cuda",)).as_text()
    except ValueError as exc:
        if host and "different from the lowering platform" in str(exc):
            return sorted(host)
        raise
    found = list(host)
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


# ------------------------------------------------------------------ the programs the experiments run at scale

STEPS = 10  # control steps: the loops are scans / while loops, lowered once whatever their length
slow_mjx = pytest.mark.slow  # tracing an MJX step takes 3-5 s (as every MJX test, in the slow tier)


def rows(x):
    """``x`` repeated as ``B`` rows (a batch axis first), as the sweeps pass their parameters."""
    return np.broadcast_to(np.asarray(x), (B, *np.shape(x)))


@pytest.fixture(scope="module")
def ur5e_setup():
    """The UR5e (position task), a star path, a start configuration and the controller protocol, as rows."""
    from selfid_jax import control
    from selfid_jax.control import paths
    from selfid_jax.systems import ur5e

    system = ur5e(task_dim=3)
    q0 = np.asarray(system.sample_configs(jax.random.key(0), 1)[0])
    controller = jax.tree.map(rows, control.ControllerParams(max_step=0.004, tol=0.001))
    return system, paths.star(size=0.05, dim=3), q0, controller


def test_the_follow_loop_runs_on_the_device(ur5e_setup):
    """control.follow with the true inverse Jacobian on the UR5e, vmapped over 1,000 start configurations: no
    custom call at all (the 3 x 6 inverse is solved in plain HLO)."""
    from selfid_jax import control

    system, path, q0, controller = ur5e_setup

    def one(q, c):
        return control.follow(system, control.true_inverse(system), path, q, c, steps=STEPS)

    assert offenders(jax.vmap(one), rows(q0), controller) == []


@pytest.mark.parametrize("plant", ["ideal", "servo", pytest.param("dynamic", marks=slow_mjx)])
def test_a_valid_region_chunk_runs_on_the_device(ur5e_setup, plant):
    """One chunk of the valid-region map (experiments/valid_region.py: its compute vmapped over rows, the
    program runner.sweep runs per chunk) on the UR5e: the ideal loop, the servo plant with every non-ideality
    (latency traced under a static bound, noise, dropout, lag, deadband) and the dynamic plant (the arm's MJX
    physics; cusolver_potrf_ffi on 1000 x 6 x 6, MJX's Newton solver)."""
    from selfid_jax.experiments import valid_region as VR

    from selfid_jax.control import realism as RL

    system, path, q0, controller = ur5e_setup
    static = VR.Static(system, path, STEPS)
    params = VR.Params(eps_limit=rows(1.5), key=rows(jax.random.key_data(jax.random.key(0))), q0=rows(q0),
                       controller=controller)
    if plant != "ideal":
        real = RL.Realism(period=0.008, latency=1, noise_pos=1e-4, noise_rot=1e-3, dropout=0.1, servo_tau=0.02,
                          deadband=1e-4)
        params = params._replace(realism=jax.tree.map(rows, real._replace(latency=np.int32(1))))
        static = static._replace(max_latency=2)
    if plant == "dynamic":
        from selfid_jax.systems.dynamic import dynamic_ur5e

        arm = dynamic_ur5e(gravcomp=1.0).with_servo(kp=2000.0, kv=100.0)
        static = static._replace(plant=RL.dynamic_plant(arm, 4))
    assert offenders(VR.EXPERIMENT.batched(static), params) == []


def _ablation_params(q0, n_act, controller):
    from selfid_jax.experiments import ablation as AB

    return AB.Params(key=rows(jax.random.key_data(jax.random.key(0))), q0=rows(q0), pose_noise=rows(1e-3),
                     rot_noise=rows(0.0), m_a=rows(np.full(n_act, 0.03)), eps=rows(0.5), eps_rel=rows(0.0),
                     controller=controller)


def test_the_ablation_estimators_run_on_the_device(ur5e_setup):
    """The ablation's compute (experiments/ablation.py: one self-ID stream fed to every method, each estimate
    followed at two checkpoints) with the true inverse, ours, direct, Broyden, RLS, Kalman and the particle
    filter in one program on the UR5e, vmapped over 1,000 streams (Kalman: cusolver_potrf_ffi on 1000 x 6 x 6)."""
    from selfid_jax.experiments import ablation as AB

    from selfid_jax import baselines

    system, path, q0, controller = ur5e_setup
    methods = tuple(baselines.make(m) for m in ("true", "ours", "direct", "broyden", "rls", "kalman", "particle"))
    static = AB.Static(system, path, STEPS, iters=8, checkpoints=(1, 7), methods=methods)
    assert offenders(AB.EXPERIMENT.batched(static), _ablation_params(q0, 6, controller)) == []


def test_the_ablation_ekm_runs_on_the_device(ur5e_setup):
    """The ablation's E-KM rows (experiments/common/ekm.py: their own code path, a GP folded over the stream and
    the Eq. 10-11 QP rollout), fixed and online as configs/ablation/ablation_ekm_two_link.yaml runs them,
    on the 2-link arm at 40 iterations (a GP basis of 80: updated without a solver on it; the QP's
    cusolver_getrf_ffi is on 2 x 2 matrices)."""
    from selfid_jax.experiments import ablation as AB
    from selfid_jax.experiments.common import ekm as AE

    from selfid_jax.control import paths
    from selfid_jax.systems import two_link

    _, _, _, controller = ur5e_setup
    system, iters = two_link(), 40
    nominal = {"scale": [1.2, 0.8], "offset": [0.1, -0.1]}
    cfg = AB.AblationConfig(
        system="two_link", iterations=[2, iters], n_configs=1, n_trials=1, pose_noise=[0.0], rot_noise=[0.0], eps=0.5,
        path={"kind": "star", "size": 0.05},
        methods=[{"name": f"ekm {mode}", "method": "ekm", "options": {"mode": mode}, "nominal": nominal}
                 for mode in ("fixed", "online")])
    groups = AE.groups(system, cfg.methods, iters)
    assert len(groups) == 2 and AE.capacity(iters) > CUSOLVER_BATCHED_MAX
    static = AB.Static(system, paths.star(size=0.05, dim=2), STEPS, iters=iters, checkpoints=(1, iters - 1),
                       methods=(None, None), ekm=groups)
    params = _ablation_params(np.array([0.4, 1.2]), 2, controller)
    assert offenders(AB.EXPERIMENT.batched(static), params) == []


@pytest.fixture(scope="module")
def model_o_commands():
    from selfid_jax.systems.hands import model_o_hand as mo

    return rows(mo.model_o_home())


def test_the_model_o_kinematic_settle_runs_on_the_device(model_o_commands):
    """The Model O's default backend (Newton on the equilibrium equations): its pose and its implicit-function
    Jacobian, vmapped over 1,000 tendon commands (cusolver_getrf_ffi and cusolver_syevd_ffi on 1000 x 21 x 21:
    within the batched solvers' 32)."""
    from selfid_jax.systems.hands import model_o_hand as mo

    hand = mo.model_o(backend="kinematic")
    assert offenders(jax.vmap(hand.pose), model_o_commands) == []
    assert offenders(jax.vmap(hand.jacobian), model_o_commands) == []


@slow_mjx
@pytest.mark.xdist_group("model_o_mjx")  # on the worker that runs test_model_o.py's MJX test: one trace for both
def test_the_model_o_mjx_settle_runs_on_the_device(poses, mjx_batch):
    """The Model O settled in MJX: its pose (cusolver_potrf_ffi on 16 x 12 x 12, MJX's Newton solver), vmapped
    over the hands' tests' MJX batch of 16 commands through the poses fixture, the very program test_model_o.py
    runs, so this process traces it once (MJX tracing is most of the cost; the calls are per matrix whatever the
    batch, and the batch of 1,000 lowers to the same calls). Its forward-mode Jacobian is left out: the same
    calls, 13 s to trace."""
    from selfid_jax.systems.hands import model_o_hand as mo

    commands = jnp.asarray(np.broadcast_to(mo.model_o_home(), (mjx_batch, 3)))
    assert offenders(poses, mo.model_o(backend="mjx"), commands) == []


def test_the_model_o_native_settle_is_the_known_host_bound_backend(model_o_commands):
    """backend='native' settles in MuJoCo on the host (mujoco.rollout through jax.pure_callback): on a GPU every
    call waits on the host. Known and documented; the device backends are 'kinematic' and 'mjx'."""
    from selfid_jax.systems.hands import model_o_hand as mo

    assert offenders(jax.vmap(mo.model_o(backend="native").pose), model_o_commands) == ["host callback pure_callback"]


def _articulated_chunk(*overrides):
    """The articulated experiment's compute vmapped over 1,000 rows (the first row of its drawer part repeated) for
    the shipped configs/articulated/articulated.yaml with ``overrides``, 10 control steps."""
    from selfid_jax import runner

    exp = runner.get("articulated")
    cfg = runner.load("configs/articulated/articulated.yaml",
                      ["max_time=0.2", "objects.revolute=0", "objects.helical=0", "objects.bezier=0", *overrides])
    with runner.precision(True):
        (part,) = exp.build(cfg)
    return exp.batched(part.static), jax.tree.map(lambda x: rows(np.asarray(x)[0]), part.params)


def test_the_shipped_articulated_rollout_is_host_bound():
    """The shipped config runs backend 'native' (its spring grasp is native-only): MuJoCo on the host through
    jax.pure_callback (articulated/sim.py), the known host-bound backend."""
    f, params = _articulated_chunk()
    assert offenders(f, params) == ["host callback pure_callback"]


@slow_mjx
def test_the_articulated_mjx_rollout_runs_on_the_device():
    """The same config on backend 'mjx' with the weld grasp (the device path): self-ID, Kabsch and MJX physics
    (cusolver_potrf_ffi on 1000 x 13 x 13, cusolver_getrf_ffi on 1000 x 6 x 6, cusolver_gesvdj_ffi and
    cusolver_syevd_ffi on 1000 x 3 x 3)."""
    f, params = _articulated_chunk("backend=mjx", "grasp.model=weld")
    assert offenders(f, params) == []

