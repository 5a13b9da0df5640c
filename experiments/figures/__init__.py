"""The experiments' figures, one module per experiment (named after it), drawn from saved results only.

Each ``<experiment>.plot(table, summary, out_dir)`` reads a results table and
a summary (``selfid-jax plot RUN_DIR`` loads ``results.parquet`` and
``summary.json``) and writes PNG and PDF files; the experiment module reaches
it through :func:`selfid_jax.experiments.common.lazy_figures.figures_plot`, so
that matplotlib loads only to draw. Helpers several experiments share are in
:mod:`selfid_jax.experiments.common.figures`.
"""
