"""Seed 003's simulated population (Sec. 4.1) and its contact-threshold rule (Sec. 5.1), against independent
numpy references; every object kind as a MuJoCo model that loads and steps."""

import jax
import mujoco
import numpy as np
import pytest

from selfid_jax.articulated import scenes, tactile

# the seed's Sec. 4.1: 50 prismatic-joint objects, 50 revolute-joint objects, 100 Bezier tracks (25 of each order 2-5)
PAPER = {"prismatic": 50, "revolute": 50, "helical": 0, "bezier": 100}


def test_paper_counts_are_the_seed_mix_and_keep_its_proportions_at_any_size():
    assert scenes.paper_counts(200) == PAPER
    assert scenes.paper_counts(16) == {"prismatic": 4, "revolute": 4, "helical": 0, "bezier": 8}
    for n in range(0, 61):
        c = scenes.paper_counts(n)
        assert sum(c.values()) == n and c["helical"] == 0
        for k, v in c.items():  # largest remainder: each count within 1 of its exact share
            assert abs(v - n * PAPER[k] / 200) < 1.0
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="int n >= 0"):
            scenes.paper_counts(bad)


def test_paper_population_from_a_seed_has_the_seed_orders_and_is_reproducible():
    pop = scenes.paper_population(200, seed=0)
    assert {k: len(v.scale) for k, v in pop.items()} == {k: v for k, v in PAPER.items() if v}
    orders, counts = np.unique(pop["bezier"].order, return_counts=True)
    assert list(orders) == [2, 3, 4, 5] and list(counts) == [25, 25, 25, 25]
    assert np.all(pop["prismatic"].order == 0) and np.all(pop["revolute"].order == 0)
    np.testing.assert_allclose(pop["prismatic"].scale, 0.25)  # 250 mm
    np.testing.assert_allclose(pop["revolute"].scale, np.pi / 3)  # 60 deg
    again, other = scenes.paper_population(200, seed=0), scenes.paper_population(200, seed=1)
    for k in pop:
        for a, b in zip(pop[k], again[k]):
            np.testing.assert_array_equal(a, b)
        assert not np.array_equal(pop[k].damping, other[k].damping)
    # the resistance is drawn over the population's whole ranges (here their defaults, at the handle)
    f = pop["prismatic"].frictionloss
    assert f.min() < 1.0 and f.max() > 2.5 and np.all((f >= 0.5) & (f <= 3.0))


@pytest.mark.parametrize("kind", scenes.KINDS)
def test_every_kind_is_a_mujoco_model_that_loads_and_steps(kind):
    p1, R1 = np.array([0.4, 0.1, 0.3]), np.eye(3)
    for grasp in ("weld", "spring"):
        xml = scenes.scene_xml(kind, p1, R1, scenes.SceneSettings(grasp=grasp))
        m = mujoco.MjModel.from_xml_string(xml)
        _, lay = scenes.compile_scene(kind, p1, R1, scenes.SceneSettings(grasp=grasp))
        pop = scenes.population(kind, 4, seed=0)
        d = mujoco.MjData(m)
        for i in range(4):
            scenes.apply_native(m, lay, scenes.ObjectParams(*(a[i] for a in pop)))
            mujoco.mj_resetData(m, d)
            for _ in range(20):
                mujoco.mj_step(m, d)
            assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
        n_obj = {"prismatic": 1, "revolute": 1, "helical": 2, "bezier": 3}[kind]
        assert len(lay.obj_jnts) == n_obj and len(lay.eqs) == {"helical": 1, "bezier": 2}.get(kind, 0)


def _smallest_eps_numpy(delta, n):
    """Brute force over every candidate threshold: the deformations and the next float above each."""
    cand = np.unique(np.concatenate([delta, np.nextafter(delta, np.inf)]))
    hit = [c for c in cand if int(np.sum(delta >= c)) == n]
    return (min(hit), True) if hit else (None, False)


def test_paper_threshold_is_the_smallest_eps_leaving_exactly_n_points():
    rng = np.random.default_rng(0)
    fn = jax.jit(tactile.paper_threshold)
    for _ in range(5):
        delta = rng.uniform(0.0, 1e-3, 40)
        for n in (3, 9, 20):
            eps, ok = fn(delta, n)
            ref, ref_ok = _smallest_eps_numpy(delta, n)
            assert bool(ok) and ref_ok and float(eps) == ref
            assert int(np.sum(delta >= float(eps))) == n
    tie = np.array([5.0, 4.0, 3.0, 3.0, 3.0, 1.0])  # no threshold leaves exactly 3: the third and fourth tie
    assert not bool(fn(tie, 3)[1]) and _smallest_eps_numpy(tie, 3) == (None, False)
    # our flat pads on a round bar: 32 markers share the largest deformation, so the rule has nothing to separate
    pads = tactile.pads()
    assert int(np.sum(pads.delta0 == pads.delta0.max())) == 32
    assert not bool(fn(pads.delta0, 9)[1])


