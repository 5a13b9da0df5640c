// XLA FFI handlers for the CPU backend: the estimator's per-sample update and Eq. 14's closed form from the
// statistics, each over a batch of estimators in one call (selfid_jax.math.native registers and calls them).
//
// XLA's CPU code generator runs a vmapped estimator one scalar at a time; these kernels run the same operations
// on 8 float32 (4 float64) estimators per instruction. The arithmetic is estimator_kernels.inc, compiled twice:
// for the x86-64 baseline (SSE2) and, where the CPU has them, AVX2 and FMA (chosen at run time).
#ifdef __linux__
#include <sched.h>
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

// A kernel's arguments, each array at p + (first estimator) * stride (stride 0: one value for every estimator),
// its results written back to back (a result may be its argument's buffer: see selfid_jax.math.native's aliases).

// update's sums (its ring buffer is XLA's): sign_net, mag_sum, S_tv (n, m); mag_count (m,); S_vv (m, m); s_tt,
// v_tol, forget (); count, rejected () int32; the sample dtheta (n,), V (m,); the first eight written.
template <typename T>
struct UpdateArgs {
  const T *sign_net, *mag_sum, *mag_count, *S_vv, *S_tv, *s_tt;
  const int32_t *count, *rejected;
  const T *v_tol, *forget, *dtheta, *V;
  int64_t in_stride[12];
  T *o_sign_net, *o_mag_sum, *o_mag_count, *o_S_vv, *o_S_tv, *o_s_tt;
  int32_t *o_count, *o_rejected;
};

// record computing its norms: J, estimate (n, m); last_deltas, last_norms (2,); last_fresh (2,) bool; count,
// recorded_count, iteration, converged_at () int32; eps, eps_rel (); min_count () int32; written: estimate (= J),
// last_deltas, last_norms, last_fresh, recorded_count, iteration, converged_at.
template <typename T>
struct RecordArgs {
  const T *J, *estimate, *last_deltas, *last_norms;
  const bool* last_fresh;
  const int32_t *count, *recorded_count, *iteration, *converged_at;
  const T *eps, *eps_rel;
  const int32_t* min_count;
  int64_t in_stride[12];
  T *o_estimate, *o_last_deltas, *o_last_norms;
  bool* o_last_fresh;
  int32_t *o_recorded_count, *o_iteration, *o_converged_at;
};

namespace base {
#include "estimator_kernels.inc"
}  // namespace base

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SELFID_AVX2 1
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2,fma"))), apply_to = function)
#else
#pragma GCC push_options
#pragma GCC target("avx2,fma")
#endif
namespace avx2 {
#define SELFID_KERNELS_AVX2 1
#include "estimator_kernels.inc"
#undef SELFID_KERNELS_AVX2
}  // namespace avx2
#if defined(__clang__)
#pragma clang attribute pop
#else
#pragma GCC pop_options
#endif
#endif

namespace {

constexpr int64_t kMaxM = 6;
constexpr int64_t kMaxN = 64;

bool HasAvx2() {
#ifdef SELFID_AVX2
  static const bool has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has;
#else
  return false;
#endif
}

// CALL(NS, M) for the static m and the instruction set of this CPU.
#define SELFID_FOR_M(NS, CALL) \
  switch (m) {                 \
    case 1: CALL(NS, 1); break; \
    case 2: CALL(NS, 2); break; \
    case 3: CALL(NS, 3); break; \
    case 4: CALL(NS, 4); break; \
    case 5: CALL(NS, 5); break; \
    default: CALL(NS, 6); break; \
  }
#ifdef SELFID_AVX2
#define SELFID_DISPATCH(CALL)     \
  if (HasAvx2()) {                \
    SELFID_FOR_M(avx2, CALL)      \
  } else {                        \
    SELFID_FOR_M(base, CALL)      \
  }
#else
#define SELFID_DISPATCH(CALL) SELFID_FOR_M(base, CALL)
#endif

// One kernel's call: (n, m) from its (..., n, m) argument `shaped`, the batch, every argument's and result's size
// and dtype checked, and the arguments' strides.
struct Call {
  int64_t n = 0, m = 0, batch = 0;
  int64_t stride[12] = {};
  ffi::DataType dtype = ffi::DataType::F32;

