"""CPU XLA flags that selfid_jax sets when it is imported.

The XLA CPU backend that ships with current jaxlib compiles batched
``lax.scan``/``vmap`` programs through its fusion emitters and schedules them
with the concurrency-optimised scheduler. On small CPUs both are badly slow for
the programs this library runs (many small matrix ops inside long scans):
a 200-step rollout took 202 ms instead of 1.3 ms, and batched ``mjx.step``
stalled at batch >= ~350 on 2 cores. ``benchmarks/xla_flags.py`` measures the
effect on this machine.

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
}


def merged_xla_flags(existing: str | None, defaults: dict[str, str] = DEFAULT_XLA_FLAGS) -> str:
    """Return ``existing`` XLA flags with each default appended unless already set.

    A flag counts as set if ``existing`` names it in any form
    (``--flag=value`` or bare ``--flag``).
    """
    tokens = (existing or "").split()
    present = {tok.split("=", 1)[0] for tok in tokens}
    for flag, value in defaults.items():
        if flag not in present:
            tokens.append(f"{flag}={value}")
    return " ".join(tokens)


def apply_default_xla_flags() -> None:
    """Write the merged flags into ``os.environ['XLA_FLAGS']`` (opt out: ``SELFID_JAX_NO_XLA_FLAGS=1``)."""
    if os.environ.get("SELFID_JAX_NO_XLA_FLAGS", "") not in ("", "0"):
        return
    os.environ["XLA_FLAGS"] = merged_xla_flags(os.environ.get("XLA_FLAGS"))
