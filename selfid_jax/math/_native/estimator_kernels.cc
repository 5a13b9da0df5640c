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

// the whole closed-form step (selfid_jax.identify.step.sample_step, ring buffer aside): update's arguments and
// results, then record's on the estimate the step refines (r.J unused; r.count is u.o_count, the new count), rcond.
template <typename T>
struct StepArgs {
  UpdateArgs<T> u;
  RecordArgs<T> r;
  const T* rcond;
  int64_t s_rcond;
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

// A kernel's fields: sizes per estimator in terms of (n, m), and element types (float: the call's dtype).
enum Size { kNM, kM, kMM, kN, kOne, kTwo };
enum Kind { kFloat, kInt, kBool };
struct Field {
  Size size;
  Kind kind;
};

struct Spec {
  const char* name;
  int shaped;  // the argument whose last two dimensions are (n, m)
  std::vector<Field> in, out;
};

// One kernel's call: (n, m) from its (..., n, m) argument, the batch, every argument's and result's size and dtype
// checked; the arguments' data and strides (stride 0: one value for every estimator), the results' data.
struct Call {
  int64_t n = 0, m = 0, batch = 0;
  ffi::DataType dtype = ffi::DataType::F32;
  std::vector<const void*> in;
  std::vector<int64_t> stride;
  std::vector<void*> out;

  ffi::Error Decode(const Spec& spec, const ffi::RemainingArgs& args, const ffi::RemainingRets& rets) {
    if (args.size() != spec.in.size() || rets.size() != spec.out.size())
      return Fail(spec, "wrong number of arguments or results");
    std::vector<ffi::AnyBuffer> a;
    for (size_t k = 0; k < args.size(); ++k) {
      auto x = args.get<ffi::AnyBuffer>(k);
      if (x.has_error()) return Fail(spec, "an argument is not a buffer");
      a.push_back(x.value());
    }
    auto dims = a[spec.shaped].dimensions();
    if (dims.size() < 2) return Fail(spec, "the (n, m) argument has rank < 2");
    n = dims[dims.size() - 2];
    m = dims[dims.size() - 1];
    if (m < 1 || m > kMaxM || n < 1 || n > kMaxN) return Fail(spec, "expected 1 <= m <= 6 and 1 <= n <= 64");
    batch = static_cast<int64_t>(a[spec.shaped].element_count()) / (n * m);
    dtype = a[spec.shaped].element_type();
    if (dtype != ffi::DataType::F32 && dtype != ffi::DataType::F64) return Fail(spec, "float32 or float64 only");
    for (size_t k = 0; k < a.size(); ++k) {
      const int64_t size = Count(spec.in[k].size), count = static_cast<int64_t>(a[k].element_count());
      if (a[k].element_type() != Type(spec.in[k].kind)) return Fail(spec, "an argument's dtype is not the expected one");
      if (count != size * batch && count != size) return Fail(spec, "an argument's size does not match the batch");
      in.push_back(a[k].untyped_data());
      stride.push_back(count == size * batch ? size : 0);
    }
    for (size_t k = 0; k < rets.size(); ++k) {
      auto x = rets.get<ffi::AnyBuffer>(k);
      if (x.has_error()) return Fail(spec, "a result is not a buffer");
      if (static_cast<int64_t>(x.value()->element_count()) != Count(spec.out[k].size) * batch ||
          x.value()->element_type() != Type(spec.out[k].kind))
        return Fail(spec, "a result's size or dtype is not the expected one");
      out.push_back(x.value()->untyped_data());
    }
    return ffi::Error::Success();
  }

  int64_t Count(Size size) const {
    switch (size) {
      case kNM: return n * m;
      case kM: return m;
      case kMM: return m * m;
      case kN: return n;
      case kOne: return 1;
      default: return 2;
    }
  }

  ffi::DataType Type(Kind kind) const {
    return kind == kFloat ? dtype : kind == kInt ? ffi::DataType::S32 : ffi::DataType::PRED;
  }

  template <typename U>
  const U* In(int k) const {
    return static_cast<const U*>(in[k]);
  }
  template <typename U>
  U* Out(int k) const {
    return static_cast<U*>(out[k]);
  }

