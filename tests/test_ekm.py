"""E-KM (seed 002): the nominal model is the true map with wrong parameters (checked against closed-form
2-link kinematics), its control Jacobian approaches the true one as the GP learns (both formulations),
it works behind the estimator protocol (make, run_stream, sample screen, jit == vmap), and on a hard
nominal model the online E-KM completes a 2-link star from one self-ID sample."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax import baselines, control
from selfid_jax.baselines import ekm
from selfid_jax.control import paths
from selfid_jax.systems.two_link import two_link

HARD = dict(scale=(1.5, 0.6), offset=(0.6, -0.6))


def fk(l1, l2, q):
    return np.array([l1 * np.cos(q[0]) + l2 * np.cos(q[0] + q[1]), l1 * np.sin(q[0]) + l2 * np.sin(q[0] + q[1])])


def samples(arm, q0, k, m_a=0.02, seed=0):
    """k random actuations from q0 and the true task changes (dead-reckoned chain, as self-ID)."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(-m_a, m_a, (k, arm.n_act))
    q = np.asarray(q0) + np.concatenate([np.zeros((1, arm.n_act)), np.cumsum(d, axis=0)])
    p = np.stack([np.asarray(arm.pose(qi)[0][:2]) for qi in q])
    return d, np.diff(p, axis=0)


@jax.jit
def control_jacobian(mdl, state):
    return ekm.linearise(mdl, state, state.q0)


def test_nominal_system_is_the_true_map_with_wrong_parameters():
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    q = np.array([0.3, 1.1])
    np.testing.assert_allclose(nom.pose(q)[0][:2], fk(1.5, 0.6, q + np.array([0.6, -0.6])), atol=1e-12)
    np.testing.assert_allclose(arm.pose(q)[0][:2], fk(1.0, 1.0, q), atol=1e-12)  # the true arm is untouched
    with pytest.raises(ValueError, match=r"offset: expected shape \(\) or \(2,\)"):
        ekm.nominal_system(arm, offset=np.zeros(3))
    with pytest.raises(ValueError, match=r"scale: expected shape \(\) or \(2,\)"):
        ekm.nominal_system(arm, scale=np.ones(3))


@pytest.mark.slow
@pytest.mark.parametrize("formulation", ["incremental", "absolute"])
def test_control_jacobian_learns_the_true_jacobian(formulation):
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    q0 = jnp.array([0.4, 1.2])
    mdl = ekm.model(nom, formulation=formulation)
    J_true = np.asarray(arm.jacobian(q0))
    state = ekm.init(mdl, q0, capacity=20)
    J0, off0 = control_jacobian(mdl, state)
    np.testing.assert_allclose(J0, nom.jacobian(q0), atol=1e-12)  # empty GP: the nominal model
    np.testing.assert_allclose(off0, 0.0, atol=1e-12)
    d, V = samples(arm, q0, 12)
    state = jax.jit(ekm.fold)(mdl, state, d, V)
    J, off = control_jacobian(mdl, state)
    err0 = np.linalg.norm(J0 - J_true) / np.linalg.norm(J_true)
    err = np.linalg.norm(J - J_true) / np.linalg.norm(J_true)
    assert err0 > 0.3 and err < 0.05, (err0, err)  # nominal 33 % off
    assert np.linalg.norm(off) < 1e-3 * np.linalg.norm(V, axis=1).mean() + 1e-9  # no motion without actuation


def test_protocol_option_and_init_errors():
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    q0 = jnp.array([0.4, 1.2])
    with pytest.raises(ValueError, match="ekm: nominal: init needs the nominal System"):
        baselines.make("ekm").init(2, 2)
    with pytest.raises(ValueError, match="ekm: q0: init needs the start configuration"):
        baselines.make("ekm", nominal=nom).init(2, 2)
    with pytest.raises(ValueError, match=r"ekm: init for \(n, m\) = \(3, 2\)"):
        baselines.make("ekm", nominal=nom, q0=q0).init(3, 2)
    with pytest.raises(ValueError, match=r"ekm: mode: expected one of \('fixed', 'online'\)"):
        baselines.make("ekm", mode="batch")
    with pytest.raises(ValueError, match="needs a position task"):
        ekm.model(ekm.nominal_system(two_link(task_dim=6)), formulation="absolute")
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64"):
        baselines.make("ekm", nominal=nom, q0=q0).init(2, 2, dtype=jnp.float32)




@pytest.mark.slow
def test_behind_the_estimator_protocol():
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    q0s = jnp.array([[0.4, 1.2], [-0.3, 0.9]])
    streams = [samples(arm, q, 6, seed=i) for i, q in enumerate(q0s)]
    d = np.stack([s[0] for s in streams])
    V = np.stack([s[1] for s in streams])
    d[:, 2] = np.nan  # a non-finite sample: rejected and counted, the configuration is not advanced

    def final(q0, d, V):
        est = baselines.make("ekm", nominal=nom, q0=q0)
        state = est.init(2, 2, capacity=12)
        state, estimates = baselines.scan(est, state, d, V, jnp.zeros((2, 2)))
        return state, estimates[-1]

    batched = jax.jit(jax.vmap(final))(q0s, d, V)
    for i in range(2):
        one = jax.jit(final)(q0s[i], d[i], V[i])
        chex.assert_trees_all_close(jax.tree.map(lambda a, i=i: a[i], batched), one, atol=1e-12)
        state, Jinv = one
        assert int(state.count) == 5 and int(state.rejected) == 1 and np.all(np.isfinite(Jinv))
        # the sample after the rejected one is learned from the wrong place, as dead reckoning says
        assert Jinv.shape == (2, 2)


@pytest.mark.slow
def test_protocol_estimate_is_the_pseudo_inverse_of_the_control_jacobian():
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    q0 = jnp.array([0.4, 1.2])
    d, V = samples(arm, q0, 8)
    est = baselines.run_stream(baselines.make("ekm", nominal=nom, q0=q0), None, d, V, jnp.zeros((2, 2)))
    mdl = ekm.model(nom)
    J, _ = control_jacobian(mdl, jax.jit(ekm.fold)(mdl, ekm.init(mdl, q0, capacity=8), d, V))
    np.testing.assert_allclose(est[-1], np.linalg.inv(np.asarray(J)), rtol=1e-9)


@pytest.mark.slow
def test_online_ekm_completes_a_star_from_one_sample_on_a_hard_nominal_model():
    arm = two_link()
    nom = ekm.nominal_system(arm, **HARD)
    path = paths.star(size=0.2, dim=2)
    ctrl = control.ControllerParams(max_step=0.01, tol=0.002)
    q0 = jnp.array([0.3, 1.4])
    mdl = ekm.model(nom)
    d, V = samples(arm, q0, 1, m_a=0.05)
    state = ekm.fold(mdl, ekm.init(mdl, q0, capacity=30), d, V)

    @jax.jit
    def run(state):
        return ekm.follow(mdl, state, arm, path, ctrl, mode="online", steps=435)

    res, final = run(state)
    assert float(res.completion) == 1.0 and not bool(res.failed)
    assert int(final.gp.count) > 100 and int(final.gp.unstable) < int(final.gp.count)
    J, _ = control_jacobian(mdl, final._replace(q0=final.q))  # learned along the way: near the truth at the end
    J_true = np.asarray(arm.jacobian(final.q))
    assert np.linalg.norm(J - J_true) / np.linalg.norm(J_true) < 0.1
