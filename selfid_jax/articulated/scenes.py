"""Articulated objects written as MJCF from parameters (nothing downloaded), and a seeded population.

Every scene has the same gripper and the object of one kind; the kinds share
one MJCF template each, and an object is that template plus a few model
fields (:class:`ObjectParams`), so a whole population of one kind batches as
one MJX model with per-object fields, and native MuJoCo sets the same fields
on one ``MjModel``.

Frames: ``G1`` is the gripper's (= the arm's tool flange) pose at the start
(world frame); the handle starts there (seed Eq. 1), and every object
parameter is expressed in ``G1``. The base velocity ``u0`` points along
``G1``'s x axis (the known rough direction); the pads close along y; the
handle bar runs along z.

Gripper, two grasp models (``SceneSettings.grasp``):

* ``"weld"`` (the original): a mocap body ``target`` moved by the arm, a free
  ``gripper`` body (0.5 kg) welded to it (``solref`` ``drive_solref``: the body
  carries velocity, so the object's damping and friction loss load it), and a
  ``gel`` body on six spring-damper joints under the gripper (shear/normal
  stiffness ``gel_k`` N/m, torsional ``gel_kr`` N m/rad) welded to the handle:
  the compliant pads. The gel-to-handle weld is in series with the gel, and
  MuJoCo clamps a weld's time constant to twice the timestep, so the
  effective grasp stiffness is about 7.3 kN/m at ``gel_k`` 20 kN/m (measured
  on a static pull), whatever ``grasp_solref`` says.
* ``"spring"``: the gripper is the mocap body ``target`` itself (the arm's
  tracking taken as exact) and the grasp is an explicit spring-damper wrench
  between it and the handle, applied to the handle every physics step by
  :mod:`selfid_jax.articulated.sim` (stiffness ``k`` [N/m], ``kr`` [N m/rad] and dampings per
  rollout): the stiffness is exactly the configured one, from soft to
  near-rigid (at ``k = 1e6`` N/m the physics timestep must be <= about
  0.7 ms; the experiment checks it).

No-slip holds by construction; a slip is declared (and
the rollout failed) when the in-hand translation exceeds ``slip`` m or the
rotation ``slip_rot`` rad. There are no contacts (all geoms have
``contype = conaffinity = 0``): the MJX zero-contact elliptic-cone crash
cannot happen, and ``cone`` is pyramidal anyway. Gravity is off (objects are
loaded by their damping, friction loss and inertia only).

Kinds:

* ``prismatic``: a drawer (1 kg) on a slide along ``axis``; progress = slide / 0.25 m.
* ``revolute``: a door (2 kg) on a hinge along ``axis`` through the point
  ``hinge`` (``|hinge|`` = radius); progress = angle / 60 deg.
* ``helical``: a crank: hinge along ``axis`` through ``hinge`` plus a slide
  along the same axis, coupled by a joint equality ``slide = pitch * angle``;
  progress = angle / 60 deg.
* ``bezier``: a toy train on a planar track in ``G1``'s x-y plane: slides x
  and y and a yaw hinge; equality constraints ``y = P(x)`` and ``yaw = Q(x)``
  (MuJoCo joint equalities are quartic polynomials). ``P`` is the Bezier curve
  of order ``n`` with control points evenly spaced in x (so ``x(s) = L s`` and
  ``y`` is a degree-``n`` polynomial in ``x``): exact for ``n <= 4``, the
  least-squares quartic for ``n = 5`` (its distance to the order-5 curve is
  recorded in ``fit_error``). ``Q`` is the least-squares quartic of the track
  heading ``atan P'(x) - atan P'(0)``. Progress = x / L; the end is reached at
  progress ``>= 0.98``.

The seed's simulated population (its Sec. 4.1 and Fig. 3: 50 prismatic-joint
and 50 revolute-joint objects from PartNet-Mobility, and 100 Bezier tracks,
25 each of orders 2, 3, 4 and 5) is :data:`PAPER_MIX`; :func:`paper_counts`
splits any number of objects in its proportions and :func:`paper_population`
draws them from a seed. The seed has no cranks in simulation (its helical
vise is a real-world object, Sec. 5.1); ``helical`` stays a kind of its own.
Drawers and doors here are generated (a slide or a hinge with random axis,
radius and resistance), not PartNet-Mobility meshes.
"""

