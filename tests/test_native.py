"""The native CPU kernels (selfid_jax.math.native) against the pure-JAX functions they replace.

Eq. 14's closed form must give :func:`selfid_jax.identify.refine._minimum_norm_correction`'s values to float
round-off for every shape it takes (``1 <= m <= 6``, ``1 <= n <= 64``, any batch, a batch below one block of 8 or 4
estimators and a remainder past the last block), every rank of ``S_vv`` (its null-space branch), broadcast and
nested ``vmap`` inputs, and the pure-JAX derivatives; a float64 numpy pseudo-inverse is the independent reference.
The update must give :func:`selfid_jax.identify.estimator.update`'s pure-JAX sums to round-off and its counters
exactly, for accepted samples and for every kind it rejects (non-finite, all-zero, overflowing), with forgetting
and a magnitude threshold; a numpy loop over Eq. 6-12 and 14 is the independent reference. The record must give
the pure-JAX record's norms to round-off and its counters and convergence iteration exactly, which
:func:`selfid_jax.identify.estimator.convergence_iteration` (a vectorised form of the test over the whole
sequence) checks independently.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from selfid_jax.identify import estimator as E
from selfid_jax.identify import refine as RF
from selfid_jax.identify import step as ST
from selfid_jax.math import native


@pytest.fixture(autouse=True)
def _native_on():
    old = native.set_enabled(True)
    yield
    native.set_enabled(old)


def both(f, *args):
    """``(native, reference)`` values of ``jit(f)(*args)``, each traced afresh."""
    native.set_enabled(True)
    a = jax.jit(f)(*args)
    native.set_enabled(False)
    b = jax.jit(f)(*args)
    native.set_enabled(True)
    return np.asarray(a), np.asarray(b)


def statistics(batch: int, n: int, m: int, rank: int, dtype, seed: int = 0, K: int = 12):
    """``S_vv (batch, m, m)`` of rank ``rank`` (``V`` in a ``rank``-dimensional subspace), ``S_tv``, ``J0``."""
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(batch, m, rank))
    V = np.einsum("bmr,bkr->bkm", basis, rng.normal(size=(batch, K, rank)))
    theta = rng.normal(size=(batch, K, n))
    S_vv = np.einsum("bki,bkj->bij", V, V)
    S_tv = np.einsum("bki,bkj->bij", theta, V)
    J0 = rng.normal(size=(batch, n, m))
    return tuple(jnp.asarray(x, dtype) for x in (S_vv, S_tv, J0))


def test_the_kernel_is_built_and_registered():
    assert native.available(), native.load_error()
    assert native.enabled()


def test_the_library_runs_where_the_cpu_has_avx2_and_fma():
    """``SelfidKernelsSupported`` against the CPU's flags (``/proc/cpuinfo``): the kernels are built for AVX2 and FMA
    only, and another CPU gets the pure-JAX functions with the reason."""
    import ctypes
    import pathlib

    info = pathlib.Path("/proc/cpuinfo")
    if not info.is_file():
        pytest.skip("no /proc/cpuinfo on this system")
    flags = next(line for line in info.read_text().splitlines() if line.startswith("flags")).split()
    lib = ctypes.cdll.LoadLibrary(str(native._library_path()))
    assert bool(lib.SelfidKernelsSupported()) == ("avx2" in flags and "fma" in flags)


def test_the_cpu_program_calls_the_kernel_and_the_cuda_program_does_not():
    S_vv, S_tv, J0 = statistics(5, 6, 3, 3, jnp.float32)
    f = jax.jit(jax.vmap(RF.statistics_closed_form))
    assert "SelfidClosedForm" in f.lower(S_vv, S_tv, J0).as_text()
    cuda = f.trace(S_vv, S_tv, J0).lower(lowering_platforms=("cuda",)).as_text()
    assert "SelfidClosedForm" not in cuda and "custom_call" not in cuda


@pytest.mark.parametrize("dtype, tol", [(jnp.float32, 2e-5), (jnp.float64, 1e-12)])
@pytest.mark.parametrize("n, m, batch", [(6, 3, 21), (1, 1, 3), (4, 2, 9), (2, 6, 5), (16, 3, 8)])
def test_full_rank_equals_the_reference_and_numpy_float64(n, m, batch, dtype, tol):
    S_vv, S_tv, J0 = statistics(batch, n, m, m, dtype, seed=n * 10 + m)
    got, ref = both(jax.vmap(RF.statistics_closed_form), S_vv, S_tv, J0)
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol * scale)
    S64, St64 = np.asarray(S_vv, np.float64), np.asarray(S_tv, np.float64)
    exact = np.einsum("bnm,bmk->bnk", St64, np.linalg.inv(S64))  # S_tv S_vv^-1 whatever J0 at full rank
    cond = max(np.linalg.cond(S64[b]) for b in range(batch))
    np.testing.assert_allclose(got, exact, rtol=0, atol=50 * cond * float(jnp.finfo(dtype).eps) * scale)


@pytest.mark.parametrize("dtype, tol", [(jnp.float32, 2e-5), (jnp.float64, 1e-12)])
@pytest.mark.parametrize("m, rank", [(3, 0), (3, 1), (3, 2), (6, 4), (2, 1)])
def test_rank_deficient_statistics_take_the_null_space_branch_like_the_reference(m, rank, dtype, tol):
    """S_tv P + J0 N: the kernel keeps J0 on S_vv's null space, as the reference does (and numpy's pinv)."""
    n, batch = 5, 11
    S_vv, S_tv, J0 = statistics(batch, n, m, rank, dtype, seed=rank + 7)
    if rank == 0:
        S_vv, S_tv = jnp.zeros_like(S_vv), jnp.zeros_like(S_tv)
    got, ref = both(jax.vmap(RF.statistics_closed_form), S_vv, S_tv, J0)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol * max(1.0, np.max(np.abs(ref))))
    if dtype == jnp.float32:  # the float32 null space is round-off's (both paths alike); numpy checks float64
        return
    S64 = np.asarray(S_vv, np.float64)
    P = np.linalg.pinv(S64, rcond=1e-9, hermitian=True)
    N = np.eye(m) - np.einsum("bij,bjk->bik", S64, P)
    exact = np.einsum("bnm,bmk->bnk", np.asarray(S_tv, np.float64), P) + np.einsum(
        "bnm,bmk->bnk", np.asarray(J0, np.float64), N)
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-8 * max(1.0, np.max(np.abs(exact))))


def test_one_estimator_without_vmap_and_a_traced_rcond():
    S_vv, S_tv, J0 = (x[0] for x in statistics(1, 6, 3, 2, jnp.float32, seed=3))
    got, ref = both(lambda a, b, c, r: RF.statistics_closed_form(a, b, c, rcond=r), S_vv, S_tv, J0,
                    jnp.float32(1e-4))
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-5 * np.max(np.abs(ref)))


def test_broadcast_and_nested_vmap():
    S_vv, S_tv, J0 = statistics(12, 6, 3, 3, jnp.float32, seed=4)
    shared = jax.vmap(RF.statistics_closed_form, in_axes=(0, 0, None))  # one J0 for every estimator
    got, ref = both(shared, S_vv, S_tv, J0[0])
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-5 * np.max(np.abs(ref)))
    nested = jax.vmap(jax.vmap(RF.statistics_closed_form))
    r = lambda x: x.reshape(3, 4, *x.shape[1:])
    got, ref = both(nested, r(S_vv), r(S_tv), r(J0))
    assert got.shape == (3, 4, 6, 3)
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-5 * np.max(np.abs(ref)))


def test_unsupported_shapes_and_mixed_dtypes_go_to_the_reference():
    """m > 6 and mixed dtypes: no custom call in the program, the reference's values."""
    S_vv, S_tv, J0 = statistics(3, 4, 7, 7, jnp.float32, seed=5)
    f = jax.jit(jax.vmap(RF.statistics_closed_form))
    assert "SelfidClosedForm" not in f.lower(S_vv, S_tv, J0).as_text()
    S_vv, S_tv, J0 = statistics(3, 4, 3, 3, jnp.float32, seed=6)
    mixed = jax.jit(jax.vmap(RF.statistics_closed_form))
    assert "SelfidClosedForm" not in mixed.lower(S_vv, S_tv, J0.astype(jnp.float64)).as_text()


