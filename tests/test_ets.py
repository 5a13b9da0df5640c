"""ETS arms against independent references: roboticstoolbox-python (optional), a numpy product-rule Jacobian, DH."""

import jax

jax.config.update("jax_enable_x64", True)

import math  # noqa: E402

import chex  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from selfid_jax.systems.ets import ARM5_ETS, ARM5_Q_HIGH, ARM5_Q_LOW, arm5, from_ets, parse_ets  # noqa: E402

POS_TOL = 1e-9  # m, float64
JAC_TOL = 1e-9  # m/rad and rad/rad, float64
B = 16  # random configurations per ETS

# Several sequences: the seed's arm, a 6-DOF arm (UR5e from its DH table, one DH link = Rz(q) tz(d) tx(a) Rx(alpha)),
# and one with prismatic joints, constant rotations and a flipped joint.
UR5E_DH = dict(d=[0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996], a=[0.0, -0.425, -0.3922, 0.0, 0.0, 0.0],
               alpha=[math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])
UR5E_ETS = [s for d, a, al in zip(UR5E_DH["d"], UR5E_DH["a"], UR5E_DH["alpha"])
            for s in ("Rz", f"tz({d})", f"tx({a})", f"Rx({al!r})")]
MIXED_ETS = ["tx(0.05)", "Ry(pi/6)", "tz", "Rx", "ty(-0.2)", "Rz(-q)", "tx(0.3)", "Rx(0.4)", "ty", "Ry", "tz(0.07)"]
SEQUENCES = {"arm5": list(ARM5_ETS), "ur5e_dh": UR5E_ETS, "mixed": MIXED_ETS}
LIMITS = {"mixed": (np.array([-1, -3, -3, -1, -3.0]), np.array([1, 3, 3, 1, 3.0]))}


def build(name, task_dim=6):
    lo, hi = LIMITS.get(name, (None, None))
    return from_ets(SEQUENCES[name], task_dim=task_dim, q_low=lo, q_high=hi)


# ------------------------------------------------------------------ numpy reference (independent of the JAX walk)
def _elem(kind, axis, v):
    T = np.eye(4)
    if kind == "t":
        T[axis, 3] = v
        return T
    c, s = np.cos(v), np.sin(v)
    i, k = [(1, 2), (2, 0), (0, 1)][axis]
    T[i, i], T[i, k], T[k, i], T[k, k] = c, -s, s, c
    return T


def _delem(kind, axis, v):
    """d E(v) / d v as a 4x4 matrix (the generator times E)."""
    G = np.zeros((4, 4))
    if kind == "t":
        G[axis, 3] = 1.0
    else:
        i, k = [(1, 2), (2, 0), (0, 1)][axis]
        G[k, i], G[i, k] = 1.0, -1.0
    return G @ _elem(kind, axis, v)


def _tokens(seq):
    """(kind, axis, constant or None, sign) per element, parsed here by hand."""
    out = []
    for s in seq:
        kind = "R" if s[0] == "R" else "t"
        axis = "xyz".index(s[1])
        arg = s[3:-1] if "(" in s else None
        if arg is None or arg.lstrip("-").startswith("q"):
            out.append((kind, axis, None, -1.0 if arg and arg.startswith("-") else 1.0))
        else:
            out.append((kind, axis, float(eval(arg, {"pi": math.pi})), 1.0))  # noqa: S307 - test literals only
    return out


def numpy_fk_jacobian(seq, q):
    """T (4, 4) by the plain product, J (6, n) by the product rule: dT/dq_i = A dE_i B, omega = vee(dR R^T)."""
    toks = _tokens(seq)
    mats, joint_at = [], []
    qi = 0
    for kind, axis, c, sign in toks:
        if c is None:
            mats.append((kind, axis, sign * q[qi], sign))
            joint_at.append(len(mats) - 1)
            qi += 1
        else:
            mats.append((kind, axis, c, None))
    T = np.eye(4)
    for kind, axis, v, _ in mats:
        T = T @ _elem(kind, axis, v)
    J = np.zeros((6, len(joint_at)))
    for col, j in enumerate(joint_at):
        dT = np.eye(4)
        for idx, (kind, axis, v, sign) in enumerate(mats):
            dT = dT @ (sign * _delem(kind, axis, v) if idx == j else _elem(kind, axis, v))
        W = dT[:3, :3] @ T[:3, :3].T
        J[:3, col] = dT[:3, 3]
        J[3:, col] = [W[2, 1], W[0, 2], W[1, 0]]
    return T, J


@pytest.fixture(scope="module")
def evaluate():
    return jax.jit(jax.vmap(lambda s, q: s.pose_and_jacobian(q), in_axes=(None, 0)))


def _random_q(system, seed):
    return np.random.default_rng(seed).uniform(system.q_low, system.q_high, size=(B, system.n_act))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SEQUENCES))