from __future__ import annotations

import functools
from math import comb
from typing import NamedTuple, TypeAlias

import jax
import numpy as np

ParamArray: TypeAlias = jax.Array | np.ndarray
"""A parameter leaf: numpy where a host builds the rows of a sweep, a ``jax.Array`` once traced."""

__all__ = [
    "KINDS",
    "Layout",
    "ObjectParams",
    "SceneSettings",
    "apply_mjx",
    "apply_native",
    "compile_scene",
    "paper_counts",
    "paper_population",
    "population",
    "progress",
    "scene_xml",
]

KINDS = ("prismatic", "revolute", "helical", "bezier")
SUCCESS = {"prismatic": 0.25, "revolute": np.pi / 3, "helical": np.pi / 3}  # m, rad, rad; bezier: L
BEZIER_END = 0.98
PAPER_MIX = {"prismatic": 50, "revolute": 50, "bezier": 100}  # the seed's Sec. 4.1: 200 objects, no cranks
PAPER_ORDERS = (2, 3, 4, 5)  # the seed's Bezier orders, 25 tracks of each


class SceneSettings(NamedTuple):
    """Static simulation settings (part of the MJCF)."""

    timestep: float = 0.002  # s
    gel_k: float = 20000.0  # N/m
    gel_c: float = 20.0  # N s/m
    gel_kr: float = 5.0  # N m/rad
    gel_cr: float = 0.05  # N m s/rad
    drive_solref: float = 0.005  # s, weld time constant mocap -> gripper
    grasp_solref: float = 0.004  # s, weld time constant gel -> handle
    track_solref: float = 0.004  # s, time constant of the crank's screw and the tracks' y(x), yaw(x) couplings
    grasp: str = "weld"  # grasp model: "weld" (gel joints + welds) or "spring" (explicit wrench, see the module doc)


class ObjectParams(NamedTuple):
    """Per-object model fields, ``G1`` frame (leading batch axis in a population)."""

    axis: ParamArray  # (3,) unit joint axis (slide for prismatic; hinge otherwise; bezier: unused)
    hinge: ParamArray  # (3,) point on the hinge axis [m] (prismatic, bezier: 0)
    damping: ParamArray  # () joint damping [N s/m or N m s/rad]
    frictionloss: ParamArray  # () joint friction loss [N or N m]
    poly: ParamArray  # (2, 5) joint-equality polycoef: helical [0, pitch, 0, 0, 0]; bezier P and Q
    scale: ParamArray  # () progress scale: 0.25 m, pi/3 rad, or the track length L [m]
    order: ParamArray  # () int Bezier order (0 for other kinds)
    fit_error: ParamArray  # () bezier: max |P - Bezier| [m] (0 when exact)


def _quat(R):
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, float).ravel())
    return q


def _fmt(v):
    return " ".join(f"{float(x):.17g}" for x in np.ravel(v))


_GRIPPER = """
    <body name="target" mocap="true" pos="{p}" quat="{q}"/>
    <body name="gripper" pos="{p}" quat="{q}">
      <freejoint name="gripper_free"/>
      <inertial pos="0 0 0" mass="0.5" diaginertia="1e-3 1e-3 1e-3"/>
      <geom type="box" pos="0 0.012 0" size="0.012 0.003 0.012" contype="0" conaffinity="0" rgba=".3 .3 .3 1"/>
      <geom type="box" pos="0 -0.012 0" size="0.012 0.003 0.012" contype="0" conaffinity="0" rgba=".3 .3 .3 1"/>
      <body name="gel">
        <joint name="gel_x" type="slide" axis="1 0 0" stiffness="{k}" damping="{c}"/>
        <joint name="gel_y" type="slide" axis="0 1 0" stiffness="{k}" damping="{c}"/>
        <joint name="gel_z" type="slide" axis="0 0 1" stiffness="{k}" damping="{c}"/>
        <joint name="gel_rx" type="hinge" axis="1 0 0" stiffness="{kr}" damping="{cr}"/>
        <joint name="gel_ry" type="hinge" axis="0 1 0" stiffness="{kr}" damping="{cr}"/>
        <joint name="gel_rz" type="hinge" axis="0 0 1" stiffness="{kr}" damping="{cr}"/>
        <inertial pos="0 0 0" mass="0.02" diaginertia="1e-6 1e-6 1e-6"/>
      </body>
    </body>"""

