"""The follow loop reads the tracker that self-ID reads (issue 45, item 2): an experiment's noise levels
(``pose_noise``, ``rot_noise``) and a ``realism`` section's latency reach the controller's readings through
:func:`selfid_jax.control.realism.with_tracker_noise`. Realism off is the exact-pose loop bit for bit; the readings'
sd is the configured one; the tracking error grows with the noise; latency delays the readings by whole steps;
one compiled program serves every noise value under jit and vmap."""

import functools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax import control, runner
from selfid_jax.control import paths
from selfid_jax.control import realism as R
from selfid_jax.math import geometry
from selfid_jax.systems import REGISTRY

ARM = REGISTRY["two_link"].factory()
PATH = paths.star(size=0.1, dim=2)
CTRL = control.ControllerParams(max_step=0.01, tol=0.002)
STEPS = 150
# one worker runs the module: `follow_batch`, the start configurations and the tracking programs are built once
pytestmark = pytest.mark.xdist_group("follow_noise")


def follow_sensed(q0, pose_noise, rot_noise, key, latency=0):
    """The true inverse Jacobian on the star, reading the tracker of ``with_tracker_noise(Realism(latency), ...)``."""
    sensed = R.with_tracker_noise(R.Realism(latency=latency), pose_noise, rot_noise)
    return control.follow(ARM, control.true_inverse(ARM), PATH, q0, CTRL, steps=STEPS, return_trajectory=True,
                          realism=sensed, key=key, max_latency=3)


@jax.jit
@chex.assert_max_traces(n=1)
def follow_batch(q0s, pose_noise, latency, keys):
    """One compiled call for any batch of noise levels and latencies (up to 3)."""
    return jax.vmap(lambda q, s, lat, k: follow_sensed(q, s, 0.0, k, lat))(q0s, pose_noise, latency, keys)


@functools.cache
def start_configs() -> np.ndarray:
    """``(4, 2)`` start configurations from which the truth completes the star."""
    return np.asarray(control.feasible_starts(ARM, PATH, jax.random.key(0), 4, CTRL, steps=STEPS))


@pytest.fixture(scope="module")
def starts():
    return start_configs()


def keys(n, seed=1):
    return jax.random.split(jax.random.key(seed), n)


def assert_same(a, b, fields):
    for f in fields:
        for x, y in zip(jax.tree.leaves(getattr(a, f)), jax.tree.leaves(getattr(b, f)), strict=True):
            np.testing.assert_array_equal(x, y, err_msg=f)


# ------------------------------------------------------------------ (1) realism off is the exact-pose loop

@pytest.mark.slow
def test_realism_off_is_the_exact_pose_loop_bit_for_bit(starts):
    exact = jax.jit(jax.vmap(lambda q: control.follow(ARM, control.true_inverse(ARM), PATH, q, CTRL, steps=STEPS,
                                                      return_trajectory=True)))(starts)
    off = follow_batch(starts, np.zeros(4), np.zeros(4, np.int32), keys(4))  # noise 0, latency 0, no dropouts
    assert_same(off, exact, [f for f in exact._fields if getattr(exact, f) is not None])
    np.testing.assert_array_equal(off.readings, off.positions)
    assert int(off.dropouts.sum()) == 0
    none = R.with_tracker_noise(None)  # no section, no noise: IDEAL's values exactly
    assert all(float(a) == float(b) for a, b in zip(none, R.IDEAL))
    r = R.Realism(latency=2, noise_pos=3e-4, dropout=0.1)
    assert R.with_tracker_noise(r) == r  # zero noise adds nothing to a section's values


TRACKING = dict(system="two_link", path={"kind": "star", "size": 0.1},
                controller={"max_step": 0.01, "tol": 0.002, "steps": STEPS}, n_configs=2, iters=12, m_a=0.02,
                eps=0.05)


def tracking_outputs(**overrides):
    """The tracking experiment's per-row outputs, computed as the runner does (one jit(vmap) over the rows)."""
    exp = runner.get("tracking")
    (part,) = exp.parts(exp.config(**{**TRACKING, **overrides}))
    return part, jax.jit(exp.batched(part.static))(part.params)


@functools.cache
def noisy_tracking():
    """:func:`tracking_outputs` with a noise-free and a 0.5 mm level, computed once for the tests that read it."""
    return tracking_outputs(pose_noise=[0.0, 5e-4], rot_noise=[0.0, 0.0])


@pytest.mark.slow  # compiles the tracking program twice (with and without the tracker in the follow loop)
def test_noise_free_rows_of_a_noisy_sweep_equal_the_noise_free_sweep():
    """The follow loop reads the tracker only where a level has noise; its noise-free rows (the real loop at zero
    noise) give the ideal loop's outputs bit for bit, self-ID included (the same row keys). Two different programs:
    this holds here (two-link, float64); XLA may fuse another system's program differently (the shipped UR5e cube's
    noise-free rows agree to float32 rounding). A config without noise levels compiles the program it always did."""
    plain_part, plain = tracking_outputs()
    noisy_part, noisy = noisy_tracking()
    assert plain_part.static.max_latency is None and noisy_part.static.max_latency == 0
    clean = np.flatnonzero(noisy_part.meta["pose_noise"].to_numpy() == 0)
    np.testing.assert_array_equal(clean, np.arange(len(plain_part.meta)))
    for f in plain._fields:
        for x, y in zip(jax.tree.leaves(getattr(plain, f)), jax.tree.leaves(getattr(noisy, f)), strict=True):
            np.testing.assert_array_equal(np.asarray(y)[clean], x, err_msg=f)


