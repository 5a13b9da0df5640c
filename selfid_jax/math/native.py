"""Native CPU kernels for the estimator's per-sample step: the whole step, the update, Eq. 14's closed form, the record.

XLA's CPU backend compiles a vmapped estimator step into loops that update one
scalar per instruction (about 0.45 ns per value on the 2-core development
machine, whatever the layout; ``docs/benchmarks.md``). The C++ kernels in
``selfid_jax/math/_native/`` run the same operations, in the same order, on 8
float32 (4 float64) estimators per instruction, each as one XLA FFI custom
call over the whole batch. They are built for x86-64 CPUs with AVX2 and FMA
(any x86-64 server CPU since 2013-2015); on another CPU :func:`available` is
False, with the reason, and the pure-JAX functions run (an SSE2 build of the
same code ran slower than XLA's code on the development machine). The
kernels:

* ``"update"``: the sums of :func:`selfid_jax.identify.estimator.update`
  (the sample screen, the sums of Eq. 6-12 and 14, the counters; the ring
  buffer's write, if the state has one, stays XLA code);
* ``"closed_form"``: :func:`selfid_jax.identify.refine.statistics_closed_form`
  with no ridge (two unrolled ``L D L^T`` factorisations, a null-space
  projector and a solve per estimator);
* ``"record"``: :func:`selfid_jax.identify.estimator.record` where it
  computes ``||J_t - J_{t-1}||_F`` and ``||J_t||_F`` itself (the convergence
  test of Sec. IV-D);
* ``"step"``: the four of :func:`selfid_jax.identify.step.sample_step` with
  the closed form in one pass, the update, the initial guess (Eq. 13), Eq.
  14 and the record, each field of the state read once and written once
  (the ring buffer's write stays XLA code).

With AVX2, float32 fields of 8 or more values per estimator move between the
batch's rows and the lanes by 8x8 register transposes. A caller composing
the first three gets the initial guess (Eq. 13, elementwise) as XLA code
between them; ``"step"`` computes it in the update's pass.

They are built with the package (``pip install``, a C++17 compiler; the build
goes on without them if none is found) and used on the CPU backend only:
:func:`call` lowers the kernel for CPU and the pure-JAX function for every
other platform (``jax.lax.platform_dependent``), and its derivatives are the
pure-JAX function's (``jax.custom_jvp``), so a caller jits, vmaps and
differentiates as before. Values agree with the pure-JAX functions to float
round-off (the kernels contract a multiply and an add into one FMA where the
CPU has it); the counters are equal.

Each call splits its batch over XLA's intra-op thread pool in chunks of at
least 2,048 estimators (a smaller batch runs on the calling thread), on at
most as many threads as the CPUs the process may run on (Linux's affinity
mask); ``SELFID_JAX_NATIVE_THREADS=k`` in the environment before the first
call caps it at ``k`` threads instead.

:func:`available` says whether the kernels are loaded; :func:`enabled` is
False where they are not, or where ``SELFID_JAX_NATIVE=0`` was set before
import or :func:`set_enabled` turned them off (read when a function is
traced, so a ``jit`` compiled before keeps what it had).
"""

from __future__ import annotations

import ctypes
import functools
import importlib.machinery
import os
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp

__all__ = ["available", "call", "enabled", "load_error", "set_enabled", "status"]

_LIB_STEM = "_native_kernels"
_ABI = 3  # SelfidKernelsAbi() of the sources beside this module: a change to a handler's arguments bumps both
_TARGETS = {"closed_form": "SelfidClosedForm", "record": "SelfidRecord", "step": "SelfidStep",
            "update": "SelfidUpdate"}
# result k written over argument j's buffer ({j: k}): XLA then updates a loop's carried state in place instead of
# copying each new field into it
_ALIASES = {"closed_form": {2: 0}, "record": {1: 0, 2: 1, 3: 2, 4: 3, 6: 4, 7: 5, 8: 6},
            "step": {**{k: k for k in range(8)}, **{k: k - 2 for k in range(10, 17)}},
            "update": {k: k for k in range(8)}}
_state: dict[str, object] = {"enabled": os.environ.get("SELFID_JAX_NATIVE", "1") != "0"}


def _library_path() -> Path | None:
    here = Path(__file__).parent
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = here / f"{_LIB_STEM}{suffix}"
        if path.is_file():
            return path
    return None


@functools.cache
def _load() -> tuple[bool, str]:
    """Load the library and register its FFI targets once: ``(loaded, why not)``."""
    path = _library_path()
    if path is None:
        return False, f"no {_LIB_STEM} library next to {__file__} (built without a C++ compiler?)"
    try:
        lib = ctypes.cdll.LoadLibrary(str(path))
        abi = lib.SelfidKernelsAbi()
        if abi != _ABI:
            return False, f"{path} was built from other sources (ABI {abi}, expected {_ABI}): reinstall the package"
        if not lib.SelfidKernelsSupported():
            return False, "the kernels run on x86-64 CPUs with AVX2 and FMA only; this one runs the pure-JAX code"
        for target in _TARGETS.values():
            jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, target)), platform="cpu")
    except (OSError, AttributeError) as e:
        return False, f"{path}: {e}"
    return True, ""


