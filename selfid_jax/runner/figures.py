"""Saving figures into a run directory: PNG and PDF per figure, each written whole (temporary file + rename)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

from selfid_jax.runner.files import atomic_write_bytes

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["matrix_panel", "right_inverse_panels", "save_figure"]


def save_figure(fig: Figure, out_dir: str | Path, name: str, *, dpi: int = 150) -> list[Path]:
    """Write ``fig`` as ``out_dir/name.png`` and ``out_dir/name.pdf``; returns both paths.

    Each file is rendered in memory and written atomically, so an interrupted or
    disk-full save leaves the previous figure (or none), never a partial one; an
    ``OSError`` names the file. A figure with a layout engine (constrained or
    tight layout) is saved at its own size, which that engine already fills, and
    laid out once, by the first file's draw; others are cropped to their contents
    (``bbox_inches="tight"``, one more draw of the figure per file: 1.1 s of the
    demo's 3.6 s per file).
    """
    out_dir = Path(out_dir)
    paths = [out_dir / f"{name}.png", out_dir / f"{name}.pdf"]
    engine = fig.get_layout_engine()
    crop = None if engine is not None else "tight"
    try:
        for p in paths:
            buf = io.BytesIO()
            fig.savefig(buf, format=p.suffix[1:], dpi=dpi, bbox_inches=crop)
            atomic_write_bytes(p, buf.getvalue())
            if engine is not None:  # laid out by the first draw: the second file keeps that layout
                fig.set_layout_engine("none")
    finally:
        if engine is not None:
            fig.set_layout_engine(engine)
    return paths


def matrix_panel(ax, mat, title: str, cols: list[str], rows: list[str], vmax: float):
    """Draw ``mat (r, c)`` as a heat map on ``ax`` with each value written in its cell; returns the image."""
    import numpy as np

    im = ax.imshow(mat, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    ax.set_title(title, fontsize=9)
    ax.set_xticks(range(len(cols)), cols)
    ax.set_yticks(range(len(rows)), rows)
    for (i, j), v in np.ndenumerate(mat):  # white on the dark ends of the colour map
        ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=7, color="w" if abs(v) > 0.6 * vmax else "k")
    return im


def right_inverse_panels(axes, J, estimate, names: list[str], prefix: str):
    """``J Ĵ`` and ``J Ĵ - I`` on two axes: ``J (m, n)`` a Jacobian, ``estimate (n, m)`` an inverse of it.

    Every right inverse of ``J`` gives ``J Ĵ = I``; with more actuators than
    task axes they differ in ``J``'s null space, so the product, not ``Ĵ``
    beside ``J^+``, says whether an estimate is right. Returns the image."""
    import numpy as np

    product = np.asarray(J) @ np.asarray(estimate)
    m = product.shape[0]
    im = matrix_panel(axes[0], product, rf"{prefix}$J\hat J$ ($I$ for any right inverse of $J$)", names, names, 1.0)
    matrix_panel(axes[1], product - np.eye(m),
                 rf"{prefix}$J\hat J - I$: $\|\cdot\|_F$ = {np.linalg.norm(product - np.eye(m)):.3f}", names, names,
                 1.0)
    return im