_GRIPPER_SPRING = """
    <body name="target" mocap="true" pos="{p}" quat="{q}">
      <geom type="box" pos="0 0.012 0" size="0.012 0.003 0.012" contype="0" conaffinity="0" rgba=".3 .3 .3 1"/>
      <geom type="box" pos="0 -0.012 0" size="0.012 0.003 0.012" contype="0" conaffinity="0" rgba=".3 .3 .3 1"/>
    </body>"""

_HANDLE = """<body name="handle" pos="{pos}">
          <inertial pos="0 0 0" mass="0.1" diaginertia="1e-4 1e-4 1e-5"/>
          <geom type="cylinder" size="0.006 0.03" contype="0" conaffinity="0" rgba=".8 .5 .2 1"/>
        </body>"""

_OBJECT = {
    "prismatic": """
    <body name="part" pos="{p}" quat="{q}">
      <joint name="obj" type="slide" axis="1 0 0"/>
      <inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
      {handle}
    </body>""",
    "revolute": """
    <body name="part" pos="{p}" quat="{q}">
      <joint name="obj" type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="2" diaginertia="0.05 0.05 0.05"/>
      {handle}
    </body>""",
    "helical": """
    <body name="part" pos="{p}" quat="{q}">
      <joint name="obj" type="hinge" axis="0 0 1"/>
      <joint name="obj_slide" type="slide" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
      {handle}
    </body>""",
    "bezier": """
    <body name="part" pos="{p}" quat="{q}">
      <joint name="obj" type="slide" axis="1 0 0"/>
      <joint name="obj_y" type="slide" axis="0 1 0"/>
      <joint name="obj_yaw" type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="0.5" diaginertia="0.002 0.002 0.002"/>
      {handle}
    </body>""",
}

_EQ_EXTRA = {
    "prismatic": "",
    "revolute": "",
    "helical": '<joint name="screw" joint1="obj_slide" joint2="obj" polycoef="0 0.01 0 0 0" solref="{t} 1"/>',
    "bezier": '<joint name="track_y" joint1="obj_y" joint2="obj" polycoef="0 0 0 0 0" solref="{t} 1"/>\n'
              '    <joint name="track_yaw" joint1="obj_yaw" joint2="obj" polycoef="0 0 0 0 0" solref="{t} 1"/>',
}


def scene_xml(kind: str, p1, R1, settings: SceneSettings = SceneSettings()) -> str:
    """MJCF of the template of ``kind`` with the gripper and handle at ``(p1 (3,), R1 (3, 3))`` (world)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    s = settings
    if s.grasp not in ("weld", "spring"):
        raise ValueError(f"grasp must be 'weld' or 'spring', got {s.grasp!r}")
    p, q = _fmt(p1), _fmt(_quat(R1))
    if s.grasp == "weld":
        gripper = _GRIPPER.format(p=p, q=q, k=s.gel_k, c=s.gel_c, kr=s.gel_kr, cr=s.gel_cr)
        welds = (f'<weld name="drive" body1="target" body2="gripper" solref="{s.drive_solref} 1"/>\n'
                 f'    <weld name="grasp" body1="gel" body2="handle" solref="{s.grasp_solref} 1"/>')
    else:
        gripper, welds = _GRIPPER_SPRING.format(p=p, q=q), ""
    obj = _OBJECT[kind].format(p=p, q=q, handle=_HANDLE.format(pos="0 0 0"))
    return f"""<mujoco model="articulated_{kind}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{s.timestep}" gravity="0 0 0" integrator="Euler" cone="pyramidal" impratio="1"/>
  <worldbody>{gripper}{obj}
  </worldbody>
  <equality>
    {welds}
    {_EQ_EXTRA[kind].format(t=s.track_solref)}
  </equality>
