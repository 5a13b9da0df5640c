"""Seed 003 as its paper describes it: the stop-and-go Tac-Man, Eq. 27, the spring grasp, the paper's metrics,
configurable population ranges and the metrics figure.

References are independent: closed forms (a cubic's third difference, the
spring's static equilibrium against a MuJoCo joint spring, the sum of
Eq. 27's stretched intervals), MuJoCo's own joint-spring force, and
matplotlib's rendered text extents.
"""

import chex
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pandas as pd
import pytest

from selfid_jax.articulated import scenes, sim, tacman, tactile

PADS = tactile.pads()


# ----------------------------------------------------------------------------- Eq. 27


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.3, 0.07])
def test_stretched_step_covers_the_whole_unscaled_displacement(alpha):
    """Eq. 27: a step scaled by alpha runs dt / alpha, i.e. ceil(1 / alpha) intervals, the last in part."""
    k = jnp.arange(40.0)
    frac = np.asarray(jax.jit(jax.vmap(tacman.stretch_fraction, (None, 0)))(alpha, k))
    n = int(np.ceil(1.0 / alpha - 1e-12))
    assert np.all(frac[: n - 1] == 1.0) and np.all(frac[n:] == 0.0)
    np.testing.assert_allclose(frac[n - 1], 1.0 / alpha - (n - 1), rtol=1e-12)
    np.testing.assert_allclose(alpha * frac.sum(), 1.0, rtol=1e-12)  # the displacement of the unscaled command


# ----------------------------------------------------------------------------- the paper's metrics


class TestTimeWeightedJerk(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_cubic_from_rest_and_a_quartic_under_vmap(self):
        """q(t) = a t^3 from rest: the third backward difference is a, 5a, then exactly 6a (= d^3 q / dt^3)."""
        a, dt, n_steps = 0.7, 0.02, 50
        t = dt * np.arange(n_steps + 1)
        q = jnp.asarray(a * t**3)
        f = self.variant(sim.time_weighted_jerk)
        samples = np.array([a, 5 * a] + [6 * a] * (n_steps - 2))
        for n_used in (1, 2, 3, 30, 50):
            expect = samples[:n_used].sum() / n_used  # each sample weighted by dt, over the task time n_used dt
            assert float(f(q, dt, jnp.asarray(n_used))) == pytest.approx(expect, rel=1e-6)
        # vmap: a quartic b t^4 from rest: b dt, 13 b dt (the two steps touching t < 0), then the exact backward
        # third difference of t^4, 24 dt^3 (t - 1.5 dt), divided by dt^3
        b = 2.0
        quartic = np.array([b * dt, 13 * b * dt] + [24 * b * (k * dt - 1.5 * dt) for k in range(3, n_steps + 1)])
        qs = jnp.stack([q, jnp.asarray(b * t**4)])
        out = self.variant(jax.vmap(lambda x: sim.time_weighted_jerk(x, dt, n_steps)))(qs)
        assert float(out[0]) == pytest.approx(samples.mean(), rel=1e-6)
        assert float(out[1]) == pytest.approx(quartic.mean(), rel=1e-6)


# ----------------------------------------------------------------------------- the stop-and-go Tac-Man


def _reading(X: jaxlie.SE3, T_g=None):
    ref = jnp.asarray(PADS.ref)
    mask = jnp.asarray(PADS.delta0 >= 3e-4)
    T_g = jaxlie.SE3.identity() if T_g is None else T_g
    return tacman.Reading(T_g, ref, jax.vmap(X.apply)(ref), mask)


def _shift(x, y=0.0):
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.identity(), jnp.array([x, y, 0.0]))


