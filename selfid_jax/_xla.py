"""CPU XLA flags that selfid_jax sets when it is imported.

The XLA CPU backend that ships with current jaxlib compiles batched
``lax.scan``/``vmap`` programs through its fusion emitters and schedules them
with the concurrency-optimised scheduler. On small CPUs both are badly slow for
the programs this library runs (many small matrix ops inside long scans):
a 200-step rollout took 202 ms instead of 1.3 ms, and batched ``mjx.step``
stalled at batch >= ~350 on 2 cores. From jaxlib 0.8.1 it also hands
reductions and elementwise chains to YNNPACK kernels, one call per fusion: for
a few entries per estimator or per joint that doubled the UR5e rollout
(0.125 against 0.062 ms at batch 10,000) and slowed the self-ID step 1.2x.
``benchmarks/xla_flags.py`` measures the effect on this machine. Each flag is
set only for the jaxlib releases that know it (:data:`MIN_JAXLIB`).

The flags are appended to ``XLA_FLAGS`` unless the user already set that flag
(either value wins over ours). They only take effect if the XLA backend has not
been initialised yet, i.e. import ``selfid_jax`` before running any JAX
computation.
"""

from __future__ import annotations

import os

DEFAULT_XLA_FLAGS: dict[str, str] = {
    "--xla_cpu_use_fusion_emitters": "false",
    "--xla_cpu_enable_concurrency_optimized_scheduler": "false",
    "--xla_cpu_experimental_ynn_fusion_type": "",
}

# The oldest jaxlib whose XLA knows each flag (checked in the released wheels:
# an unknown flag in XLA_FLAGS aborts the process when the backend starts).
MIN_JAXLIB: dict[str, tuple[int, ...]] = {
    "--xla_cpu_use_fusion_emitters": (0, 6, 0),
    "--xla_cpu_experimental_ynn_fusion_type": (0, 8, 1),
    "--xla_cpu_parallel_codegen_split_count": (0, 4, 32),
}


def jaxlib_version() -> tuple[int, ...] | None:
    """The installed jaxlib's release as an int tuple (:func:`release_tuple`), None if unknown; jaxlib is not
    imported."""
    from importlib import metadata

    try:
        return release_tuple(metadata.version("jaxlib"))
    except metadata.PackageNotFoundError:
        return None


def release_tuple(text: str) -> tuple[int, ...] | None:
    """Release numbers of a version string: ``"0.9.0.1"`` -> ``(0, 9, 0, 1)``, ``"0.7.0rc1"`` -> ``(0, 7, 0)``.

    None when it does not start with a number.
    """
    parts = []
    for token in text.split("+")[0].split("."):
        digits = ""
        for c in token:
            if not c.isdigit():
                break
            digits += c
        if not digits:
            break
        parts.append(int(digits))
        if digits != token:  # "0rc1", "2dev3": the release number ends here
            break
    return tuple(parts) or None


def defaults_for(version: tuple[int, ...] | None, flags: dict[str, str] | None = None) -> dict[str, str]:
    """The flags of ``flags`` (default :data:`DEFAULT_XLA_FLAGS`) that this jaxlib release knows: those whose
    minimum (:data:`MIN_JAXLIB`) it meets.

    ``version`` None (unknown) keeps only the flags without a minimum.
    """
    return {flag: value for flag, value in (DEFAULT_XLA_FLAGS if flags is None else flags).items()
            if flag not in MIN_JAXLIB or (version is not None and version >= MIN_JAXLIB[flag])}


def merged_xla_flags(existing: str | None, defaults: dict[str, str] | None = None) -> str:
    """Return ``existing`` XLA flags with each default appended unless already set.

    A flag counts as set if ``existing`` names it in any form
    (``--flag=value`` or bare ``--flag``). ``defaults``: the flags to add
    (default: :func:`defaults_for` the installed jaxlib).
    """
    defaults = defaults_for(jaxlib_version()) if defaults is None else defaults
    tokens = (existing or "").split()
    present = {tok.split("=", 1)[0] for tok in tokens}
    for flag, value in defaults.items():
        if flag not in present:
            tokens.append(f"{flag}={value}")
    return " ".join(tokens)


def apply_default_xla_flags(defaults: dict[str, str] | None = None) -> None:
    """Write the merged flags into ``os.environ['XLA_FLAGS']`` (opt out: ``SELFID_JAX_NO_XLA_FLAGS=1``).

    ``defaults``: as :func:`merged_xla_flags` (default: the installed jaxlib's).
    """
    if os.environ.get("SELFID_JAX_NO_XLA_FLAGS", "") not in ("", "0"):
        return
    os.environ["XLA_FLAGS"] = merged_xla_flags(os.environ.get("XLA_FLAGS"), defaults)


QUICK_COMPILE_FLAGS: dict[str, str] = {"--xla_backend_optimization_level": "0",
                                       "--xla_cpu_parallel_codegen_split_count": "1"}
"""Quick compiles for a process whose programs each run once on small data. LLVM's optimisation level 0 for XLA's
CPU code: XLA's graph passes (fusion, simplification) are unchanged, only the machine code is less optimised. XLA
compiles the hands' pose programs in about half the time; the code runs slower (up to 4.4x for the hands' pose
solve), and the results differ from level 3's by round-off. And each program's LLVM module compiled whole instead of
split into parts for a thread pool (from jaxlib 0.4.32), which a compile does not win back on 2 cores (XLA's compile
seconds over four test files 33.0 -> 30.6 s; ``selfid-jax demo`` 14.0-14.6 against 15.0-15.3 s wall). The split
changes the code by round-off too: the demo's UR5e rows are bit-identical, its Model O estimates move by up to 8e-13
(relative errors by 2e-13), and what it prints is the same."""


def quick_compile_flags() -> dict[str, str]:
    """:data:`QUICK_COMPILE_FLAGS` that the installed jaxlib knows (:func:`defaults_for`)."""
    return defaults_for(jaxlib_version(), QUICK_COMPILE_FLAGS)


def request_quick_compile() -> None:
    """Merge :func:`quick_compile_flags` into ``os.environ['XLA_FLAGS']`` (a flag the user set there wins).

    For a process whose programs each run once on small data, where compile time is most of the wall time
    (``selfid-jax demo``: 20.3-20.6 against 25.8-26.1 s wall, CPU 24 against 38 s, two interleaved pairs on 2
    cores, for level 0). Takes effect only before JAX's first computation, as the default flags; the same opt-out.
    """
    apply_default_xla_flags(quick_compile_flags())