  ffi::Error Check(const char* kernel, const ffi::AnyBuffer& shaped, const ffi::AnyBuffer* in, int n_in,
                   const int64_t* in_sizes, const ffi::DataType* in_types, ffi::Result<ffi::AnyBuffer>* out,
                   int n_out, const int64_t* out_sizes, const ffi::DataType* out_types) {
    auto dims = shaped.dimensions();
    if (dims.size() < 2) return Fail(kernel, "the (n, m) argument has rank < 2");
    n = dims[dims.size() - 2];
    m = dims[dims.size() - 1];
    if (m < 1 || m > kMaxM || n < 1 || n > kMaxN) return Fail(kernel, "expected 1 <= m <= 6 and 1 <= n <= 64");
    batch = static_cast<int64_t>(shaped.element_count()) / (n * m);
    dtype = shaped.element_type();
    if (dtype != ffi::DataType::F32 && dtype != ffi::DataType::F64) return Fail(kernel, "float32 or float64 only");
    for (int k = 0; k < n_in; ++k) {
      const int64_t count = static_cast<int64_t>(in[k].element_count());
      if (in[k].element_type() != in_types[k]) return Fail(kernel, "an argument's dtype is not the expected one");
      if (count != in_sizes[k] * batch && count != in_sizes[k])
        return Fail(kernel, "an argument's size does not match the batch");
      stride[k] = count == in_sizes[k] * batch ? in_sizes[k] : 0;
    }
    for (int k = 0; k < n_out; ++k)
      if (static_cast<int64_t>(out[k]->element_count()) != out_sizes[k] * batch ||
          out[k]->element_type() != out_types[k])
        return Fail(kernel, "a result's size or dtype is not the expected one");
    return ffi::Error::Success();
  }