@pytest.mark.slow
def test_stop_and_go_tacman_explores_one_step_then_recovers_without_driving_the_object():
    speed, dt, gain = 0.03, 0.02, 0.5
    p = tacman.TacManParams(speed, dt, 1e-4, 2e-5, gain, 2 * speed, False)
    step = jax.jit(tacman.tacman_step)
    st = tacman.tacman_init(jaxlie.SE3.identity(), jnp.array([1.0, 0.0, 0.0]))
    st, u, _ = step(st, _reading(_shift(0.0)), p)  # in contact, no deviation: one exploration step along x
    np.testing.assert_allclose(np.asarray(u), [speed, 0, 0, 0, 0, 0], atol=1e-12)
    # the handle stayed behind (the gripper moved 0.6 mm, the handle 0.1 mm): deviation 0.5 mm > 0.1 mm
    lag = _shift(-5e-4, 1e-4)
    st, u, _ = step(st, _reading(lag), p)
    assert bool(st.recovering)
    # recovery: the gripper moves back onto the handle by gain * the in-hand offset, nothing along u0 beyond it
    np.testing.assert_allclose(np.asarray(u[:3]), gain * np.array([-5e-4, 1e-4, 0.0]) / dt, atol=1e-9)
    np.testing.assert_allclose(np.asarray(u[3:]), 0.0, atol=1e-9)
    assert float(u[0]) < 0  # it retreats towards the handle: the object is not driven
    st, u, _ = step(st, _reading(_shift(-1e-5)), p)  # below the tolerance: explore again, same fixed direction
    assert not bool(st.recovering)
    np.testing.assert_allclose(np.asarray(u), [speed, 0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(st.direction), [1, 0, 0], atol=1e-12)


@pytest.mark.slow
def test_reaim_turns_the_exploration_direction_and_the_paper_tacman_does_not():
    """After a recovery, tacman_reaim aims along the handle's net motion over the cycle; tacman keeps u0's."""
    speed, dt = 0.03, 0.02
    out = {}
    for reaim in (False, True):
        p = tacman.TacManParams(speed, dt, 1e-4, 2e-5, 0.5, 2 * speed, reaim)
        st = tacman.tacman_init(jaxlie.SE3.identity(), jnp.array([1.0, 0.0, 0.0]))
        st, _, _ = tacman.tacman_step(st, _reading(_shift(0.0)), p)
        # the handle moved 1 mm along (1, 1)/sqrt 2 in the world while the gripper went to x = 2 mm
        T_g = _shift(2e-3)
        h = np.array([1e-3, 1e-3]) / np.sqrt(2)
        st, _, _ = tacman.tacman_step(st, _reading(_shift(h[0] - 2e-3, h[1]), T_g), p)
        assert bool(st.recovering)
        st, u, _ = tacman.tacman_step(st, _reading(_shift(0.0), _shift(h[0], h[1])), p)  # back on the handle
        assert not bool(st.recovering)
        out[reaim] = np.asarray(st.direction), np.asarray(u)
    np.testing.assert_allclose(out[False][0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(out[True][0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-9)
    np.testing.assert_allclose(out[True][1][:3], speed * out[True][0], atol=1e-9)


# ----------------------------------------------------------------------------- the spring grasp


@pytest.mark.parametrize("k", [7300.0, 1e5, 1e6])
def test_spring_grasp_stiffness_is_the_configured_k_on_a_static_pull(k):
    """Gripper held 2 mm ahead of a drawer on a MuJoCo joint spring k_j: at rest k (d - x) = k_j x (MuJoCo's
    qfrc_spring), so the measured grasp stiffness k_j x / |p_t - p_h| is k."""
    import mujoco
    from selfid_jax.experiments.articulated import Grasp

    m, lay = scenes.compile_scene("prismatic", np.zeros(3), np.eye(3),
                                  scenes.SceneSettings(timestep=5e-4, grasp="spring"))
    k_j = 3000.0
    m.jnt_stiffness[lay.obj_jnts[0]] = k_j
    m.dof_damping[lay.obj_dofs[0]] = 50.0
    d = mujoco.MjData(m)
    gains = Grasp(model="spring", k=[k]).gains(k)
    delta = 2e-3
    d.mocap_pos[0] = [delta, 0.0, 0.0]
    vel, zero = np.zeros(6), np.zeros(3)
    for _ in range(6000):  # 3 s
        mujoco.mj_step1(m, d)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, lay.handle, vel, 0)
        sim.spring_wrench(d.xpos[lay.gripper], d.xquat[lay.gripper], zero, zero, d.xpos[lay.handle],
                          d.xquat[lay.handle], vel[3:], vel[:3], gains, out=d.xfrc_applied[lay.handle])
        mujoco.mj_step2(m, d)
    mujoco.mj_forward(m, d)
    x = float(d.qpos[lay.obj_qpos])
    force = -float(d.qfrc_spring[lay.obj_dofs[0]])  # MuJoCo's joint spring on the drawer, = k_j x
    assert force == pytest.approx(k_j * x, rel=1e-9)
    stretch = float(np.linalg.norm(d.xpos[lay.gripper] - d.xpos[lay.handle]))
    assert x == pytest.approx(k * delta / (k + k_j), rel=0.02)  # the closed-form equilibrium
    assert force / stretch == pytest.approx(k, rel=0.02)


def test_spring_wrench_closed_form():
    """A 1 mm offset and a 0.1 rad twist about z, relative velocities: F = -k e - c v, tau = -kr theta - cr w."""
    q_t = np.array([1.0, 0, 0, 0])
    q_h = np.array([np.cos(0.05), 0, 0, np.sin(0.05)])  # 0.1 rad about z
    w = sim.spring_wrench(np.zeros(3), q_t, np.array([0.01, 0, 0]), np.zeros(3), np.array([1e-3, 0, 0]), q_h,
                          np.zeros(3), np.array([0, 0, 0.2]), np.array([1e4, 50.0, 3.0, 0.1]))
    np.testing.assert_allclose(w, [-10.0 + 0.5, 0, 0, 0, 0, -0.3 - 0.02], atol=1e-12)


def test_spring_wrench_equals_the_numpy_form_bit_for_bit():
    """The host loop's wrench (Python floats, work arrays kept) is numpy's expression of the same formula, exactly."""
    import mujoco

    rng = np.random.default_rng(3)
    for _ in range(50):
        p_t, p_h, v_t, v_h, w_t, w_h = rng.normal(size=(6, 3)) * [[1], [1], [0.1], [0.1], [1], [1]]
        q_t, q_h = (q / np.linalg.norm(q) for q in rng.normal(size=(2, 4)))
        k, c, kr, cr = grasp = rng.uniform(0.1, 1e6, 4)
        qi, qr, rv, rot = np.empty(4), np.empty(4), np.empty(3), np.empty(3)
        mujoco.mju_negQuat(qi, q_t)
        mujoco.mju_mulQuat(qr, qi, q_h)
        mujoco.mju_quat2Vel(rv, qr, 1.0)
        mujoco.mju_rotVecQuat(rot, rv, q_t)
        ref = np.concatenate([-k * (p_h - p_t) - c * (v_h - v_t), -kr * rot - cr * (w_h - w_t)])
        assert np.array_equal(sim.spring_wrench(p_t, q_t, v_t, w_t, p_h, q_h, v_h, w_h, grasp), ref)


def test_spring_grasp_config_checks_the_timestep_and_the_backend():
    from selfid_jax.experiments.articulated import ArticulatedConfig, Grasp, spring_stable

    base = dict(objects={"prismatic": 1}, controllers=["turbo"], arms=["true"])
    with pytest.raises(ValueError, match="raise substeps to >= 37"):
        ArticulatedConfig(**base, grasp={"model": "spring", "k": [1e6]}, substeps=30)
    ArticulatedConfig(**base, grasp={"model": "spring", "k": [1e6]}, substeps=40)
    with pytest.raises(ValueError, match="native backend only"):
        ArticulatedConfig(**base, backend="mjx", grasp={"model": "spring", "k": [1e4]})
    with pytest.raises(ValueError, match="set grasp.model: spring"):
        ArticulatedConfig(**base, grasp={"k": [1e4, 1e5]})
    # the stability test against a direct simulation of the damped oscillator's semi-implicit Euler map
    g = Grasp(model="spring", k=[1e6])
    for h, stable in ((5e-4, True), (6.5e-4, False)):
        assert spring_stable(g, 1e6, h) is stable
    x, v, c = 1e-3, 0.0, g.gains(1e6)[1]
    for h, grows in ((6.5e-4, True), (5e-4, False)):
        x, v = 1e-3, 0.0
        for _ in range(300):
            v -= h * (1e6 * x + c * v) / 0.3
            x += h * v
        assert bool(abs(x) > 1e-3) is grows  # 0.65 ms: 1 mm grows on the lightest 0.3 kg; 0.5 ms: it decays


# ----------------------------------------------------------------------------- configs


def test_population_ranges_from_yaml_lists_and_set_overrides(tmp_path):
    from selfid_jax.experiments.articulated import ArticulatedConfig

    from selfid_jax.runner.registry import load

    cfg = ArticulatedConfig(objects={"prismatic": 1}, population={"damping": [0, 0], "frictionloss": [0.5, 1]})
    assert cfg.population.damping == (0.0, 0.0) and cfg.population.frictionloss == (0.5, 1.0)
    path = tmp_path / "a.yaml"
    path.write_text("experiment: articulated\nobjects: {prismatic: 1}\npopulation: {track: [0.3, 0.4]}\n")
    cfg = load(path, ["population.damping=[0,0]", "population.frictionloss=[0.0, 0.2]"])
    assert cfg.population.damping == (0.0, 0.0)
    assert cfg.population.frictionloss == (0.0, 0.2) and cfg.population.track == (0.3, 0.4)
    pop = scenes.population("prismatic", 3, 0, **cfg.population.model_dump())
    assert np.all(pop.damping == 0.0) and np.all((pop.frictionloss >= 0.0) & (pop.frictionloss <= 0.2))
    with pytest.raises(Exception, match="needs 0 <= lo <= hi"):
        ArticulatedConfig(objects={"prismatic": 1}, population={"damping": [3, 1]})
    with pytest.raises(Exception, match="two numbers"):
        ArticulatedConfig(objects={"prismatic": 1}, population={"damping": [1, 2, 3]})


@pytest.mark.slow  # the UR5e's eager forward kinematics compile on first use
def test_grid_axes_scale_resistance_and_set_the_grasp_and_tacman_thresholds_per_row():
    from selfid_jax.experiments.articulated import ArticulatedConfig, _build

    cfg = ArticulatedConfig(objects={"prismatic": 1}, controllers=["tacman", "tacman_reaim"], arms=["true"],
                            grasp={"model": "spring", "k": [1e4, 1e5]}, resistance=[0.0, 2.0], substeps=20,
                            population={"damping": [4, 4], "frictionloss": [1, 1]})
    (part,) = _build(cfg)
    r, meta = part.params.rollout, part.meta
    assert len(meta) == 2 * 2 * 2
    np.testing.assert_allclose(r.obj.damping, 4.0 * meta["resistance"].to_numpy())
    np.testing.assert_allclose(r.obj.frictionloss, 1.0 * meta["resistance"].to_numpy())
    np.testing.assert_allclose(r.grasp[:, 0], meta["grasp_k"].to_numpy())
    np.testing.assert_allclose(r.grasp[:, 1], 2 * 0.7 * np.sqrt(meta["grasp_k"].to_numpy() * 0.3))
    reaim = (meta["controller"] == "tacman_reaim").to_numpy()
    np.testing.assert_allclose(r.dev_high, np.where(reaim, 1e-3, 1e-4))
    np.testing.assert_allclose(r.dev_low, np.where(reaim, 2e-4, 2e-5))
    assert list(r.controller) == [sim.Controller.parse(c) for c in meta["controller"]]


# ----------------------------------------------------------------------------- figures


def _fake_table(kinds=scenes.KINDS, ctrls=sim.CONTROLLERS, n=3):
    from selfid_jax.experiments.articulated import METRICS

    rng = np.random.default_rng(0)
    rows = []
    for k in kinds:
        for c in ctrls:
            for i in range(n):
                row = {"kind": k, "controller": c, "object": i, "success": bool(i < 2), "grasp_k": 1e4,
                       "resistance": 1.0}
                row.update({m: float(rng.uniform(1, 100)) for m in METRICS})
                rows.append(row)
    return pd.DataFrame(rows)


def _overlaps(boxes):
    return [(i, j) for i in range(len(boxes)) for j in range(i + 1, len(boxes)) if boxes[i].overlaps(boxes[j])]


@pytest.mark.slow
def test_metrics_figure_tick_labels_do_not_overlap():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from selfid_jax.experiments.articulated import METRICS
    from selfid_jax.experiments.figures.articulated import metrics_figure

    fig = metrics_figure(_fake_table())
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    axes = fig.get_axes()
    assert len(axes) == 1 + len(METRICS)
    n_labels = len(scenes.KINDS) * len(sim.CONTROLLERS)
    for ax in axes:
        labels = [t for t in ax.get_xticklabels() if t.get_text()]
        assert len(labels) == n_labels
        assert _overlaps([t.get_window_extent(r) for t in labels]) == []


@pytest.mark.slow
def test_plane_figure_shows_every_cell():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from selfid_jax.experiments.figures.articulated import plane_figure

    plane = [{"grasp_k": k, "resistance": res, "controller": c, "success_rate": 1.0 if k > 1e5 else 0.0,
              "time_s": {"mean": 8.0 if k > 1e5 else None, "sd": 0.0}}
             for k in (7300.0, 1e5, 1e6) for res in (0.0, 1.0) for c in ("turbo", "turbo_lead")]
    fig = plane_figure({"plane": plane})
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    heat = [ax for ax in fig.get_axes() if ax.images]
    assert len(heat) == 4  # success and time for each controller
    texts = [t.get_text() for t in heat[0].texts]
    assert len(texts) == 6 and texts.count("100") == 2 and texts.count("0") == 4
    assert [t.get_text() for t in heat[1].texts].count("-") == 4  # no time where nothing succeeded


# ----------------------------------------------------------------------------- closed loop (slow)


@pytest.mark.slow  # one native rollout batch (compiles the UR5e loop)
def test_stop_and_go_tacman_in_the_loop_halts_the_object_while_it_recovers():
    """Soft spring grasp (7.3 kN/m), a drawer with 1 N friction and 4 N s/m damping: Tac-Man alternates single
    exploration steps and recoveries. While it recovers the gripper does not drive the drawer: it stays behind
    the handle along the drawer's motion (no pulling shear), and after the first recovery step (the spring's
    stored shear released) the drawer, held by its friction, moves far less than in an exploration step. The
    literal Turbo beside it never recovers."""
    from selfid_jax.experiments.articulated import ArticulatedConfig, _build

    from selfid_jax.runner.execute import precision

    with precision(True):
        cfg = ArticulatedConfig(objects={"prismatic": 1}, controllers=["tacman", "turbo"], arms=["true"],
                                grasp={"model": "spring", "k": [7300.0]}, max_time=3.0, trace_points=150,
                                population={"damping": [4, 4], "frictionloss": [1, 1]}, selfid_iters=4)
        (part,) = _build(cfg)
        st = part.static.sim
        assert st.stride == 1
        r = jax.jit(jax.vmap(lambda p: sim.rollout(st, p)))(jax.tree.map(np.asarray, part.params.rollout))
    rec = np.asarray(r.recovery_trace[0])
    used = int(r.steps_used[0])
    assert not bool(r.failed[0]) and used == 150
    assert int(r.recovery_steps[0]) == int(rec.sum()) and 0 < rec.sum() < used
    assert int(r.recovery_steps[1]) == 0 and not np.any(np.asarray(r.recovery_trace[1]))
    h, g = np.asarray(r.handle_trace[0]), np.asarray(r.gripper_trace[0])  # G1 frame, after each step
    u = (h[-1] - h[0]) / np.linalg.norm(h[-1] - h[0])  # the drawer's direction of motion
    dg = np.diff(np.concatenate([[np.zeros(3)], g]), axis=0) @ u  # the gripper's step along it [m]
    explore = dg[~rec]
    np.testing.assert_allclose(np.median(explore), 0.03 * 0.02 * np.cos(np.radians(15)), rtol=0.05)  # u0 dt
    lead = (g - h) @ u  # how far the gripper is ahead of the handle along the motion: the pulling shear
    assert np.all(lead[~rec] > 1e-4)  # exploring: the gripper pulls the drawer (0.3 mm ahead)
    assert np.all(lead[rec] < 0)  # recovering: it is never ahead of the handle, the drawer is not driven
    # the drawer (MuJoCo's slide joint) per step, recovery steps after the first of each recovery
    dp = 0.25 * np.diff(np.concatenate([[0.0], np.asarray(r.progress_trace[0])]))
    later = rec & np.concatenate([[False], rec[:-1]])
    assert later.sum() > 10 and float(r.progress[0]) > 0.02  # several cycles; it did open the drawer
    assert np.mean(np.abs(dp[later])) < 0.1 * np.median(dp[~rec])
