"""Closed-chain hands: pose maps that run a solve (kinematic Newton, MJX or native MuJoCo settling).

:mod:`~selfid_jax.systems.hands.settle` holds the generic settle loops (any
MJCF hand with position actuators and a POM site);
:mod:`~selfid_jax.systems.hands.stewart` the 6-6 Stewart Hand
(``stewart_hand(backend="kinematic" | "mjx" | "native")``);
:mod:`~selfid_jax.systems.hands.model_o_hand` the Yale Model O
(``model_o(backend=...)``). Both run in float64: build and call them under
``with jax.enable_x64(True):``.
"""

from selfid_jax.systems.hands.model_o_hand import (  # noqa: F401
    MODEL_O_XML,
    ModelOKinematicPose,
    ModelOParams,
    TiltGuardedPose,
    model_o,
    model_o_home,
    model_o_keyframe,
)
from selfid_jax.systems.hands.settle import (  # noqa: F401
    MjxSettlePose,
    NativeSettlePose,
    SettleParams,
    mjx_model,
    mjx_settle,
    native_pose_batch,
    native_settle,
)
from selfid_jax.systems.hands.stewart import (  # noqa: F401
    STEWART_XML,
    stewart_hand,
    stewart_home,
    stewart_inverse_jacobian,
    stewart_native_batch,
)
