"""The shipped sweep and robot configs (YAML), installed as the data package ``selfid_jax.configs`` and found by name."""
