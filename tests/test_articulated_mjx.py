"""MJX against native MuJoCo on articulated scenes with joint friction loss.

MJX (impl "jax") builds friction-loss constraint rows only for the dofs marked
in the static mask ``dof_hasfrictionloss`` computed at ``mjx.put_model``;
:func:`~selfid_jax.articulated.scenes.apply_mjx` marks the object's dofs (the
template has no friction loss). The reference is native MuJoCo.
"""

import jax
import numpy as np
import pytest
from helpers_articulated import PADS, rollout_params, ur5e_arm

from selfid_jax.articulated import scenes, sim


def _drawers(frictionlosses):
    """One drawer per friction loss [N] (same axis and damping 5 N s/m): ObjectParams with leading axis."""
    pops = [scenes.population("prismatic", 1, 3, misalign_deg=10.0, damping=(5.0, 5.0), frictionloss=(f, f))
            for f in frictionlosses]
    return scenes.ObjectParams(*(np.concatenate(a) for a in zip(*pops)))


@pytest.mark.slow  # > 1 s on 2 shared cores
def test_apply_mjx_marks_the_friction_loss_rows():
    """The template has no friction loss; apply_mjx adds one FRICTION_DOF row for the drawer's slide."""
    from mujoco import mjx

    m, lay = scenes.compile_scene("prismatic", np.zeros(3), np.eye(3))
    base = mjx.put_model(m, impl="jax")
    assert not base._impl.dof_hasfrictionloss.any()
    model = scenes.apply_mjx(base, lay, scenes.ObjectParams(*(a[0] for a in _drawers([0.0]))))
    assert list(np.nonzero(model._impl.dof_hasfrictionloss)[0]) == [lay.obj_dofs[0]]
    assert float(model.dof_frictionloss[lay.obj_dofs[0]]) == scenes.FRICTIONLOSS_FLOOR  # 0 N floored
    assert mjx.make_data(model)._impl.efc_type.shape[0] == mjx.make_data(base)._impl.efc_type.shape[0] + 1


@pytest.mark.slow
def test_native_and_mjx_agree_with_friction_loss():
    """Drawers with friction loss 0 and 1 N, Turbo keeping u0, 15 control steps x 10 physics steps: to 1e-7 m.

    Before apply_mjx marked the friction-loss dofs, MJX dropped the 1 N friction loss and moved the handle
    2.4x further in the first control step."""
    arm, q0, p1, R1 = ur5e_arm()
    m, lay = scenes.compile_scene("prismatic", p1, R1)
    obj = _drawers([0.0, 1.0])
    out = {}
    with jax.numpy_rank_promotion("allow"):
        for backend in ("native", "mjx"):
            st = sim.make_static(backend, lay, m, PADS, arm, q0, steps=15, substeps=10, stride=1)
            params = rollout_params(obj, [sim.Controller.TURBO_U0] * 2)
            out[backend] = jax.jit(jax.vmap(lambda p, st=st: sim.rollout(st, p)))(params)
    a, b = out["native"], out["mjx"]
    h = np.asarray(a.handle_trace)
    assert np.all(np.max(np.abs(h - h[:, :1]), axis=(1, 2)) > 1e-4)  # both handles moved
    assert float(np.max(np.abs(h[0] - h[1]))) > 1e-5  # and the friction loss made a difference
    np.testing.assert_allclose(np.asarray(b.handle_trace), h, atol=1e-7)
    np.testing.assert_allclose(np.asarray(b.dev_trace), np.asarray(a.dev_trace), atol=1e-7)
    print("max |handle diff| [m] (f = 0, 1 N):", np.max(np.abs(np.asarray(b.handle_trace) - h), axis=(1, 2)))