def test_pose_and_jacobian_match_numpy_product_rule(name, evaluate):
    s = build(name)
    qs = _random_q(s, 1)
    (p, R), J = evaluate(s, qs)
    for b in range(B):
        T, Jr = numpy_fk_jacobian(SEQUENCES[name], qs[b])
        np.testing.assert_allclose(p[b], T[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(R[b], T[:3, :3], atol=POS_TOL)
        np.testing.assert_allclose(J[b], Jr, atol=JAC_TOL)


@pytest.mark.slow
def test_ur5e_ets_equals_standard_dh_chain(evaluate):
    s = build("ur5e_dh")
    qs = _random_q(s, 2)
    (p, R), _ = evaluate(s, qs)
    for b in range(B):
        T = np.eye(4)
        for i in range(6):
            ct, st = np.cos(qs[b, i]), np.sin(qs[b, i])
            ca, sa = np.cos(UR5E_DH["alpha"][i]), np.sin(UR5E_DH["alpha"][i])
            a, d = UR5E_DH["a"][i], UR5E_DH["d"][i]
            T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                              [0, 0, 0, 1.0]])
        np.testing.assert_allclose(p[b], T[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(R[b], T[:3, :3], atol=POS_TOL)


# ------------------------------------------------------------------ roboticstoolbox-python (test extra)
def _rtb_ets(rtb, seq):
    E = rtb.ET
    out = []
    for kind, axis, c, sign in _tokens(seq):
        ctor = getattr(E, ("R" if kind == "R" else "t") + "xyz"[axis])
        out.append(ctor(flip=sign < 0) if c is None else ctor(c))
    return rtb.ETS(out)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SEQUENCES))