def test_gradients_are_the_reference_functions():
    S_vv, S_tv, J0 = (x[0] for x in statistics(1, 6, 3, 3, jnp.float64, seed=8))

    def loss(S_vv, S_tv, J0):
        return jnp.sum(jnp.sin(RF.statistics_closed_form(S_vv, S_tv, J0)))

    native.set_enabled(True)
    g = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(S_vv, S_tv, J0)
    native.set_enabled(False)
    h = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(S_vv, S_tv, J0)
    for a, b in zip(g, h, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    # and a finite difference of the native values
    d = np.random.default_rng(9).normal(size=(6, 3))
    e = 1e-6
    fd = (loss(S_vv, S_tv + e * d, J0) - loss(S_vv, S_tv - e * d, J0)) / (2 * e)
    native.set_enabled(True)
    np.testing.assert_allclose(float(jnp.sum(g[1] * d)), float(fd), rtol=1e-6)


def test_turned_off_the_program_is_the_reference_bit_for_bit():
    S_vv, S_tv, J0 = statistics(9, 6, 3, 2, jnp.float32, seed=10)
    native.set_enabled(False)
    a = np.asarray(jax.jit(jax.vmap(RF.statistics_closed_form))(S_vv, S_tv, J0))
    b = np.asarray(jax.jit(jax.vmap(RF._minimum_norm_correction))(
        S_vv, S_tv, J0, jnp.full((9,), RF.default_rcond(3, jnp.float32), jnp.float32)))
    np.testing.assert_array_equal(a, b)


class NativeJitVmapTest(chex.TestCase):
    @chex.variants(with_jit=True, without_jit=True)
    def test_jit_and_vmap(self):
        S_vv, S_tv, J0 = statistics(10, 6, 3, 3, jnp.float32, seed=11)
        got = self.variant(jax.vmap(RF.statistics_closed_form))(S_vv, S_tv, J0)
        native.set_enabled(False)
        ref = jax.jit(jax.vmap(RF.statistics_closed_form))(S_vv, S_tv, J0)
        native.set_enabled(True)
        chex.assert_trees_all_close(got, ref, atol=2e-5 * float(jnp.max(jnp.abs(ref))), rtol=0)


def sample_stream(T: int, batch: int, n: int, m: int, seed: int = 0):
    """``(dtheta (T, batch, n), V (T, batch, m))`` float64 with every kind of sample the screen rejects mixed in,
    and small ``V`` entries below a ``v_tol`` of 0.05."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(T, batch, n)) * rng.uniform(0.01, 2.0, (T, batch, 1))
    V = rng.normal(size=(T, batch, m))
    V[rng.random((T, batch, m)) < 0.2] *= 1e-3  # below v_tol: no magnitude ratio
    kind = rng.integers(0, 12, (T, batch))
    d[kind == 0, 0] = np.nan
    V[kind == 1, -1] = np.inf
    d[kind == 2] = 0.0
    V[kind == 3] = 0.0
    d[kind == 4, 0] = 1e30  # finite in float64 and float32's inf: rejected in float32 (not bounded), overflow f64?
    return d, V


def numpy_update(d, V, forget: float, v_tol: float, dtype):
    """Eq. 6-12 and 14's sums and the counters by a plain loop, in float64 with the screen of ``update``."""
    T, batch, n = d.shape
    m = V.shape[-1]
    big, tiny = np.sqrt(float(np.finfo(dtype).max)), float(np.finfo(dtype).tiny)
    out = {k: np.zeros((batch,) + s) for k, s in [("sign_net", (n, m)), ("mag_sum", (n, m)), ("mag_count", (m,)),
                                                      ("S_vv", (m, m)), ("S_tv", (n, m)), ("s_tt", ())]}
    count, rejected = np.zeros(batch, int), np.zeros(batch, int)
    for t in range(T):
        for b in range(batch):
            x, v = d[t, b].astype(dtype).astype(np.float64), V[t, b].astype(dtype).astype(np.float64)
            with np.errstate(all="ignore"):
                ok = (np.all(np.abs(x) <= big) and np.all(np.abs(v) <= big) and np.any(np.abs(x) >= tiny)
                      and np.any(np.abs(v) >= tiny))
                total = forget * (out["s_tt"][b] + np.trace(out["S_vv"][b])) + x @ x + v @ v
                ok = ok and np.isfinite(total.astype(dtype))
            if not ok:
                rejected[b] += 1
                continue
            count[b] += 1
            for k in out:
                out[k][b] *= forget
            out["sign_net"][b] += np.outer(x / np.sum(np.abs(x)), v / np.sum(np.abs(v)))
            large = np.abs(v) > v_tol
            out["mag_sum"][b] += np.outer(np.abs(x), np.where(large, 1.0 / np.where(large, np.abs(v), 1.0), 0.0))
            out["mag_count"][b] += large
            out["S_vv"][b] += np.outer(v, v)
            out["S_tv"][b] += np.outer(x, v)
            out["s_tt"][b] += x @ x
    return out, count, rejected


def run_updates(d, V, dtype, forget, v_tol, on: bool):
    """The state after folding the stream in (one scan over ``vmap(update)``), the native kernel on or off."""
    T, batch, n = d.shape
    m = V.shape[-1]

    def go(d, V):
        s0 = jax.vmap(lambda _: E.init(n, m, capacity=0, v_tol=v_tol, forget=forget, dtype=dtype))(jnp.arange(batch))
        return jax.lax.scan(lambda s, x: (jax.vmap(E.update)(s, *x), None), s0, (d, V))[0]

    native.set_enabled(on)
    try:
        out = jax.jit(go)(jnp.asarray(d, dtype), jnp.asarray(V, dtype))
        text = jax.jit(go).lower(jnp.asarray(d, dtype), jnp.asarray(V, dtype)).as_text()
    finally:
        native.set_enabled(True)
    assert ("SelfidUpdate" in text) == on
    return out


@pytest.mark.parametrize("dtype, rtol", [(jnp.float32, 2e-5), (jnp.float64, 1e-12)])
@pytest.mark.parametrize("n, m, batch, forget", [(6, 3, 21, 1.0), (6, 3, 5, 0.9), (1, 1, 9, 0.95), (16, 6, 8, 1.0),
                                                 (3, 2, 1, 0.8)])
def test_update_equals_the_reference_and_a_numpy_loop(n, m, batch, forget, dtype, rtol):
    d, V = sample_stream(12, batch, n, m, seed=n + m + batch)
    got = run_updates(d, V, dtype, forget, 0.05, True)
    ref = run_updates(d, V, dtype, forget, 0.05, False)
    want, count, rejected = numpy_update(d, V, forget, 0.05, dtype)
    np.testing.assert_array_equal(got.count, ref.count)
    np.testing.assert_array_equal(got.rejected, ref.rejected)
    np.testing.assert_array_equal(got.count, count)
    np.testing.assert_array_equal(got.rejected, rejected)
    assert int(np.sum(rejected)) > 0 and int(np.sum(count)) > 0
    for name, value in want.items():
        a, b = np.asarray(getattr(got, name), np.float64), np.asarray(getattr(ref, name), np.float64)
        scale = max(1.0, float(np.max(np.abs(b))))
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale, err_msg=name)
        np.testing.assert_allclose(a, value, rtol=50 * rtol, atol=50 * rtol * max(1.0, np.max(np.abs(value))),
                                   err_msg=name)


