"""Estimation-ablation figures (paper Fig. 5, the noise and m_a figures), from saved results.

:func:`plot` is the ``ablation`` experiment's ``plot``
(:mod:`selfid_jax.experiments.ablation`); the drawing is
:func:`selfid_jax.experiments.common.figures.ablation_figures`, whose method
styles the E-KM study script shares.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..common.figures import ablation_figures

__all__ = ["plot"]


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """``ablation``, ``ablation_noise`` and (with several m_a) ``ablation_m_a``
    (:func:`~selfid_jax.experiments.common.figures.ablation_figures`)."""
    return ablation_figures(table, summary, out_dir)
