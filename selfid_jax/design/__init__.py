"""Self-ID design by gradient: the self-ID magnitude ``m_a`` scored through self-ID, estimate and rollout.

Re-exports :mod:`selfid_jax.design.search` (``design_loss``, ``grid_search``, ``refine``, ``optimize``, ...).
"""

from selfid_jax.design.search import (
    FOLLOW_FROM,
    DesignInfo,
    DesignParams,
    DesignResult,
    GridResult,
    RefineResult,
    SafeTangentPose,
    design_loss,
    design_params,
    design_value_and_grad,
    gradient_reliable,
    grid_search,
    needs_safe_tangents,
    optimize,
    refine,
    safe_tangents,
)

__all__ = ["FOLLOW_FROM", "DesignInfo", "DesignParams", "DesignResult", "GridResult", "RefineResult",
           "SafeTangentPose", "design_loss", "design_params", "design_value_and_grad", "gradient_reliable",
           "grid_search", "needs_safe_tangents", "optimize", "refine", "safe_tangents"]