def test_update_with_one_sample_for_every_estimator_and_its_gradient():
    """A sample shared by the batch (``in_axes=None``: the kernel reads it once) and derivatives through the kernel's
    pure-JAX form."""
    n, m, batch = 6, 3, 10
    d, V = sample_stream(3, batch, n, m, seed=3)
    states = run_updates(d, V, jnp.float64, 1.0, 0.05, True)
    x, v = jnp.asarray(np.abs(d[0, 0]) + 0.1), jnp.asarray(V[1, 1])
    f = jax.jit(jax.vmap(E.update, in_axes=(0, None, None)))
    got = f(states, x, v)
    native.set_enabled(False)
    ref = jax.jit(jax.vmap(E.update, in_axes=(0, None, None)))(states, x, v)

    def loss(x, v):
        s = E.update(jax.tree.map(lambda a: a[0], states), x, v)
        return jnp.sum(s.S_tv**2) + jnp.sum(jnp.sin(s.sign_net)) + jnp.sum(s.mag_sum)

    g_ref = jax.grad(loss, argnums=(0, 1))(x, v)
    native.set_enabled(True)
    g = jax.grad(loss, argnums=(0, 1))(x, v)
    chex.assert_trees_all_close(got, ref, rtol=1e-12, atol=1e-12)
    chex.assert_trees_all_close(g, g_ref, rtol=1e-12, atol=1e-12)