  static ffi::Error Fail(const Spec& spec, const char* what) {
    return ffi::Error::InvalidArgument(std::string(spec.name) + ": " + what);
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

// The kernels' arguments and results, in selfid_jax.math.native's order.
const Spec kClosedForm{"closed form", 1, {{kMM, kFloat}, {kNM, kFloat}, {kNM, kFloat}, {kOne, kFloat}},
                       {{kNM, kFloat}}};
// update: sign_net, mag_sum, mag_count, S_vv, S_tv, s_tt, count, rejected, v_tol, forget, dtheta, V; the first 8
#define SELFID_UPDATE_IN                                                                                     \
  {kNM, kFloat}, {kNM, kFloat}, {kM, kFloat}, {kMM, kFloat}, {kNM, kFloat}, {kOne, kFloat}, {kOne, kInt}, \
      {kOne, kInt}, {kOne, kFloat}, {kOne, kFloat}
#define SELFID_UPDATE_OUT                                                                                    \
  {kNM, kFloat}, {kNM, kFloat}, {kM, kFloat}, {kMM, kFloat}, {kNM, kFloat}, {kOne, kFloat}, {kOne, kInt}, \
      {kOne, kInt}
// record's results: estimate, last_deltas, last_norms, last_fresh, recorded_count, iteration, converged_at
#define SELFID_RECORD_OUT \
  {kNM, kFloat}, {kTwo, kFloat}, {kTwo, kFloat}, {kTwo, kBool}, {kOne, kInt}, {kOne, kInt}, {kOne, kInt}
const Spec kUpdate{"update", 4, {SELFID_UPDATE_IN, {kN, kFloat}, {kM, kFloat}}, {SELFID_UPDATE_OUT}};
// record: J, estimate, last_deltas, last_norms, last_fresh, count, recorded_count, iteration, converged_at, eps,
// eps_rel, min_count
const Spec kRecord{"record", 0,
                   {{kNM, kFloat}, {kNM, kFloat}, {kTwo, kFloat}, {kTwo, kFloat}, {kTwo, kBool}, {kOne, kInt},
                    {kOne, kInt}, {kOne, kInt}, {kOne, kInt}, {kOne, kFloat}, {kOne, kFloat}, {kOne, kInt}},
                   {SELFID_RECORD_OUT}};
// step: update's ten fields, estimate, last_deltas, last_norms, last_fresh, recorded_count, iteration,
// converged_at, dtheta, V, rcond, eps, eps_rel, min_count; update's eight results, then record's seven
const Spec kStep{"step", 4,
                 {SELFID_UPDATE_IN, {kNM, kFloat}, {kTwo, kFloat}, {kTwo, kFloat}, {kTwo, kBool}, {kOne, kInt},
                  {kOne, kInt}, {kOne, kInt}, {kN, kFloat}, {kM, kFloat}, {kOne, kFloat}, {kOne, kFloat},
                  {kOne, kFloat}, {kOne, kInt}},
                 {SELFID_UPDATE_OUT, SELFID_RECORD_OUT}};
#undef SELFID_UPDATE_IN
#undef SELFID_UPDATE_OUT
#undef SELFID_RECORD_OUT

// update's arguments from the call's fields: its 10 state fields at `first`, dtheta and V at `sample`, results at
// `result`.
template <typename T>
UpdateArgs<T> UpdateFrom(const Call& c, int first, int sample, int result) {
  UpdateArgs<T> a;
  a.sign_net = c.In<T>(first);
  a.mag_sum = c.In<T>(first + 1);
  a.mag_count = c.In<T>(first + 2);
  a.S_vv = c.In<T>(first + 3);
  a.S_tv = c.In<T>(first + 4);
  a.s_tt = c.In<T>(first + 5);
  a.count = c.In<int32_t>(first + 6);
  a.rejected = c.In<int32_t>(first + 7);
  a.v_tol = c.In<T>(first + 8);
  a.forget = c.In<T>(first + 9);
  a.dtheta = c.In<T>(sample);
  a.V = c.In<T>(sample + 1);
  const int at[12] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, sample - first, sample + 1 - first};
  for (int k = 0; k < 12; ++k) a.in_stride[k] = c.stride[first + at[k]];
  a.o_sign_net = c.Out<T>(result);
  a.o_mag_sum = c.Out<T>(result + 1);
  a.o_mag_count = c.Out<T>(result + 2);
  a.o_S_vv = c.Out<T>(result + 3);
  a.o_S_tv = c.Out<T>(result + 4);
  a.o_s_tt = c.Out<T>(result + 5);
  a.o_count = c.Out<int32_t>(result + 6);
  a.o_rejected = c.Out<int32_t>(result + 7);
  return a;
}

// record's arguments: index[k] is the call's argument for record's k-th (J, estimate, last_deltas, last_norms,
// last_fresh, count, recorded_count, iteration, converged_at, eps, eps_rel, min_count; -1: none), results at
// `result`.
template <typename T>
RecordArgs<T> RecordFrom(const Call& c, const int* index, int result) {
  RecordArgs<T> a;
  auto in = [&](int k) { return index[k] < 0 ? nullptr : c.in[index[k]]; };
  a.J = static_cast<const T*>(in(0));
  a.estimate = static_cast<const T*>(in(1));
  a.last_deltas = static_cast<const T*>(in(2));
  a.last_norms = static_cast<const T*>(in(3));
  a.last_fresh = static_cast<const bool*>(in(4));
  a.count = static_cast<const int32_t*>(in(5));
  a.recorded_count = static_cast<const int32_t*>(in(6));
  a.iteration = static_cast<const int32_t*>(in(7));
  a.converged_at = static_cast<const int32_t*>(in(8));
  a.eps = static_cast<const T*>(in(9));
  a.eps_rel = static_cast<const T*>(in(10));
  a.min_count = static_cast<const int32_t*>(in(11));
  for (int k = 0; k < 12; ++k) a.in_stride[k] = index[k] < 0 ? 0 : c.stride[index[k]];
  a.o_estimate = c.Out<T>(result);
  a.o_last_deltas = c.Out<T>(result + 1);
  a.o_last_norms = c.Out<T>(result + 2);
  a.o_last_fresh = c.Out<bool>(result + 3);
  a.o_recorded_count = c.Out<int32_t>(result + 4);
  a.o_iteration = c.Out<int32_t>(result + 5);
  a.o_converged_at = c.Out<int32_t>(result + 6);
  return a;
}

template <typename T>
void ClosedFormTyped(ffi::ThreadPool& pool, const Call& c) {
  const int64_t n = c.n, m = c.m;
  const int64_t* st = c.stride.data();
  const T *S = c.In<T>(0), *St = c.In<T>(1), *J0 = c.In<T>(2), *rc = c.In<T>(3);
  T* J = c.Out<T>(0);
#define SELFID_CALL(NS, M) NS::ClosedFormBatch<T, M>(begin, end, n, S, st[0], St, st[1], J0, st[2], rc, st[3], J)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

template <typename T>
void UpdateTyped(ffi::ThreadPool& pool, const Call& c) {
  const int64_t n = c.n, m = c.m;
  const UpdateArgs<T> a = UpdateFrom<T>(c, 0, 10, 0);
#define SELFID_CALL(NS, M) NS::UpdateBatch<T, M>(begin, end, n, a)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

template <typename T>
void RecordTyped(ffi::ThreadPool& pool, const Call& c) {
  const int64_t n = c.n, m = c.m;
  const int index[12] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11};
  const RecordArgs<T> a = RecordFrom<T>(c, index, 0);
#define SELFID_CALL(NS, M) NS::RecordBatch<T, M>(begin, end, n, a)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

template <typename T>
void StepTyped(ffi::ThreadPool& pool, const Call& c) {
  const int64_t n = c.n, m = c.m;
  StepArgs<T> a;
  a.u = UpdateFrom<T>(c, 0, 17, 0);
  const int index[12] = {-1, 10, 11, 12, 13, -1, 14, 15, 16, 20, 21, 22};
  a.r = RecordFrom<T>(c, index, 8);
  a.r.count = a.u.o_count;  // the count the update wrote
  a.r.in_stride[5] = 1;
  a.rcond = c.In<T>(19);
  a.s_rcond = c.stride[19];
#define SELFID_CALL(NS, M) NS::StepBatch<T, M>(begin, end, n, a)
  ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL) });
#undef SELFID_CALL
}

template <void (*F32)(ffi::ThreadPool&, const Call&), void (*F64)(ffi::ThreadPool&, const Call&)>
ffi::Error Run(const Spec& spec, ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  Call c;
  if (auto e = c.Decode(spec, args, rets); e.failure()) return e;
  if (c.dtype == ffi::DataType::F32)
    F32(pool, c);
  else
    F64(pool, c);
  return ffi::Error::Success();
}

ffi::Error ClosedFormImpl(ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  return Run<ClosedFormTyped<float>, ClosedFormTyped<double>>(kClosedForm, pool, args, rets);
}
ffi::Error UpdateImpl(ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  return Run<UpdateTyped<float>, UpdateTyped<double>>(kUpdate, pool, args, rets);
}
ffi::Error RecordImpl(ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  return Run<RecordTyped<float>, RecordTyped<double>>(kRecord, pool, args, rets);
}
ffi::Error StepImpl(ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  return Run<StepTyped<float>, StepTyped<double>>(kStep, pool, args, rets);
}

}  // namespace

// The handlers' argument lists' version: selfid_jax.math.native refuses a library built from other sources (an
// editable checkout pulled without a rebuild) instead of calling it with arguments it does not take.
extern "C" int SelfidKernelsAbi() { return 2; }

#define SELFID_HANDLER(NAME, IMPL) \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, IMPL, ffi::Ffi::Bind().Ctx<ffi::ThreadPool>().RemainingArgs().RemainingRets());
SELFID_HANDLER(SelfidClosedForm, ClosedFormImpl)
SELFID_HANDLER(SelfidUpdate, UpdateImpl)
SELFID_HANDLER(SelfidRecord, RecordImpl)
SELFID_HANDLER(SelfidStep, StepImpl)