@pytest.mark.slow
def test_initial_contact_applies_the_rule_to_the_noisy_first_reading_or_keeps_the_fixed_eps():
    pads = tactile.pads()
    key = jax.random.key(3)
    eps, start, ok = tactile.initial_contact(pads, key, 5e-6, 3e-4, 9)
    assert bool(ok) and int(start.sum()) == 9
    # the same reading, independently: the measured deformation is delta0 plus the noise's normal component
    noise = 5e-6 * np.asarray(jax.random.normal(key, pads.ref.shape))
    measured = pads.delta0 + np.sum(pads.normal * noise, axis=-1)
    ref, _ = _smallest_eps_numpy(measured, 9)
    assert float(eps) == ref and np.array_equal(np.asarray(start), measured >= ref)
    eps, start, ok = tactile.initial_contact(pads, key, 5e-6, 3e-4, 0)
    assert float(eps) == 3e-4 and bool(ok) and int(start.sum()) == 32


def test_config_paper_mix_and_contact_rule_errors_name_their_keys():
    from selfid_jax.experiments.articulated import ArticulatedConfig

    cfg = ArticulatedConfig(objects={"paper": 200})
    assert cfg.objects.counts() == PAPER
    with pytest.raises(ValueError, match="objects.paper"):
        ArticulatedConfig(objects={"paper": 16, "helical": 2})
    with pytest.raises(ValueError, match="pads.contact_rule 'paper' finds no threshold"):
        ArticulatedConfig(objects={"prismatic": 1}, pads={"contact_rule": "paper", "marker_noise": 0.0})
    with pytest.raises(ValueError, match="pads.contact_points"):
        ArticulatedConfig(objects={"prismatic": 1}, pads={"contact_rule": "paper", "contact_points": 40})
    ArticulatedConfig(objects={"prismatic": 1}, pads={"contact_rule": "paper"})
    with pytest.raises(ValueError, match="contact_rule"):
        ArticulatedConfig(objects={"prismatic": 1}, pads={"contact_rule": "smallest"})


@pytest.mark.slow  # one short native rollout batch (compiles the UR5e loop)
def test_rollout_records_the_threshold_and_initial_set_of_each_rule():
    """Two rows of one vmapped rollout: the fixed 0.3 mm threshold (all 32 touching markers in C_1) and the seed's
    rule (9 markers, the threshold just above the 10th-deepest noisy reading of the 0.868 mm tie)."""
    from selfid_jax.articulated import sim
    from selfid_jax.systems.ur5e import UR5E_HOME, ur5e

    with jax.numpy_rank_promotion("allow"):
        arm = ur5e(task_dim=6)
        q0 = np.asarray(UR5E_HOME)
        p1, R1 = (np.asarray(a) for a in arm.pose(jax.numpy.asarray(q0)))
        pads = tactile.pads()
        m, lay = scenes.compile_scene("prismatic", p1, R1)
        st = sim.make_static("native", lay, m, pads, arm, q0, steps=5, substeps=10, stride=1)
        pop = scenes.population("prismatic", 1, 0)
        B = 2
        full = lambda v: np.full((B,), v)
        p = sim.RolloutParams(
            obj=scenes.ObjectParams(*(np.repeat(a, B, axis=0) for a in pop)),
            controller=np.full((B,), int(sim.Controller.TURBO_LEAD), np.int32), use_estimate=np.zeros(B, bool),
            jinv_est=np.zeros((B, 6, 6)), key=np.asarray(jax.random.key_data(jax.random.split(jax.random.key(0), B))),
            speed=full(0.03), marker_noise=full(5e-6), contact_eps=full(3e-4),
            contact_points=np.array([0, 9], np.int32), qdot_max=np.ones((B, 6)), beta=full(0.9),
            dev_high=full(1e-3), dev_low=full(2e-4), recovery_gain=full(0.5), slip=full(5e-3), slip_rot=full(0.3),
            lead_max=full(1e-3), twist_tau=full(0.06), grasp=np.tile([2e4, 280.0, 5.0, 0.44], (B, 1)))
        r = jax.jit(jax.vmap(lambda q: sim.rollout(st, q)))(p)
    assert list(np.asarray(r.contact_n)) == [32, 9] and bool(np.all(r.contact_ok))
    assert float(r.contact_eps[0]) == 3e-4
    assert pads.delta0.max() < float(r.contact_eps[1]) < pads.delta0.max() + 2e-5  # within 4 sd of the tie