def test_update_checks_shapes_before_the_kernel():
    s = E.init(6, 3, capacity=0)
    with pytest.raises(ValueError, match="dtheta"):
        E.update(s, jnp.ones(5), jnp.ones(3))
    with pytest.raises(ValueError, match="V"):
        E.update(s, jnp.ones(6), jnp.ones(4))


def record_sequence(T: int, batch: int, n: int, m: int, dtype, seed: int):
    """Estimates ``(T, batch, n, m)`` that settle at a different step per estimator, and acceptance flags."""
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(batch, n, m))
    rate = rng.uniform(0.2, 0.9, (batch, 1, 1))
    t = np.arange(1, T + 1)[:, None, None, None]
    J = target * (1.0 - rate**t) + 1e-7 * rng.normal(size=(T, batch, n, m))
    accepted = rng.random((T, batch)) > 0.15
    return jnp.asarray(J, dtype), jnp.asarray(accepted)


def run_records(J, accepted, eps, eps_rel, min_count, on: bool):
    """The state after recording each estimate, the count advanced where the sample was accepted."""
    T, batch, n, m = J.shape

    def go(J, accepted):
        s0 = jax.vmap(lambda _: E.init(n, m, capacity=0, dtype=J.dtype))(jnp.arange(batch))

        def body(s, x):
            Jt, ok = x
            s = s._replace(count=s.count + ok.astype(jnp.int32))
            s = jax.vmap(lambda s, J: E.record(s, J, eps, eps_rel, min_count=min_count))(s, Jt)
            return s, None

        return jax.lax.scan(body, s0, (J, accepted))[0]

    native.set_enabled(on)
    try:
        out = jax.jit(go)(J, accepted)
        assert ("SelfidRecord" in jax.jit(go).lower(J, accepted).as_text()) == on
    finally:
        native.set_enabled(True)
    return out


