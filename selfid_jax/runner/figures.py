"""Saving figures into a run directory: PNG and PDF per figure, each written whole (temporary file + rename)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

from selfid_jax.runner.files import atomic_write_bytes

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["save_figure"]


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
