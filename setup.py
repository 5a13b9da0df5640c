"""The package list, the one part of the build that pyproject.toml cannot state without listing every folder.

selfid_jax's subpackages and data folders (systems/assets, robot/data) are found in selfid_jax/; the top-level
experiments/ and its subpackages install as selfid_jax.experiments (``[tool.setuptools.package-dir]`` in
pyproject.toml) and configs/ as the data package selfid_jax.configs (its folders, one per experiment, as data
subpackages: without them setuptools warns that it may drop their YAML), so a wheel holds the same files that a
checkout and an editable install import.
"""

from setuptools import find_namespace_packages, find_packages, setup

setup(
    packages=[
        *find_namespace_packages(include=["selfid_jax", "selfid_jax.*"], exclude=["*.__pycache__"]),
        "selfid_jax.experiments",
        *(f"selfid_jax.experiments.{name}" for name in find_packages("experiments")),
        "selfid_jax.configs",
        *(f"selfid_jax.configs.{name}" for name in find_namespace_packages("configs")),
    ]
)