@pytest.mark.parametrize("dtype, rtol", [(jnp.float32, 1e-6), (jnp.float64, 1e-14)])
@pytest.mark.parametrize("n, m, batch, eps, eps_rel, min_count", [(6, 3, 13, 1e-3, 0.0, 0), (6, 3, 3, 1e-4, 1e-3, 5),
                                                                 (2, 6, 9, 0.0, 1e-2, 0), (16, 3, 8, 1e-3, 0.0, 3)])
def test_record_equals_the_reference_and_convergence_iteration(n, m, batch, eps, eps_rel, min_count, dtype, rtol):
    J, accepted = record_sequence(40, batch, n, m, dtype, seed=n + batch)
    got = run_records(J, accepted, eps, eps_rel, min_count, True)
    ref = run_records(J, accepted, eps, eps_rel, min_count, False)
    for name in ("last_fresh", "recorded_count", "iteration", "converged_at", "estimate"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    for name in ("last_deltas", "last_norms"):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name), rtol=rtol, err_msg=name)
    converged = np.asarray(got.converged_at)
    assert np.any(converged > 0), "the sequences should converge"
    if min_count == 0:
        want = [int(E.convergence_iteration(J[:, b], eps, eps_rel, accepted=accepted[:, b])) for b in range(batch)]
        np.testing.assert_array_equal(converged, want)


def test_record_with_a_given_delta_or_other_dtypes_takes_the_pure_jax_path():
    s = E.init(6, 3, capacity=0, dtype=jnp.float32)
    J = jnp.ones((6, 3), jnp.float32)
    f = jax.jit(lambda s, J: E.record(s, J, 1e-3, delta=jnp.float32(0.5)))
    assert "SelfidRecord" not in f.lower(s, J).as_text()
    assert float(f(s, J).last_deltas[1]) == 0.5
    g = jax.jit(lambda s, J: E.record(s, J, jnp.float64(1e-3)))  # a float64 threshold: compared in float64
    assert "SelfidRecord" not in g.lower(s, J).as_text()
    h = jax.jit(lambda s, J: E.record(s, J, 1e-3))
    assert "SelfidRecord" in h.lower(s, J).as_text()


def test_a_kernel_called_with_shapes_it_does_not_take_raises_and_names_them():
    """The handlers check every argument before any compute (what :func:`native.call` never passes them)."""
    assert native.available(), native.load_error()
    f32 = jnp.float32
    call = jax.ffi.ffi_call("SelfidClosedForm", jax.ShapeDtypeStruct((4, 6, 3), f32), vmap_method="broadcast_all")
    with pytest.raises(Exception, match="closed form: an argument's size does not match the batch"):
        jax.block_until_ready(call(jnp.ones((4, 3, 3), f32), jnp.ones((4, 6, 3), f32), jnp.ones((3, 6, 3), f32),
                                   jnp.ones((4,), f32)))
    wide = jax.ffi.ffi_call("SelfidClosedForm", jax.ShapeDtypeStruct((2, 7), f32), vmap_method="broadcast_all")
    with pytest.raises(Exception, match="closed form: expected 1 <= m <= 6"):
        jax.block_until_ready(wide(jnp.ones((7, 7), f32), jnp.ones((2, 7), f32), jnp.ones((2, 7), f32),
                                   jnp.ones((), f32)))
    with pytest.raises(ValueError, match="kernel: expected one of"):
        native.call("solve", lambda x: x, jnp.ones(3))


