"""The package list and the native kernel: the parts of the build that pyproject.toml cannot state.

selfid_jax's subpackages and data folders (systems/assets, robot/data) are found in selfid_jax/; the top-level
experiments/ and its subpackages install as selfid_jax.experiments (``[tool.setuptools.package-dir]`` in
pyproject.toml) and configs/ as the data package selfid_jax.configs (its folders, one per experiment, as data
subpackages: without them setuptools warns that it may drop their YAML), so a wheel holds the same files that a
checkout and an editable install import.

selfid_jax.math._native_kernels is a plain shared library, not a Python module: selfid_jax.math.native loads it
with ctypes and registers its XLA FFI handler. It is built from selfid_jax/math/_native/ against the XLA FFI
headers vendored there (OpenXLA, Apache-2.0), so the build needs no jaxlib. It is optional: without a C++17
compiler the build goes on and the pure-JAX code runs instead. Its two translation units (the step kernel's, which
inlines the others' arithmetic, is the larger) compile side by side, one compiler process per CPU.
"""

import os
from concurrent.futures import ThreadPoolExecutor

from setuptools import Extension, find_namespace_packages, find_packages, setup
from setuptools.command.build_ext import build_ext

NATIVE = Extension(
    "selfid_jax.math._native_kernels",
    sources=["selfid_jax/math/_native/step_kernel.cc", "selfid_jax/math/_native/estimator_kernels.cc"],
    depends=["selfid_jax/math/_native/estimator_kernels.h", "selfid_jax/math/_native/estimator_kernels.inc",
             "selfid_jax/math/_native/xla/ffi/api/ffi.h",
             "selfid_jax/math/_native/xla/ffi/api/api.h", "selfid_jax/math/_native/xla/ffi/api/c_api.h"],
    include_dirs=["selfid_jax/math/_native"],
    language="c++",
    # the vendored headers warn under GCC's defaults (-Wattributes, -Wreturn-type); -Wno-psabi: 32-byte vectors
    # passed by value between the kernel's inline functions; -g0 drops the debug information Python's own flags ask
    # for (-g): the same machine code, the step's unit compiles in 11.3 instead of 15.2 s (6.3 MB object -> 0.45 MB)
    extra_compile_args=["-std=c++17", "-O3", "-g0", "-fno-math-errno", "-Wno-psabi", "-Wno-attributes",
                        "-Wno-return-type"],
    optional=True,
)


class ParallelBuildExt(build_ext):
    """build_ext that compiles an extension's sources side by side: one compiler call per source, at most one per
    CPU this process may run on (the compiler's own ``compile`` runs its sources one after another)."""

    def build_extension(self, ext):
        one_by_one = self.compiler.compile

        def compile(sources, *args, **kwargs):
            workers = min(len(sources), len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1)
            if workers < 2:
                return one_by_one(sources, *args, **kwargs)
            with ThreadPoolExecutor(workers) as pool:
                parts = list(pool.map(lambda source: one_by_one([source], *args, **kwargs), sources))
            return [obj for part in parts for obj in part]

        self.compiler.compile = compile
        try:
            super().build_extension(ext)
        finally:
            del self.compiler.compile  # the instance attribute; the class's method again


setup(
    cmdclass={"build_ext": ParallelBuildExt},
    ext_modules=[NATIVE],
    packages=[
        *find_namespace_packages(include=["selfid_jax", "selfid_jax.*"], exclude=["*.__pycache__"]),
        "selfid_jax.experiments",
        *(f"selfid_jax.experiments.{name}" for name in find_packages("experiments")),
        "selfid_jax.configs",
        *(f"selfid_jax.configs.{name}" for name in find_namespace_packages("configs")),
    ]
)
