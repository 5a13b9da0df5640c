"""The experiments: one module per registered experiment (config schema, build, compute, summary, figures), plus
common/."""