def test_a_batch_split_over_the_thread_pool_equals_the_reference():
    """4,099 estimators: above the kernels' smallest chunk per thread (2,048), with a remainder past the last
    block; the same values as the pure-JAX step."""
    n, m, batch = 6, 3, 4099
    d, V = sample_stream(3, batch, n, m, seed=12)
    got = run_updates(d, V, jnp.float32, 0.97, 0.05, True)
    ref = run_updates(d, V, jnp.float32, 0.97, 0.05, False)
    np.testing.assert_array_equal(got.count, ref.count)
    np.testing.assert_array_equal(got.rejected, ref.rejected)
    np.testing.assert_allclose(got.S_tv, ref.S_tv, rtol=2e-5, atol=2e-5 * float(jnp.max(jnp.abs(ref.S_tv))))
    J0 = jax.vmap(E.initial_guess)(got)
    a, b = both(jax.vmap(RF.statistics_closed_form), got.S_vv, got.S_tv, J0)
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-5 * np.max(np.abs(b)))
    rec = jax.jit(jax.vmap(lambda s, J: E.record(s, J, 1e-3)))
    native.set_enabled(True)
    x = rec(got, jnp.asarray(a))
    native.set_enabled(False)
    y = jax.jit(jax.vmap(lambda s, J: E.record(s, J, 1e-3)))(got, jnp.asarray(a))
    native.set_enabled(True)
    np.testing.assert_array_equal(x.estimate, y.estimate)
    np.testing.assert_allclose(x.last_deltas, y.last_deltas, rtol=1e-6)


def test_update_with_a_ring_buffer_keeps_the_accepted_samples_like_the_reference():
    """A state with ``capacity=4``: the kernel's sums, the buffer written by XLA, bit-identical buffers."""
    n, m, batch = 6, 3, 11
    d, V = sample_stream(9, batch, n, m, seed=13)

    def go(d, V):
        s0 = jax.vmap(lambda _: E.init(n, m, capacity=4, v_tol=0.05, dtype=jnp.float32))(jnp.arange(batch))
        return jax.lax.scan(lambda s, x: (jax.vmap(E.update)(s, *x), None), s0, (d, V))[0]

    args = jnp.asarray(d, jnp.float32), jnp.asarray(V, jnp.float32)
    assert "SelfidUpdate" in jax.jit(go).lower(*args).as_text()
    got = jax.jit(go)(*args)
    native.set_enabled(False)
    ref = jax.jit(go)(*args)
    native.set_enabled(True)
    np.testing.assert_array_equal(got.dtheta_buf, ref.dtheta_buf)
    np.testing.assert_array_equal(got.v_buf, ref.v_buf)
    np.testing.assert_array_equal(got.count, ref.count)
    assert np.all(np.isfinite(np.asarray(got.dtheta_buf)))
    np.testing.assert_allclose(got.S_tv, ref.S_tv, rtol=2e-5, atol=2e-5 * float(jnp.max(jnp.abs(ref.S_tv))))


def run_steps(d, V, dtype, *, forget=0.97, v_tol=0.05, capacity=0, eps=1e-2, eps_rel=1e-3, min_count=2,
              options=(), on: bool = True, compose: bool = False):
    """``(final state, StepInfo (T, batch))`` of a scan over ``vmap(sample_step)`` (closed form); ``compose``: the
    step written from the public functions instead (update, initial_guess, statistics_closed_form, record)."""
    T, batch, n = d.shape
    m = V.shape[-1]

    def one(s, x, v):
        if not compose:
            return ST.sample_step(s, x, v, eps, eps_rel, method="closed_form", options=options, min_count=min_count)
        new = E.update(s, x, v)
        J = RF.statistics_closed_form(new.S_vv, new.S_tv, E.initial_guess(new), rcond=dict(options).get("rcond"))
        new = E.record(new, J, eps, eps_rel, min_count=min_count)
        return new, new.last_deltas[1]

    def go(d, V):
        s0 = jax.vmap(lambda _: E.init(n, m, capacity=capacity, v_tol=v_tol, forget=forget, dtype=dtype))(
            jnp.arange(batch))
        return jax.lax.scan(lambda s, x: jax.vmap(one)(s, *x), s0, (d, V))

    args = jnp.asarray(d, dtype), jnp.asarray(V, dtype)
    native.set_enabled(on)
    try:
        text = jax.jit(go).lower(*args).as_text()
        out = jax.jit(go)(*args)
    finally:
        native.set_enabled(True)
    assert ("SelfidStep" in text) == (on and not compose)
    return out