  static ffi::Error Fail(const char* kernel, const char* what) {
    return ffi::Error::InvalidArgument(std::string(kernel) + ": " + what);
  }
};

// body(begin, end) over estimators [0, batch), in chunks of whole blocks of 8 on the calling thread and XLA's
// intra-op thread pool (chunks of at least kMinChunk estimators; one chunk below that). A scheduled task that starts
// late finds no chunk left and returns: the caller waits only for chunks that a thread has taken, never for a task
// the pool has not started, so a busy pool costs time, not a deadlock.
// The most threads a kernel uses (read once): SELFID_JAX_NATIVE_THREADS if set above 0, else the CPUs this process
// may run on (on Linux; a thread pool larger than that would only take turns on them), else no limit (0).
constexpr int64_t kMinChunk = 2048;

int64_t MaxThreads() {
  static const int64_t max = [] {
    const char* v = std::getenv("SELFID_JAX_NATIVE_THREADS");
    const int64_t asked = v == nullptr ? 0 : std::max<int64_t>(0, std::atoll(v));
    if (asked > 0) return asked;
#ifdef __linux__
    cpu_set_t set;
    if (sched_getaffinity(0, sizeof(set), &set) == 0) return static_cast<int64_t>(CPU_COUNT(&set));
#endif
    return int64_t{0};
  }();
  return max;
}

template <typename Body>
void ParallelFor(ffi::ThreadPool& pool, int64_t batch, const Body& body) {
  int64_t threads = std::max<int64_t>(1, pool.num_threads());
  if (MaxThreads() > 0) threads = std::min(threads, MaxThreads());
  const int64_t chunks = std::min<int64_t>(threads, batch / kMinChunk);
  if (chunks <= 1) {
    body(int64_t{0}, batch);
    return;
  }
  const int64_t size = (batch / chunks + 7) / 8 * 8;
  const int64_t count = (batch + size - 1) / size;
  struct Progress {
    std::atomic<int64_t> next{0}, done{0};
  };
  auto progress = std::make_shared<Progress>();
  auto work = [progress, &body, size, count, batch]() {
    for (int64_t k; (k = progress->next.fetch_add(1)) < count;) {
      body(k * size, std::min(batch, (k + 1) * size));
      progress->done.fetch_add(1, std::memory_order_release);
    }
  };
  for (int64_t t = 1; t < chunks; ++t) pool.Schedule([progress, work]() { work(); });
  work();
  while (progress->done.load(std::memory_order_acquire) < count) std::this_thread::yield();
}

template <typename T>
void ClosedFormTyped(ffi::ThreadPool& pool, const Call& c, const ffi::AnyBuffer* in, T* J) {
  const int64_t n = c.n, m = c.m;
  const int64_t* st = c.stride;
  const T *S = in[0].typed_data<T>(), *St = in[1].typed_data<T>(), *J0 = in[2].typed_data<T>(),
          *rc = in[3].typed_data<T>();
#define SELFID_CALL(NS, M) NS::ClosedFormBatch<T, M>(begin, end, n, S, st[0], St, st[1], J0, st[2], rc, st[3], J)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

ffi::Error ClosedFormImpl(ffi::ThreadPool pool, ffi::AnyBuffer S_vv, ffi::AnyBuffer S_tv, ffi::AnyBuffer J0,
                          ffi::AnyBuffer rcond, ffi::Result<ffi::AnyBuffer> J) {
  const ffi::AnyBuffer in[4] = {S_vv, S_tv, J0, rcond};
  ffi::Result<ffi::AnyBuffer> out[1] = {J};
  Call c;
  const auto f = S_tv.element_type();
  const int64_t n = S_tv.dimensions().size() >= 2 ? S_tv.dimensions()[S_tv.dimensions().size() - 2] : 0;
  const int64_t m = S_tv.dimensions().size() >= 2 ? S_tv.dimensions()[S_tv.dimensions().size() - 1] : 0;
  const int64_t in_sizes[4] = {m * m, n * m, n * m, 1}, out_sizes[1] = {n * m};
  const ffi::DataType in_types[4] = {f, f, f, f}, out_types[1] = {f};
  if (auto e = c.Check("closed form", S_tv, in, 4, in_sizes, in_types, out, 1, out_sizes, out_types); e.failure())
    return e;
  if (c.dtype == ffi::DataType::F32)
    ClosedFormTyped<float>(pool, c, in, J->typed_data<float>());
  else
    ClosedFormTyped<double>(pool, c, in, J->typed_data<double>());
  return ffi::Error::Success();
}

template <typename T>
void UpdateTyped(ffi::ThreadPool& pool, const Call& c, const ffi::AnyBuffer* in, ffi::Result<ffi::AnyBuffer>* out) {
  const int64_t n = c.n, m = c.m;
  UpdateArgs<T> a;
  a.sign_net = in[0].typed_data<T>();
  a.mag_sum = in[1].typed_data<T>();
  a.mag_count = in[2].typed_data<T>();
  a.S_vv = in[3].typed_data<T>();
  a.S_tv = in[4].typed_data<T>();
  a.s_tt = in[5].typed_data<T>();
  a.count = in[6].typed_data<int32_t>();
  a.rejected = in[7].typed_data<int32_t>();
  a.v_tol = in[8].typed_data<T>();
  a.forget = in[9].typed_data<T>();
  a.dtheta = in[10].typed_data<T>();
  a.V = in[11].typed_data<T>();
  for (int k = 0; k < 12; ++k) a.in_stride[k] = c.stride[k];
  a.o_sign_net = out[0]->typed_data<T>();
  a.o_mag_sum = out[1]->typed_data<T>();
  a.o_mag_count = out[2]->typed_data<T>();
  a.o_S_vv = out[3]->typed_data<T>();
  a.o_S_tv = out[4]->typed_data<T>();
  a.o_s_tt = out[5]->typed_data<T>();
  a.o_count = out[6]->typed_data<int32_t>();
  a.o_rejected = out[7]->typed_data<int32_t>();
#define SELFID_CALL(NS, M) NS::UpdateBatch<T, M>(begin, end, n, a)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

ffi::Error UpdateImpl(ffi::ThreadPool pool, ffi::AnyBuffer sign_net, ffi::AnyBuffer mag_sum, ffi::AnyBuffer mag_count,
                      ffi::AnyBuffer S_vv, ffi::AnyBuffer S_tv, ffi::AnyBuffer s_tt, ffi::AnyBuffer count,
                      ffi::AnyBuffer rejected, ffi::AnyBuffer v_tol, ffi::AnyBuffer forget, ffi::AnyBuffer dtheta,
                      ffi::AnyBuffer V, ffi::Result<ffi::AnyBuffer> o0, ffi::Result<ffi::AnyBuffer> o1,
                      ffi::Result<ffi::AnyBuffer> o2, ffi::Result<ffi::AnyBuffer> o3, ffi::Result<ffi::AnyBuffer> o4,
                      ffi::Result<ffi::AnyBuffer> o5, ffi::Result<ffi::AnyBuffer> o6, ffi::Result<ffi::AnyBuffer> o7) {
  const ffi::AnyBuffer in[12] = {sign_net, mag_sum, mag_count, S_vv, S_tv, s_tt, count, rejected, v_tol, forget,
                                 dtheta, V};
  ffi::Result<ffi::AnyBuffer> out[8] = {o0, o1, o2, o3, o4, o5, o6, o7};
  const auto f = S_tv.element_type(), i = ffi::DataType::S32;
  const int64_t n = S_tv.dimensions().size() >= 2 ? S_tv.dimensions()[S_tv.dimensions().size() - 2] : 0;
  const int64_t m = S_tv.dimensions().size() >= 2 ? S_tv.dimensions()[S_tv.dimensions().size() - 1] : 0;
  const int64_t sizes[12] = {n * m, n * m, m, m * m, n * m, 1, 1, 1, 1, 1, n, m};
  const ffi::DataType types[12] = {f, f, f, f, f, f, i, i, f, f, f, f};
  Call c;
  if (auto e = c.Check("update", S_tv, in, 12, sizes, types, out, 8, sizes, types); e.failure()) return e;
  if (c.dtype == ffi::DataType::F32)
    UpdateTyped<float>(pool, c, in, out);
  else
    UpdateTyped<double>(pool, c, in, out);
  return ffi::Error::Success();
}

template <typename T>
void RecordTyped(ffi::ThreadPool& pool, const Call& c, const ffi::AnyBuffer* in, ffi::Result<ffi::AnyBuffer>* out) {
  const int64_t n = c.n, m = c.m;
  RecordArgs<T> a;
  a.J = in[0].typed_data<T>();
  a.estimate = in[1].typed_data<T>();
  a.last_deltas = in[2].typed_data<T>();
  a.last_norms = in[3].typed_data<T>();
  a.last_fresh = in[4].typed_data<bool>();
  a.count = in[5].typed_data<int32_t>();
  a.recorded_count = in[6].typed_data<int32_t>();
  a.iteration = in[7].typed_data<int32_t>();
  a.converged_at = in[8].typed_data<int32_t>();
  a.eps = in[9].typed_data<T>();
  a.eps_rel = in[10].typed_data<T>();
  a.min_count = in[11].typed_data<int32_t>();
  for (int k = 0; k < 12; ++k) a.in_stride[k] = c.stride[k];
  a.o_estimate = out[0]->typed_data<T>();
  a.o_last_deltas = out[1]->typed_data<T>();
  a.o_last_norms = out[2]->typed_data<T>();
  a.o_last_fresh = out[3]->typed_data<bool>();
  a.o_recorded_count = out[4]->typed_data<int32_t>();
  a.o_iteration = out[5]->typed_data<int32_t>();
  a.o_converged_at = out[6]->typed_data<int32_t>();
#define SELFID_CALL(NS, M) NS::RecordBatch<T, M>(begin, end, n, a)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

ffi::Error RecordImpl(ffi::ThreadPool pool, ffi::AnyBuffer J, ffi::AnyBuffer estimate, ffi::AnyBuffer last_deltas,
                      ffi::AnyBuffer last_norms, ffi::AnyBuffer last_fresh, ffi::AnyBuffer count,
                      ffi::AnyBuffer recorded_count, ffi::AnyBuffer iteration, ffi::AnyBuffer converged_at,
                      ffi::AnyBuffer eps, ffi::AnyBuffer eps_rel, ffi::AnyBuffer min_count,
                      ffi::Result<ffi::AnyBuffer> o0, ffi::Result<ffi::AnyBuffer> o1, ffi::Result<ffi::AnyBuffer> o2,
                      ffi::Result<ffi::AnyBuffer> o3, ffi::Result<ffi::AnyBuffer> o4, ffi::Result<ffi::AnyBuffer> o5,
                      ffi::Result<ffi::AnyBuffer> o6) {
  const ffi::AnyBuffer in[12] = {J, estimate, last_deltas, last_norms, last_fresh, count, recorded_count,
                                 iteration, converged_at, eps, eps_rel, min_count};
  ffi::Result<ffi::AnyBuffer> out[7] = {o0, o1, o2, o3, o4, o5, o6};
  const auto f = J.element_type(), i = ffi::DataType::S32, b = ffi::DataType::PRED;
  const int64_t n = J.dimensions().size() >= 2 ? J.dimensions()[J.dimensions().size() - 2] : 0;
  const int64_t m = J.dimensions().size() >= 2 ? J.dimensions()[J.dimensions().size() - 1] : 0;
  const int64_t in_sizes[12] = {n * m, n * m, 2, 2, 2, 1, 1, 1, 1, 1, 1, 1}, out_sizes[7] = {n * m, 2, 2, 2, 1, 1, 1};
  const ffi::DataType in_types[12] = {f, f, f, f, b, i, i, i, i, f, f, i}, out_types[7] = {f, f, f, b, i, i, i};
  Call c;
  if (auto e = c.Check("record", J, in, 12, in_sizes, in_types, out, 7, out_sizes, out_types); e.failure())
    return e;
  if (c.dtype == ffi::DataType::F32)
    RecordTyped<float>(pool, c, in, out);
  else
    RecordTyped<double>(pool, c, in, out);
  return ffi::Error::Success();
}

}  // namespace

// The handlers' argument lists' version: selfid_jax.math.native refuses a library built from other sources (an
// editable checkout pulled without a rebuild) instead of calling it with arguments it does not take.
extern "C" int SelfidKernelsAbi() { return 1; }

XLA_FFI_DEFINE_HANDLER_SYMBOL(SelfidClosedForm, ClosedFormImpl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(SelfidUpdate, UpdateImpl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(SelfidRecord, RecordImpl,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>());