</mujoco>"""


class Layout(NamedTuple):
    """Indices into the compiled template (static ints / tuples)."""

    kind: str
    part: int  # body id of the moving part
    handle: int  # body id of the handle
    gripper: int  # body id of the gripper (the mocap ``target`` under the spring grasp)
    obj_jnts: tuple  # joint ids of the object (first = the progress joint)
    obj_dofs: tuple  # their dof addresses
    obj_qpos: int  # qpos address of the progress joint
    gripper_qpos: int  # qpos address of the gripper's free joint (pos 3, quat 4); -1 under the spring grasp
    eqs: tuple  # ids of the object's joint equalities
    p1: tuple  # (3,) G1 position (world)
    R1: tuple  # (3, 3) G1 rotation (world), nested tuples
    grasp: str = "weld"  # grasp model (SceneSettings.grasp)


@functools.lru_cache(maxsize=16)
def _compile(xml: str):
    import mujoco

    return mujoco.MjModel.from_xml_string(xml)


def compile_scene(kind: str, p1, R1, settings: SceneSettings = SceneSettings()):
    """``(mujoco.MjModel, Layout)`` of the template of ``kind`` (cached by its XML)."""
    import mujoco

    m = _compile(scene_xml(kind, p1, R1, settings))
    name = functools.partial(mujoco.mj_name2id, m)
    jn = [j for j in ("obj", "obj_slide", "obj_y", "obj_yaw") if name(mujoco.mjtObj.mjOBJ_JOINT, j) >= 0]
    jids = tuple(int(name(mujoco.mjtObj.mjOBJ_JOINT, j)) for j in jn)
    eqs = tuple(int(name(mujoco.mjtObj.mjOBJ_EQUALITY, e)) for e in ("screw", "track_y", "track_yaw")
                if name(mujoco.mjtObj.mjOBJ_EQUALITY, e) >= 0)
    gfree = int(name(mujoco.mjtObj.mjOBJ_JOINT, "gripper_free"))
    spring = settings.grasp == "spring"
    layout = Layout(kind, int(name(mujoco.mjtObj.mjOBJ_BODY, "part")), int(name(mujoco.mjtObj.mjOBJ_BODY, "handle")),
                    int(name(mujoco.mjtObj.mjOBJ_BODY, "target" if spring else "gripper")), jids,
                    tuple(int(m.jnt_dofadr[j]) for j in jids), int(m.jnt_qposadr[jids[0]]),
                    -1 if spring else int(m.jnt_qposadr[gfree]), eqs, tuple(map(float, np.ravel(p1))),
                    tuple(tuple(map(float, r)) for r in np.asarray(R1)), settings.grasp)
    return m, layout


def _fields(layout: Layout, obj: ObjectParams, xp):
    """The model-field values of one object: ``dict(name -> (index, value))`` (numpy or jax.numpy ``xp``)."""
    p1 = xp.asarray(layout.p1)
    R1 = xp.asarray(layout.R1)
    axis, hinge = xp.asarray(obj.axis), xp.asarray(obj.hinge)
    out = {}
    if layout.kind in ("prismatic", "revolute", "helical"):
        out["jnt_axis"] = [(j, axis) for j in layout.obj_jnts]
    if layout.kind in ("revolute", "helical"):
        out["body_pos"] = [(layout.part, p1 + R1 @ hinge), (layout.handle, -hinge)]
    n_res = 1 if layout.kind == "helical" else len(layout.obj_dofs)  # helical: resistance on the hinge
    out["dof_damping"] = [(d, obj.damping) for d in layout.obj_dofs[:n_res]]
    out["dof_frictionloss"] = [(d, obj.frictionloss) for d in layout.obj_dofs[:n_res]]
    poly = xp.asarray(obj.poly)
    out["eq_data"] = [(e, poly[k]) for k, e in enumerate(layout.eqs)]
    return out


def apply_native(m, layout: Layout, obj: ObjectParams) -> None:
    """Write one object's fields into the ``MjModel`` ``m`` (in place)."""
    for field, items in _fields(layout, obj, np).items():
        arr = getattr(m, field)
        for idx, val in items:
            if field == "eq_data":
                arr[idx, :5] = val
            else:
                arr[idx] = val


FRICTIONLOSS_FLOOR = 1e-9  # N or N m: MJX friction-loss rows carry at least this (see apply_mjx)