def assert_states_close(got, ref, rtol):
    """Counters, flags and iterations equal; float fields within ``rtol`` of the field's largest entry (the
    deltas, differences of estimates that were larger before, within ``10 rtol``)."""
    for name, a, b in zip(got._fields, got, ref, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype.kind in "biu":
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            finite = np.isfinite(b)
            np.testing.assert_array_equal(np.isfinite(a), finite, err_msg=name)
            scale = max(1.0, float(np.max(np.abs(b[finite]), initial=0.0))) * (10 if name == "last_deltas" else 1)
            np.testing.assert_allclose(a[finite], b[finite], rtol=0, atol=rtol * scale, err_msg=name)


@pytest.mark.parametrize("dtype, rtol", [(jnp.float32, 2e-5), (jnp.float64, 1e-12)])
@pytest.mark.parametrize("n, m, batch", [(6, 3, 21), (1, 1, 3), (16, 6, 9), (3, 2, 1)])
def test_the_step_is_one_kernel_equal_to_the_pure_jax_step_and_to_least_squares(n, m, batch, dtype, rtol):
    """``sample_step`` with the closed form: one ``SelfidStep`` call per sample (no other kernel, no XLA guess), the
    pure-JAX step's state and diagnostics to round-off (counters and convergence iterations equal), the three-kernel
    composition's, and the float64 least-squares solution of the accepted samples (numpy)."""
    d, V = sample_stream(14, batch, n, m, seed=3 * n + m + batch)
    (got, info), (ref, ref_info) = run_steps(d, V, dtype), run_steps(d, V, dtype, on=False)
    assert_states_close(got, ref, rtol)
    np.testing.assert_array_equal(info.accepted, ref_info.accepted)
    composed, composed_delta = run_steps(d, V, dtype, compose=True)
    assert_states_close(got, composed, rtol)
    # the per-sample deltas: the three kernels' to round-off; the pure-JAX step's in float64 (in float32 the
    # estimates of the first, rank-deficient samples are ill-conditioned: 0.4 % apart where they jump by 1e3)
    np.testing.assert_allclose(info.delta, composed_delta, rtol=rtol, atol=rtol)
    if dtype == jnp.float64:
        np.testing.assert_allclose(info.delta, ref_info.delta, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(info.threshold, ref_info.threshold, rtol=1e-9)
    want, count, rejected = numpy_update(d, V, 0.97, 0.05, dtype)
    np.testing.assert_array_equal(got.count, count)
    np.testing.assert_array_equal(got.rejected, rejected)
    for b in range(batch):
        if np.linalg.matrix_rank(want["S_vv"][b]) == m:
            J = np.linalg.solve(want["S_vv"][b], want["S_tv"][b].T).T
            np.testing.assert_allclose(got.estimate[b], J, rtol=0, atol=200 * rtol * max(1.0, np.max(np.abs(J))))


def test_the_step_with_a_ring_buffer_a_thread_split_and_a_given_rcond_equals_the_pure_jax_step():
    """4,099 estimators (split over the pool, a remainder past the last block), ``capacity=4`` (the buffer written by
    XLA after the kernel: bit-identical) and ``options=(("rcond", 1e-3),)``."""
    d, V = sample_stream(4, 4099, 6, 3, seed=21)
    opts = (("rcond", 1e-3),)
    (got, _), (ref, _) = (run_steps(d, V, jnp.float32, capacity=4, options=opts, on=on) for on in (True, False))
    assert_states_close(got, ref, 2e-5)
    np.testing.assert_array_equal(got.dtheta_buf, ref.dtheta_buf)
    np.testing.assert_array_equal(got.v_buf, ref.v_buf)


def test_the_step_takes_the_composed_path_where_the_kernel_does_not_apply():
    """A ridge, the optax method, thresholds of another dtype or a float ``min_count``: no ``SelfidStep``."""
    s = E.init(6, 3, capacity=0, dtype=jnp.float32)
    x, v = jnp.ones(6, jnp.float32), jnp.ones(3, jnp.float32)

    def text(**kw):
        kw = {"method": "closed_form", **kw}
        eps = kw.pop("eps", 1e-3)
        return jax.jit(lambda s: ST.sample_step(s, x, v, eps, 0.0, **kw)).lower(s).as_text()

    assert "SelfidStep" in text()
    assert "SelfidStep" in text(options=(("ridge", 0.0),))
    assert "SelfidStep" not in text(options=(("ridge", 1e-3),))
    assert "SelfidStep" not in text(method="optax", options=(("steps", 2),))
    assert "SelfidStep" not in text(eps=np.float64(1e-3))
    assert "SelfidStep" not in text(min_count=1.0)
    native.set_enabled(False)
    assert "Selfid" not in text()


def test_the_step_checks_its_arguments_first_and_differentiates_as_the_pure_jax_step():
    s = E.init(4, 2, capacity=0, dtype=jnp.float64)
    with pytest.raises(ValueError, match="dtheta"):
        ST.sample_step(s, jnp.ones(5), jnp.ones(2), 1e-3, 0.0, method="closed_form")
    with pytest.raises(ValueError, match="eps"):
        ST.sample_step(s, jnp.ones(4), jnp.ones(2), 0.0, 0.0, method="closed_form")
    with pytest.raises(ValueError, match="rcond"):
        ST.sample_step(s, jnp.ones(4), jnp.ones(2), 1e-3, 0.0, method="closed_form", options=(("rcond", -1.0),))
    d, V = sample_stream(5, 1, 4, 2, seed=5)
    s = jax.lax.scan(lambda s, xv: (ST.sample_step(s, *xv, 1e-3, 0.0, method="closed_form")[0], None), s,
                     (jnp.asarray(d[:, 0]), jnp.asarray(V[:, 0])))[0]

    def loss(x):
        new, _ = ST.sample_step(s, x, jnp.asarray([0.3, -0.2]), 1e-3, 0.0, method="closed_form")
        return jnp.sum(new.estimate**2) + new.last_deltas[1]

    x = jnp.asarray([0.1, -0.2, 0.3, 0.05])
    a, b = both(jax.grad(loss), x)
    np.testing.assert_allclose(a, b, rtol=1e-10)
    h = 1e-6
    fd = [(loss(x.at[i].add(h)) - loss(x.at[i].add(-h))) / (2 * h) for i in range(4)]
    np.testing.assert_allclose(a, fd, rtol=1e-5, atol=1e-8)


def test_the_step_handler_checks_its_argument_count():
    f32 = jnp.float32
    call = jax.ffi.ffi_call("SelfidStep", jax.ShapeDtypeStruct((4, 6, 3), f32), vmap_method="broadcast_all")
    with pytest.raises(Exception, match="step: wrong number of arguments or results"):
        jax.block_until_ready(call(jnp.ones((4, 6, 3), f32)))


def test_the_step_under_nested_vmap_with_a_threshold_batched_on_the_outer_axis_only():
    """``vmap(vmap(sample_step))`` over 3 x 5 estimators, ``eps`` batched over the 3 only (``broadcast_all`` gives the
    kernel one flat batch of 15): the pure-JAX values, ring buffers bit-identical."""
    A, B, n, m = 3, 5, 4, 2
    rng = np.random.default_rng(4)
    d = jnp.asarray(rng.normal(size=(2, A, B, n)), jnp.float32)
    V = jnp.asarray(rng.normal(size=(2, A, B, m)), jnp.float32)
    eps = jnp.asarray([1e-3, 1e-2, 1e-1], jnp.float32)

    def go(d, V, eps):
        s = jax.vmap(jax.vmap(lambda _: E.init(n, m, capacity=2, dtype=jnp.float32)))(jnp.zeros((A, B)))
        for t in range(2):
            s = jax.vmap(lambda s, x, v, e: jax.vmap(
                lambda s, x, v: ST.sample_step(s, x, v, e, 0.0, method="closed_form")[0])(s, x, v))(s, d[t], V[t], eps)
        return s

    assert "SelfidStep" in jax.jit(go).lower(d, V, eps).as_text()
    got = jax.jit(go)(d, V, eps)
    native.set_enabled(False)
    ref = jax.jit(go)(d, V, eps)
    native.set_enabled(True)
    assert_states_close(got, ref, 2e-5)
    np.testing.assert_array_equal(got.dtheta_buf, ref.dtheta_buf)
