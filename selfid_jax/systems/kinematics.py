"""Pose maps of an MJCF site over actuator coordinates, and the kinematic model copies they read.

:class:`ChainSitePose` walks the joint chain from the world to the site in
plain JAX (reading a :class:`ChainModel`, the handful of ``MjModel`` arrays the
walk needs, or an ``mjx.Model``) and gives the world-frame site Jacobian from
the same walk; :class:`MjxSitePose` runs ``mjx.kinematics`` on the
``mjx.Model`` of :func:`kinematic_mjx_model`. Both take ``q`` in actuator
coordinates when given a :class:`~selfid_jax.systems.actuation.QposMap`
(``qpos = offset + A q``), else ``q = qpos``, and return
``(p (3,), R (3, 3))`` in the model's length unit.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from selfid_jax.math import geometry
from selfid_jax.systems.actuation import QposMap, joint_label, joint_type_name

__all__ = ["ChainModel", "ChainSitePose", "MjxSitePose", "chain_site_pose", "kinematic_mjx_model"]


def _mjx():
    """``mujoco.mjx``, imported with its stdout notices about the optional Warp backend silenced."""
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


@dataclasses.dataclass(frozen=True)
class ChainModel:
    """The ``MjModel`` arrays :class:`ChainSitePose` reads, as a traced pytree (same names and indexing).

    ``body_pos (nbody, 3)``, ``body_quat (nbody, 4)`` (w, x, y, z), ``jnt_pos``,
    ``jnt_axis (njnt, 3)``, ``qpos0 (nq,)``, ``site_pos (nsite, 3)``,
    ``site_quat (nsite, 4)``; model length unit. A sweep can vmap over any field.
    """

    body_pos: jax.Array
    body_quat: jax.Array
    jnt_pos: jax.Array
    jnt_axis: jax.Array
    qpos0: jax.Array
    site_pos: jax.Array
    site_quat: jax.Array

    @classmethod
    def from_mjmodel(cls, mj) -> ChainModel:
        """The arrays of a ``mujoco.MjModel``, in the default float dtype."""
        fl = jnp.result_type(float)
        return cls(**{f.name: jnp.asarray(np.asarray(getattr(mj, f.name)), fl) for f in dataclasses.fields(cls)})

    def replace(self, **changes) -> ChainModel:
        """``dataclasses.replace`` (e.g. a batched ``site_pos``)."""
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    ChainModel, data_fields=[f.name for f in dataclasses.fields(ChainModel)], meta_fields=[]
)


@dataclasses.dataclass(frozen=True)
class MjxSitePose:
    """Pose map of an MJCF site by ``mjx.kinematics``: ``(mjx.Model, q) -> (site_xpos, site_xmat)``.

    ``qpos = qmap(q)`` (full ``(nq,)``, free-joint quaternions included), or
    ``qpos = q`` without ``qmap``. Hashable by value, so systems rebuilt from
    the same file share compiled code.
    """

    site_id: int
    qmap: QposMap | None = None

    def __call__(self, model, q):
        mjx = _mjx()
        d = mjx.make_data(model)
        qpos = q if self.qmap is None else self.qmap(jnp.asarray(q))
        d = d.replace(qpos=jnp.asarray(qpos, dtype=d.qpos.dtype))
        d = mjx.kinematics(model, d)
        return d.site_xpos[self.site_id], d.site_xmat[self.site_id].reshape(3, 3)


@dataclasses.dataclass(frozen=True)
class ChainSitePose:
    """Pose map of an MJCF site by a plain-JAX product of joint transforms.

    Walks only the bodies from the world to the site's body (static indices),
    reading ``body_pos``, ``body_quat``, ``jnt_pos``, ``jnt_axis``, ``qpos0``,
    ``site_pos`` and ``site_quat`` from ``params`` (a :class:`ChainModel` or an
    ``mjx.Model``; a swept/batched one works too), with rotation matrices and
    without computing other bodies, geoms or sites. Same convention as MuJoCo:
    a hinge rotates about its anchor by ``qpos - qpos0``; a slide translates by
    ``qpos - qpos0``. Only hinge and slide joints may lie on the chain.

    Attributes:
      site_id: site index.
      bodies: body ids from the world's child down to the site's body.
      joints: per body, tuple of ``(joint id, qpos address, is_hinge)``.
      qmap: actuator -> qpos map (then ``q`` is ``(n_act,)``); None: ``q = qpos``.
    """

    site_id: int
    bodies: tuple[int, ...]
    joints: tuple[tuple[tuple[int, int, bool], ...], ...]
    qmap: QposMap | None = None

    def __call__(self, model, q):
        p, R, _ = self._walk(model, q)
        return p, R

    def jacobian(self, model, q):
        """Site Jacobian ``(6, n)`` in the world frame, rows ``[dp/dq; omega/dq]`` (as ``mj_jacSite``).

        Joint column: hinge ``[a x (p - c); a]`` (world axis ``a``, anchor ``c``),
        slide ``[a; 0]``; with a ``qmap`` the actuator column ``i`` is
        ``sum_k col_k A[k, i]`` (``n = n_act``), else ``n = nq``. One walk, about
        one forward-kinematics pass.
        """
        return self.pose_and_jacobian(model, q)[1]

    def pose_and_jacobian(self, model, q):
        """``((p, R), J (6, n))`` from one walk: the pose of :meth:`__call__` and :meth:`jacobian`."""
        p, R, joints = self._walk(model, q)
        cols = []
        for adr, is_hinge, axis_w, anchor in joints:
            if is_hinge:
                cols.append((adr, jnp.concatenate([jnp.cross(axis_w, p - anchor), axis_w])))
            else:
                cols.append((adr, jnp.concatenate([axis_w, jnp.zeros(3, p.dtype)])))
        zero = jnp.zeros(6, p.dtype)
        if self.qmap is not None:
            return (p, R), self.qmap.pullback(cols, zero)
        full = [zero] * jnp.shape(q)[-1]
        for adr, col in cols:
            full[adr] = col
        return (p, R), jnp.stack(full, axis=1)

    def _walk(self, model, q):
        """World pose of the site and, per joint, ``(qpos address, is_hinge, world axis, world anchor)``."""
        q = jnp.asarray(q)
        dtype = jnp.result_type(q, model.body_pos)
        bodies = np.asarray(self.bodies, dtype=np.int32)
        flat = [jt for jnts in self.joints for jt in jnts]
        jid = np.asarray([j for j, _, _ in flat], dtype=np.int32)
        adr = np.asarray([a for _, a, _ in flat], dtype=np.int32)

        body_p = model.body_pos[bodies].astype(dtype)  # (nb, 3)
        body_R = jaxlie.SO3(model.body_quat[bodies].astype(dtype)).as_matrix()  # (nb, 3, 3); quats (w, x, y, z)
        if len(flat):
            qpos = q[adr] if self.qmap is None else self.qmap.rows(q, adr)  # (nj,) qpos of the chain joints
            angle = (qpos - model.qpos0[adr]).astype(dtype)  # (nj,)
            axis = model.jnt_axis[jid].astype(dtype)  # (nj, 3)
            jpos = model.jnt_pos[jid].astype(dtype)  # (nj, 3)
            k = geometry.hat(axis)
            eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), k.shape)
            # Rodrigues for unit axes (MuJoCo normalises jnt_axis): smooth, no division. Kept over
            # geometry.so3_exp (jaxlie): that costs ~1.5x in this walk and ~5-10% in rollout compile time.
            joint_R = eye + jnp.sin(angle)[:, None, None] * k + (1.0 - jnp.cos(angle))[:, None, None] * (k @ k)

        pos = jnp.zeros(3, dtype)
        rot = jnp.eye(3, dtype=dtype)
        joints = []
        i = 0
        for b, jnts in enumerate(self.joints):
            pos = pos + rot @ body_p[b]
            rot = rot @ body_R[b]
            for _, qadr, is_hinge in jnts:
                axis_w = rot @ axis[i]
                if is_hinge:
                    anchor = pos + rot @ jpos[i]
                    rot = rot @ joint_R[i]
                    pos = anchor - rot @ jpos[i]
                    joints.append((qadr, True, axis_w, anchor))
                else:
                    pos = pos + axis_w * angle[i]
                    joints.append((qadr, False, axis_w, None))
                i += 1
        p = pos + rot @ model.site_pos[self.site_id].astype(dtype)
        R = rot @ jaxlie.SO3(model.site_quat[self.site_id].astype(dtype)).as_matrix()
        return p, R, joints


def chain_site_pose(mj, site_id: int, site: str, qmap: QposMap | None = None) -> ChainSitePose:
    """The :class:`ChainSitePose` of site ``site_id`` of ``mujoco.MjModel`` ``mj``.

    Raises:
      ValueError: a free or ball joint on the chain from the world to the site
        (it is named; free/ball joints elsewhere are ignored).
    """
    body = int(mj.site_bodyid[site_id])
    path = []
    while body != 0:
        path.append(body)
        body = int(mj.body_parentid[body])
    path = path[::-1]
    joints = []
    for b in path:
        start, num = int(mj.body_jntadr[b]), int(mj.body_jntnum[b])
        for j in range(start, start + num):
            t = joint_type_name(mj.jnt_type[j])
            if t not in ("hinge", "slide"):
                raise ValueError(
                    f"{joint_label(mj, j)} is a {t} joint on the kinematic chain of site {site!r}; only hinge and "
                    "slide joints may lie between the world and the POM site"
                )
        joints.append(tuple((j, int(mj.jnt_qposadr[j]), joint_type_name(mj.jnt_type[j]) == "hinge")
                            for j in range(start, start + num)))
    return ChainSitePose(int(site_id), tuple(path), tuple(joints), qmap)


def kinematic_mjx_model(mj, label: str = "MJCF"):
    """``mjx.put_model`` of a kinematics-only copy of ``mujoco.MjModel`` ``mj`` (``mj`` is not modified).

    ``mjx.kinematics`` reads only the tree, joint and site fields, so the copy
    overrides what MJX may not implement and kinematics never reads: integrator
    Euler, pyramidal cones, dense constraint Jacobian, Newton solver, every
    enable flag off, no fluid (``density = viscosity = wind = 0``), contacts
    off (``geom_contype = geom_conaffinity = 0``: no collision pairs or mesh
    hulls to prepare), contact sensors and actuator dynamics/gain/bias/
    transmission, equality, sensor and wrap types MJX lacks replaced by
    supported ones (inactive equalities). Do not simulate the result.

    Raises:
      ValueError: what cannot be overridden (flexes, explicit contact pairs of
        unsupported geom types); ``fk="chain"`` needs no ``mjx.Model``.
    """
    import mujoco

    mjx = _mjx()
    if mj.nflex:
        raise ValueError(f"MJCF {label} has flexes, which mjx.put_model cannot load; use fk='chain'")
    mk = copy.deepcopy(mj)
    o = mk.opt
    o.integrator = int(mujoco.mjtIntegrator.mjINT_EULER)
    o.cone = int(mujoco.mjtCone.mjCONE_PYRAMIDAL)
    o.jacobian = int(mujoco.mjtJacobian.mjJAC_DENSE)
    o.solver = int(mujoco.mjtSolver.mjSOL_NEWTON)
    o.enableflags = 0
    o.density, o.viscosity = 0.0, 0.0
    o.wind[:] = 0.0
    mk.geom_contype[:] = 0
    mk.geom_conaffinity[:] = 0
    mk.sensor_type[mk.sensor_type == int(mujoco.mjtSensor.mjSENS_CONTACT)] = int(mujoco.mjtSensor.mjSENS_CLOCK)
    for field, enum, fallback in (
        ("actuator_dyntype", mjx.DynType, mujoco.mjtDyn.mjDYN_NONE),
        ("actuator_gaintype", mjx.GainType, mujoco.mjtGain.mjGAIN_FIXED),
        ("actuator_biastype", mjx.BiasType, mujoco.mjtBias.mjBIAS_NONE),
        ("actuator_trntype", mjx.TrnType, mujoco.mjtTrn.mjTRN_SITE),
        ("eq_type", mjx.EqType, mujoco.mjtEq.mjEQ_CONNECT),
        ("sensor_type", mjx.SensorType, mujoco.mjtSensor.mjSENS_CLOCK),
        ("wrap_type", mjx.WrapType, mujoco.mjtWrap.mjWRAP_JOINT),
    ):
        arr = getattr(mk, field)
        bad = ~np.isin(arr, [int(e) for e in enum])
        arr[bad] = int(fallback)
        if field == "eq_type":
            mk.eq_active0[bad] = 0
    try:
        return mjx.put_model(mk)
    except NotImplementedError as e:
        raise ValueError(f"mjx.put_model cannot load MJCF {label} even for kinematics ({e}); use fk='chain'") from e