def test_pose_and_jacobian_match_roboticstoolbox(name, evaluate):
    rtb = pytest.importorskip("roboticstoolbox")
    ets = _rtb_ets(rtb, SEQUENCES[name])
    s = build(name)
    qs = _random_q(s, 3)
    (p, R), J = evaluate(s, qs)
    for b in range(B):
        T = np.asarray(ets.fkine(qs[b]).A)
        np.testing.assert_allclose(p[b], T[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(R[b], T[:3, :3], atol=POS_TOL)
        np.testing.assert_allclose(J[b], np.asarray(ets.jacob0(qs[b])), atol=JAC_TOL)


@pytest.mark.slow
def test_roboticstoolbox_ets_object_is_accepted(evaluate):
    """An rtb ETS with flip, offset, jindex order, qlim and a general SE3 constant builds the same kinematics."""
    rtb = pytest.importorskip("roboticstoolbox")
    E = rtb.ET
    T_const = np.array([[0, -1, 0, 0.02], [1, 0, 0, 0.01], [0, 0, 1, 0.05], [0, 0, 0, 1.0]])
    j0, j1, j2 = E.Rz(jindex=2, qlim=[-1.0, 1.0]), E.Ry(jindex=0, flip=True), E.tx(jindex=1, qlim=[0.0, 0.2])
    j1.offset = 0.3  # joint moves by -q + 0.3
    ets = rtb.ETS([E.tz(0.1), j0, E.SE3(T_const), j1, E.tz(0.2), j2, E.Rx(0.5), E.tz(0.05)])
    s = from_ets(ets, task_dim=6, q_low=[-1, -1, 0.0], q_high=[1, 1, 0.2])
    qs = _random_q(s, 4)
    (p, R), J = evaluate(s, qs)
    jindex = [2, 0, 1]  # of the joints in chain order
    for b in range(B):
        np.testing.assert_allclose(p[b], ets.fkine(qs[b]).A[:3, 3], atol=POS_TOL)
        # rtb's fkine reads q[jindex] but its jacob0 lists the columns in chain order: column c is d/dq[jindex[c]]
        np.testing.assert_allclose(J[b][:, jindex], ets.jacob0(qs[b]), atol=JAC_TOL)
    h = 1e-6  # and ours is d/dq in q's order: central differences of rtb's fkine
    fd = np.stack([(ets.fkine(qs[0] + h * e).A[:3, 3] - ets.fkine(qs[0] - h * e).A[:3, 3]) / (2 * h)
                   for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(J[0][:3], fd, atol=1e-8)
    with pytest.raises(ValueError, match="prismatic"):
        from_ets(rtb.ETS([E.Rz(), E.tx()]))  # no qlim on the slide, none given
    s_default = from_ets(rtb.ETS([E.Rz(qlim=[-0.5, 0.7]), E.tx(0.1)]))
    np.testing.assert_allclose([s_default.q_low[0], s_default.q_high[0]], [-0.5, 0.7])


# ------------------------------------------------------------------ the seed's arm, forms, errors, tracing
@pytest.mark.slow
def test_arm5_geometry_and_limits():
    s = arm5(task_dim=6)
    assert (s.n_act, s.name) == (5, "arm5")
    np.testing.assert_allclose(s.q_low, ARM5_Q_LOW)
    np.testing.assert_allclose(s.q_high, ARM5_Q_HIGH)
    p, R = s.pose(jnp.zeros(5))  # straight up: 0.10 + 0.15 + 0.15 + 0.06 + 0.04
    np.testing.assert_allclose(p, [0, 0, 0.5], atol=1e-15)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-15)
    J = s.jacobian(jnp.array([0.3, 0.4, 0.9, 0.6, -0.2]))
    assert np.linalg.matrix_rank(np.asarray(J), tol=1e-9) == 5  # 6x5: no tool yaw
    np.testing.assert_allclose(J[:3, 4], 0.0, atol=1e-15)  # wrist roll about the tool axis never moves the tip


@pytest.mark.slow
def test_string_forms_agree():
    q = jnp.array([0.3, -0.7, 1.1, 0.4, 0.2])
    ref = arm5(task_dim=6).pose_and_jacobian(q)
    one_string = " ⊕ ".join(["tz(0.1)", "Rz(q0)", "Ry(q1)", "tz(0.15)", "Ry(q2)", "Tz(3*0.05)", "Ry(q3)", "tz(.06)",
                             "Rz(q4)", "tz(0.04)"])
    alt = from_ets(one_string, task_dim=6, q_low=ARM5_Q_LOW, q_high=ARM5_Q_HIGH).pose_and_jacobian(q)
    chex.assert_trees_all_close(ref, alt, atol=1e-15)
    flipped = from_ets(["Rz(-q)", "tx(1.0)"], task_dim=6)
    np.testing.assert_allclose(flipped.pose(jnp.array([0.5]))[0], [np.cos(0.5), -np.sin(0.5), 0], atol=1e-15)


@pytest.mark.parametrize(
    "ets, kw, match",
    [
        (["tz(0.1)", "Qz"], {}, r"element 1 \('Qz'\)"),
        (["tz(abc)", "Rz"], {}, r"element 0 .*cannot read 'abc'"),
        (["Rz()"], {}, "empty parentheses"),
        (["tz(0.1)", "Rx(0.2)"], {}, "no joint variable"),
        (["Rz", 0.3], {}, "element 1: expected a string"),
        ("Rz(q0) Ry(q0)", {}, "permutation"),
        (["tz(1e400)", "Rz"], {}, "finite"),
        (["Rz", "Ry"], dict(q_low=[0.0, 0.0], q_high=[1.0, 0.0]), "q_low must be < q_high"),
        (["Rz", "Ry"], dict(q_low=[0.0, 0.0, 0.0]), "q_low must have shape"),
        (["Rz", "tx"], {}, "prismatic: give q_low and q_high"),
        (["Rz"], dict(task_dim=4), "task_dim"),
        (42, {}, "ets must be a list"),
    ],
)
def test_bad_input_is_named_before_compute(ets, kw, match):
    with pytest.raises(ValueError, match=match):
        from_ets(ets, **kw)


def test_parse_keeps_constants_and_joints():
    els = parse_ets(["tz(0.1)", "Rz", "Rx(pi/2)"])
    np.testing.assert_allclose(els[0][:3, 3], [0, 0, 0.1])
    assert els[1].kind == "R" and els[1].axis == 2 and els[1].value is None
    np.testing.assert_allclose(els[2][:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-16)


@pytest.mark.slow
class TestTracing(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_jit_and_eager_agree(self):
        s = arm5(task_dim=6)
        q = jnp.array([0.2, 0.5, 0.8, -0.3, 0.1])
        out = self.variant(lambda s_, q_: s_.pose_and_jacobian(q_))(s, q)
        chex.assert_trees_all_close(out, (s.pose(q), s.jacobian(q)), atol=1e-14)

    def test_rebuilt_and_swept_systems_do_not_retrace(self):
        @jax.jit
        @chex.assert_max_traces(n=1)
        def tip(system, q):
            return system.pose(q)[0]

        q = jnp.array([0.1, 0.2, 0.3, 0.4, 0.5])
        tip(arm5(), q)
        tip(arm5(m_a=0.01), q)  # another system, same ETS: same static pose map
        longer = arm5().params.replace(pos=arm5().params.pos.at[2, 2].set(0.25))  # a data field: no retrace
        np.testing.assert_allclose(tip(arm5().replace(params=longer), q), tip(arm5(), q) + 0.1 * np.array(
            [np.sin(0.2) * np.cos(0.1), np.sin(0.2) * np.sin(0.1), np.cos(0.2)]), atol=1e-15)

    def test_vmap_over_link_lengths(self):
        s = arm5()
        lengths = jnp.array([0.1, 0.2, 0.3])
        pos = jnp.broadcast_to(s.params.pos, (3,) + s.params.pos.shape).at[:, 2, 2].set(lengths)
        params = type(s.params)(rot=jnp.broadcast_to(s.params.rot, (3,) + s.params.rot.shape), pos=pos)
        tips = jax.vmap(lambda m: s.replace(params=m).pose(jnp.zeros(5))[0])(params)
        np.testing.assert_allclose(tips[:, 2], 0.1 + 0.15 + lengths + 0.1, atol=1e-15)