def available() -> bool:
    """True iff the native kernels are built and registered with XLA's CPU backend."""
    return _load()[0]


def load_error() -> str:
    """Why the kernels are not available ("" when they are)."""
    return _load()[1]


def enabled() -> bool:
    """True iff :func:`call` uses the native kernels on CPU (available and not turned off)."""
    return bool(_state["enabled"]) and available()


def status() -> str:
    """One line for a report: ``"on"``, or ``"off (why)"``."""
    return "on" if enabled() else f"off ({load_error() or 'turned off'})"


def set_enabled(on: bool) -> bool:
    """Use the native kernels (``True``, if available) or the pure-JAX functions everywhere; returns the old
    setting. Read at trace time."""
    old = bool(_state["enabled"])
    _state["enabled"] = bool(on)
    return old


def call(kernel: str, reference: Callable, *args: jax.Array):
    """``reference(*args)``, computed on CPU by the native kernel ``kernel`` (see the module docstring).

    ``kernel``: ``"update"`` (``sign_net, mag_sum (n, m), mag_count (m,),
    S_vv (m, m), S_tv (n, m), s_tt (), count, rejected () int32, v_tol,
    forget (), dtheta (n,), V (m,)`` -> the first eight after the sample),
    ``"closed_form"`` (``S_vv (m, m), S_tv (n, m), J0 (n, m), rcond () ->
    J (n, m)``) or ``"record"`` (``J, estimate (n, m), last_deltas,
    last_norms (2,), last_fresh (2,) bool, count, recorded_count, iteration,
    converged_at () int32, eps, eps_rel (), min_count () int32`` -> the
    state's ``estimate (= J), last_deltas, last_norms, last_fresh,
    recorded_count, iteration, converged_at`` after it) or ``"step"``
    (update's first ten arguments, record's ``estimate, last_deltas,
    last_norms, last_fresh, recorded_count, iteration, converged_at``,
    ``dtheta, V``, ``rcond, eps, eps_rel``, ``min_count`` -> update's eight
    results, then record's seven); one float dtype (float32 or float64), ``1 <= m <= 6``,
    ``1 <= n <= 64``: other shapes and dtypes go to ``reference``. ``args``
    are one estimator's arrays (``vmap`` adds the kernel's batch); the result
    has ``reference``'s structure, shapes and dtypes. Falls back to
    ``reference`` where :func:`enabled` is False.
    """
    if kernel not in _TARGETS:
        raise ValueError(f"kernel: expected one of {sorted(_TARGETS)}, got {kernel!r}")
    args = tuple(jnp.asarray(a) for a in args)
    if not (enabled() and _supported(kernel, args)):
        return reference(*args)
    out_shape = jax.eval_shape(reference, *args)
    leaves, tree = jax.tree.flatten(out_shape)
    ffi = jax.ffi.ffi_call(_TARGETS[kernel], [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves],
                           vmap_method="broadcast_all", input_output_aliases=_ALIASES[kernel])

    def native(*xs):
        return jax.tree.unflatten(tree, ffi(*xs))

    @jax.custom_jvp
    def f(*xs):
        return jax.lax.platform_dependent(*xs, cpu=native, default=reference)

    @f.defjvp
    def f_jvp(primals, tangents):
        return f(*primals), jax.jvp(reference, primals, tangents)[1]

    return f(*args)


def _supported(kernel: str, args: tuple[jax.Array, ...]) -> bool:
    """The kernel's shapes (``1 <= m <= 6``, ``1 <= n <= 64``) and dtypes (float32 or float64; int32 counters)."""
    J = args[{"closed_form": 1, "update": 4, "record": 0, "step": 4}[kernel]]  # an (n, m) argument
    if J.ndim != 2 or not (1 <= J.shape[1] <= 6 and 1 <= J.shape[0] <= 64) or J.dtype not in (jnp.float32,
                                                                                             jnp.float64):
        return False
    n, m = J.shape
    f, i, b = J.dtype, jnp.dtype(jnp.int32), jnp.dtype(bool)
    update = (((n, m), f), ((n, m), f), ((m,), f), ((m, m), f), ((n, m), f), ((), f), ((), i), ((), i), ((), f),
              ((), f))
    record = (((n, m), f), ((2,), f), ((2,), f), ((2,), b))
    signature = {
        "closed_form": (((m, m), f), ((n, m), f), ((n, m), f), ((), f)),
        "update": (*update, ((n,), f), ((m,), f)),
        "record": (((n, m), f), *record, ((), i), ((), i), ((), i), ((), i), ((), f), ((), f), ((), i)),
        "step": (*update, *record, ((), i), ((), i), ((), i), ((n,), f), ((m,), f), ((), f), ((), f), ((), f),
                 ((), i)),
    }[kernel]
    return len(args) == len(signature) and all(a.shape == s and a.dtype == d
                                               for a, (s, d) in zip(args, signature, strict=True))