def apply_mjx(model, layout: Layout, obj: ObjectParams):
    """``model`` (``mjx.Model``) with one object's fields (traceable; vmap over ``obj``).

    MJX (impl "jax") decides at ``mjx.put_model`` which dofs get a friction-loss
    constraint row: the static mask ``model._impl.dof_hasfrictionloss =
    dof_frictionloss > 0`` of the template (0 here), and writing
    ``dof_frictionloss`` afterwards alone leaves the friction loss out. So the
    object's resistance dofs are marked here (the efc size grows by one row
    each: make the ``mjx.Data`` from the returned model). MJX treats a marked
    row with friction loss exactly 0 as an always-active quadratic
    (velocity-locking) row, while native MuJoCo omits it; the value is floored
    at ``FRICTIONLOSS_FLOOR`` so such a row carries at most that force.
    """
    import jax.numpy as jnp

    changes = {}
    fields = _fields(layout, obj, jnp)
    fields["dof_frictionloss"] = [(i, jnp.maximum(v, FRICTIONLOSS_FLOOR)) for i, v in fields["dof_frictionloss"]]
    for field, items in fields.items():
        arr = getattr(model, field)
        for idx, val in items:
            arr = arr.at[idx, :5].set(val) if field == "eq_data" else arr.at[idx].set(val)
        changes[field] = arr
    model = model.replace(**changes)
    impl = getattr(model, "_impl", None)
    if impl is not None and hasattr(impl, "dof_hasfrictionloss"):  # impl "jax"; a static numpy mask (pytree metadata)
        has = np.array(impl.dof_hasfrictionloss, dtype=np.bool_)
        has[[i for i, _ in fields["dof_frictionloss"]]] = True
        model = model.tree_replace({"_impl.dof_hasfrictionloss": has})
    return model


def progress(qpos, layout: Layout, obj: ObjectParams):
    """Normalised progress along the path (1 = success threshold), from ``qpos (nq,)``."""
    return qpos[layout.obj_qpos] / obj.scale


def success_level(kind: str) -> float:
    return BEZIER_END if kind == "bezier" else 1.0


# ----------------------------------------------------------------------------- population


def _rand_rotation(rng, max_angle):
    """Rotation by a uniform angle in ``[0, max_angle]`` about a uniform random axis."""
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * rng.uniform(0.0, max_angle)).as_matrix()


def _bernstein_power(coeffs):
    """Power-basis coefficients (ascending) of ``sum_i b_i C(n,i) s^i (1-s)^(n-i)``."""
    n = len(coeffs) - 1
    out = np.zeros(n + 1)
    for i, b in enumerate(coeffs):
        for k in range(n - i + 1):  # (1-s)^(n-i) = sum_k C(n-i,k) (-s)^k
            out[i + k] += b * comb(n, i) * comb(n - i, k) * (-1) ** k
    return out


def _quartic_fit(x, y):
    """Least-squares ``a1..a4`` of ``y ~ a1 x + ... + a4 x^4`` (no constant: the equality holds at qpos0)."""
    A = np.stack([x**k for k in range(1, 5)], axis=1)
    return np.concatenate([[0.0], np.linalg.lstsq(A, y, rcond=None)[0]])


def _bezier(rng, order, length, amplitude, max_slope_deg):
    n = order
    ys = np.concatenate([[0.0], rng.uniform(-amplitude, amplitude, n)])
    slope_max = np.tan(np.radians(max_slope_deg)) * length / n
    ys[1] = np.clip(ys[1], -slope_max, slope_max)  # the initial tangent is within max_slope of u0
    c = _bernstein_power(ys)  # y(s), s = x / L
    x = np.linspace(0.0, length, 401)
    y_true = np.polyval(c[::-1], x / length)
    if n <= 4:
        P = np.zeros(5)
        P[: n + 1] = c / length ** np.arange(n + 1)
    else:
        P = _quartic_fit(x, y_true)
    y_fit = np.polyval(P[::-1], x)
    dP = np.polyval((P[1:] * np.arange(1, 5))[::-1], x)
    heading = np.arctan(dP) - np.arctan(dP[0])
    Q = _quartic_fit(x, heading)
    return np.stack([P, Q]), float(np.max(np.abs(y_fit - y_true)))