# ------------------------------------------------------------------ (2) the readings' noise and its cost

@pytest.mark.slow
def test_readings_differ_from_the_pose_by_the_configured_sd(starts):
    sd = np.array([1e-4, 1e-4, 5e-4, 5e-4])
    res = follow_batch(starts, sd, np.zeros(4, np.int32), keys(4, 3))
    for i in range(4):
        used = int(res.steps_used[i])
        err = (np.asarray(res.readings[i]) - np.asarray(res.positions[i]))[: used + 1, :2]  # the plane's axes
        n = err.size
        assert n >= 60
        assert abs(err.std() / sd[i] - 1) < 5 / math.sqrt(2 * n), (sd[i], err.std(), n)  # 5 sd of the sample sd
        assert abs(err.mean()) < 5 * sd[i] / math.sqrt(n)
    # many independent readings of one pose: the per-axis sd of position and rotation noise, as self-ID draws them
    tr = R.tracker((jnp.zeros(3), jnp.eye(3)), 0)
    sensed = R.with_tracker_noise(None, 2e-4, 0.01)
    p, Rm = jax.jit(jax.vmap(lambda k: R.read(tr, k, sensed)[0]))(keys(4000, 5))
    np.testing.assert_allclose(np.asarray(p).std(axis=0), 2e-4, rtol=0.06)  # 4000 samples: sd's sd is 1.1 %
    np.testing.assert_allclose(np.asarray(geometry.so3_log(Rm)).std(axis=0), 0.01, rtol=0.06)


@pytest.mark.slow  # the noisy tracking program (compiled once for this test and the noise-free rows' test)
def test_tracking_error_grows_with_the_tracker_noise():
    """Two-link star: the analytical inverse's path error with 0.5 mm of noise on every reading is more than twice
    the noise-free one (which reads exact poses; its 0.09 mm is the corners cut by 10 mm steps)."""
    part, out = noisy_tracking()
    noise = part.meta["pose_noise"].to_numpy()
    err = np.asarray(out.error_mm)[:, 1, :2].mean(axis=1)  # analytical inverse, x and y [mm]
    clean, noisy = err[noise == 0].mean(), err[noise > 0].mean()
    assert noisy > 2 * clean and noisy > clean + 0.1, (clean, noisy)
    assert not np.any(np.asarray(out.failed))


@pytest.mark.slow  # compiles the UR5e's 6-D tracking program
def test_analytical_cube_error_with_half_a_millimetre_of_noise_is_well_above_the_noise_free_one(tmp_path):
    """The shipped cube's finding at small size: noise-free the analytical inverse tracks to a few hundredths of a
    mm (0.03-0.09 mm per axis in docs/results/tracking.md); with 0.5 mm of tracker noise on every reading it is
    several times that."""
    exp = runner.get("tracking")
    cfg = exp.config(system="ur5e_6d", path={"kind": "cube", "edge": 0.05},
                     controller={"max_step": 0.0025, "tol": 0.0005, "steps": 400, "max_rot_step": 0.05,
                                 "rot_tol": 0.01},
                     n_configs=1, iters=20, m_a=0.03, eps=0.5, pose_noise=[0.0, 5e-4], rot_noise=[0.0, 0.0])
    table, _ = runner.run(exp, cfg, tmp_path)
    truth = table[table.inverse == "analytical"]
    axes = ["error_x_mm", "error_y_mm", "error_z_mm"]
    clean = truth[truth.pose_noise == 0][axes].to_numpy().mean()
    noisy = truth[truth.pose_noise > 0][axes].to_numpy().mean()
    assert clean < 0.1 and noisy > 0.15 and noisy > 3 * clean, (clean, noisy)


# ------------------------------------------------------------------ (3) latency

@pytest.mark.slow
def test_latency_the_follow_loop_sees_the_pose_of_L_steps_ago(starts):
    lat = np.array([0, 1, 2, 3], np.int32)
    res = follow_batch(starts, np.zeros(4), lat, keys(4, 7))
    for i, L in enumerate(lat):
        pos, seen = np.asarray(res.positions[i]), np.asarray(res.readings[i])
        used = int(res.steps_used[i])
        assert used > 2 * L
        np.testing.assert_array_equal(seen[L:used], pos[: used - L])
        np.testing.assert_array_equal(seen[:L], np.repeat(pos[:1], L, axis=0))  # before the start: at rest


# ------------------------------------------------------------------ (4) jit and vmap

class TestTransforms(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    @pytest.mark.slow
    def test_jit_and_eager_agree_and_vmap_is_the_loop(self):
        q0 = jnp.asarray(start_configs()[0])
        ks = keys(2, 11)
        sd = jnp.array([0.0, 5e-4])
        fn = self.variant(lambda s, k: follow_sensed(q0, s, 0.01, k, 1))
        batched = jax.vmap(fn)(sd, ks)
        for i in range(2):
            one = fn(sd[i], ks[i])
            for f in ("completion", "mean_error", "waypoint_error", "steps_used", "final_q", "positions",
                      "readings"):
                np.testing.assert_allclose(np.asarray(getattr(batched, f))[i], getattr(one, f), rtol=1e-9,
                                           atol=1e-12, err_msg=f)
        assert np.all(np.isfinite(np.asarray(batched.positions)))
        gaps = np.abs(np.asarray(batched.readings) - np.roll(np.asarray(batched.positions), 1, axis=1))[:, 1:]
        assert gaps[0].max() == 0.0 and gaps[1].max() > 0.0  # latency 1, then the noise as configured