def population(kind: str, n: int, seed: int, *, misalign_deg: float = 15.0, damping=(2.0, 20.0),
               frictionloss=(0.5, 3.0), radius=(0.25, 0.45), crank=(0.1, 0.2), pitch=(0.005, 0.02),
               track=(0.25, 0.35), amplitude=0.06, orders=(2, 3, 4, 5)) -> ObjectParams:
    """``n`` objects of ``kind`` from ``seed``: :class:`ObjectParams` with leading axis ``n`` (numpy).

    Translational resistance (damping [N s/m], friction loss [N]) is drawn
    uniformly in the given ranges; for hinges both are multiplied by the
    radius (friction loss) and its square (damping): the same force at the handle. ``misalign_deg``: the mechanism's
    initial direction differs from ``u0`` (G1 x) by a random rotation of up
    to this angle (drawer axis; door/crank hinge frame about the handle;
    Bezier: the initial tangent's slope is at most this angle). Bezier orders
    cycle through ``orders`` (paper: 25 of each of 2-5 in 100).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    mis = np.radians(misalign_deg)
    rows = []
    for i in range(n):
        damp, fric = rng.uniform(*damping), rng.uniform(*frictionloss)
        axis, hinge, poly = np.array([1.0, 0, 0]), np.zeros(3), np.zeros((2, 5))
        order, fit, scale = 0, 0.0, SUCCESS.get(kind, 0.0)
        if kind == "prismatic":
            axis = _rand_rotation(rng, mis) @ axis
        elif kind in ("revolute", "helical"):
            r = rng.uniform(*(radius if kind == "revolute" else crank))
            side = rng.choice([-1.0, 1.0])
            Rm = _rand_rotation(rng, mis)
            hinge = Rm @ np.array([0.0, side * r, 0.0])  # tangent at the handle = axis x (-hinge) = r x
            axis = Rm @ np.array([0.0, 0.0, side])
            damp, fric = damp * r * r, fric * r  # the same force at the handle
            if kind == "helical":
                poly[0, 1] = rng.uniform(*pitch)
        else:
            order = int(orders[i % len(orders)])
            scale = rng.uniform(*track)
            poly, fit = _bezier(rng, order, scale, amplitude, misalign_deg)
        f64 = functools.partial(np.asarray, dtype=np.float64)
        rows.append(ObjectParams(axis, hinge, f64(damp), f64(fric), poly, f64(scale), np.asarray(order, np.int32),
                                 f64(fit)))
    return ObjectParams(*(np.stack([np.asarray(getattr(r, f)) for r in rows]) for f in ObjectParams._fields))


def paper_counts(n: int) -> dict[str, int]:
    """Objects per kind (every kind of :data:`KINDS`, in order) for ``n`` objects in the seed's proportions.

    :data:`PAPER_MIX` scaled to ``n`` (1/4 prismatic, 1/4 revolute, 1/2
    Bezier; 0 helical) and rounded by largest remainder (ties to the earlier
    kind), so the counts sum to ``n``; ``n = 200`` gives the seed's 50 / 50 /
    100. Bezier orders cycle through :data:`PAPER_ORDERS` in
    :func:`population`, so a multiple of 4 tracks has each order equally often.
    """
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 0:
        raise ValueError(f"paper_counts needs an int n >= 0, got {n!r}")
    total = sum(PAPER_MIX.values())
    exact = {k: n * PAPER_MIX.get(k, 0) / total for k in KINDS}
    out = {k: int(np.floor(v)) for k, v in exact.items()}
    rest = n - sum(out.values())
    for k in sorted(KINDS, key=lambda k: (-(exact[k] - out[k]), KINDS.index(k)))[:rest]:
        out[k] += 1
    return out


def paper_population(n: int, seed: int, **ranges) -> dict[str, ObjectParams]:
    """``n`` objects in the seed's mix (:func:`paper_counts`) from ``seed``: ``{kind: ObjectParams}`` (kinds with a
    count > 0; each as :func:`population` draws it, with the ``ranges`` keywords and Bezier orders 2-5)."""
    return {k: population(k, c, seed, orders=PAPER_ORDERS, **ranges) for k, c in paper_counts(n).items() if c}
