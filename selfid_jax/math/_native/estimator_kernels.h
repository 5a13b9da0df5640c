// Shared by the kernels' translation units (estimator_kernels.cc: update, closed form, record; step_kernel.cc:
// the step), which setup.py compiles side by side: the arrays and argument roles, the batch loop, the argument
// checks and the handler macros; the arithmetic itself is estimator_kernels.inc.
#ifndef SELFID_ESTIMATOR_KERNELS_H_
#define SELFID_ESTIMATOR_KERNELS_H_

#ifdef __linux__
#include <sched.h>
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
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

// One array of a call: F elements per estimator, estimator l's element k at p[(l * ls + k) * bytes] (bytes per
// element; ls = F, or 0: one array for every estimator).
struct Arr {
  char* p;
  int64_t ls, F;
  int bytes;

  Arr At(int64_t start) const { return Arr{p + start * ls * bytes, ls, F, bytes}; }
};

// A call's arguments and results.
struct Args {
  Arr in[24];
  Arr out[16];
  int n_in = 0, n_out = 0;
};

// W estimators' copy of `a` (its first r, the last repeated), row-major in `buf`; `a` itself where ls = 0.
inline Arr Pad(const Arr& a, int64_t r, int W, std::vector<char>& buf) {
  if (a.ls == 0) return a;
  buf.resize(static_cast<size_t>(W * a.F * a.bytes));
  for (int64_t l = 0; l < W; ++l)
    for (int64_t k = 0; k < a.F; ++k)
      std::memcpy(buf.data() + (l * a.F + k) * a.bytes, a.p + ((l < r ? l : r - 1) * a.ls + k) * a.bytes, a.bytes);
  return Arr{buf.data(), a.F, a.F, a.bytes};
}

// W estimators' row-major scratch for a result like `a`.
inline Arr Scratch(const Arr& a, int W, std::vector<char>& buf) {
  buf.resize(static_cast<size_t>(W * a.F * a.bytes));
  return Arr{buf.data(), a.F, a.F, a.bytes};
}

// The first r estimators of scratch `s` into `d`.
inline void Unpad(const Arr& s, const Arr& d, int64_t r) {
  for (int64_t l = 0; l < r; ++l)
    for (int64_t k = 0; k < s.F; ++k)
      std::memcpy(d.p + (l * d.ls + k) * d.bytes, s.p + (l * s.F + k) * s.bytes, s.bytes);
}

// The kernels' arguments by role: update's (its first eight are also its results, in this order) and record's
// (J, then the state's fields it reads, the thresholds), and where each kernel has them.
enum UpdateRole { kSignNet, kMagSum, kMagCount, kSvv, kStv, kStt, kCount, kRejected, kVtol, kForget, kDtheta, kV };
enum RecordRole {
  kJ, kEstimate, kLastDeltas, kLastNorms, kLastFresh, kRecordCount, kRecordedCount, kIteration, kConvergedAt,
  kEps, kEpsRel, kMinCount
};
enum RecordResult {
  kOutEstimate, kOutLastDeltas, kOutLastNorms, kOutLastFresh, kOutRecordedCount, kOutIteration, kOutConvergedAt
};
constexpr int kUpdateArgs[12] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11};
constexpr int kRecordArgs[12] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11};
// step: update's ten fields, estimate, last_deltas, last_norms, last_fresh, recorded_count, iteration,
// converged_at, dtheta, V, rcond, eps, eps_rel, min_count (the record's count is the update's result)
constexpr int kStepUpdateArgs[12] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 17, 18};
constexpr int kStepRecordArgs[12] = {-1, 10, 11, 12, 13, -1, 14, 15, 16, 20, 21, 22};
constexpr int kStepRcond = 19;

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SELFID_KERNELS 1
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx2,fma"))), apply_to = function)
#else
#pragma GCC push_options
#pragma GCC target("avx2,fma")
#endif
// the step kernel inlines every function it calls (GCC's flatten): its loads, transposes and the closed form's
// factorisations then share registers with the update and the record
#define SELFID_FLATTEN __attribute__((flatten))
namespace avx2 {
#include "estimator_kernels.inc"
}  // namespace avx2
#if defined(__clang__)
#pragma clang attribute pop
#else
#pragma GCC pop_options
#endif

namespace {

constexpr int64_t kMaxM = 6;
constexpr int64_t kMaxN = 64;

bool HasAvx2() {
  static const bool has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has;
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
#define SELFID_DISPATCH(CALL) SELFID_FOR_M(avx2, CALL)

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
// checked; its arrays.
struct Call {
  int64_t n = 0, m = 0, batch = 0;
  ffi::DataType dtype = ffi::DataType::F32;
  Args args;

  ffi::Error Decode(const Spec& spec, const ffi::RemainingArgs& in, const ffi::RemainingRets& out) {
    if (in.size() != spec.in.size() || out.size() != spec.out.size())
      return Fail(spec, "wrong number of arguments or results");
    std::vector<ffi::AnyBuffer> a;
    for (size_t k = 0; k < in.size(); ++k) {
      auto x = in.get<ffi::AnyBuffer>(k);
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
    args.n_in = static_cast<int>(a.size());
    for (size_t k = 0; k < a.size(); ++k) {
      const int64_t size = Count(spec.in[k].size), count = static_cast<int64_t>(a[k].element_count());
      if (a[k].element_type() != Type(spec.in[k].kind)) return Fail(spec, "an argument's dtype is not the expected one");
      if (count != size * batch && count != size) return Fail(spec, "an argument's size does not match the batch");
      args.in[k] = Arr{static_cast<char*>(a[k].untyped_data()), count == size * batch ? size : 0, size,
                       Bytes(spec.in[k].kind)};
    }
    args.n_out = static_cast<int>(out.size());
    for (size_t k = 0; k < out.size(); ++k) {
      auto x = out.get<ffi::AnyBuffer>(k);
      if (x.has_error()) return Fail(spec, "a result is not a buffer");
      const int64_t size = Count(spec.out[k].size);
      if (static_cast<int64_t>(x.value()->element_count()) != size * batch ||
          x.value()->element_type() != Type(spec.out[k].kind))
        return Fail(spec, "a result's size or dtype is not the expected one");
      args.out[k] = Arr{static_cast<char*>(x.value()->untyped_data()), size, size, Bytes(spec.out[k].kind)};
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

  int Bytes(Kind kind) const {
    return kind == kFloat ? (dtype == ffi::DataType::F32 ? 4 : 8) : kind == kInt ? 4 : 1;
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

// The kernel's blocks over the call's estimators, on the calling thread and XLA's pool.
#define SELFID_TYPED(KERNEL)                                                                            \
  template <typename T>                                                                                 \
  void KERNEL##Typed(ffi::ThreadPool& pool, const Call& c) {                                            \
    const int64_t n = c.n, m = c.m;                                                                     \
    const Args& a = c.args;                                                                             \
    ParallelFor(pool, c.batch, [&](int64_t begin, int64_t end) { SELFID_DISPATCH(SELFID_CALL_##KERNEL) }); \
  }
#define SELFID_CALL_ClosedForm(NS, M) NS::Batch<T, NS::ClosedFormBlock<T, M>>(begin, end, n, a)
#define SELFID_CALL_Update(NS, M) NS::Batch<T, NS::UpdateBlock<T, M>>(begin, end, n, a)
#define SELFID_CALL_Record(NS, M) NS::Batch<T, NS::RecordBlock<T, M>>(begin, end, n, a)
#define SELFID_CALL_Step(NS, M) NS::Batch<T, NS::StepBlock<T, M>>(begin, end, n, a)

template <void (*F32)(ffi::ThreadPool&, const Call&), void (*F64)(ffi::ThreadPool&, const Call&)>
ffi::Error Run(const Spec& spec, ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) {
  if (!HasAvx2()) return ffi::Error::InvalidArgument(std::string(spec.name) + ": this CPU lacks AVX2 or FMA");
  Call c;
  if (auto e = c.Decode(spec, args, rets); e.failure()) return e;
  if (c.dtype == ffi::DataType::F32)
    F32(pool, c);
  else
    F64(pool, c);
  return ffi::Error::Success();
}

#define SELFID_IMPL(KERNEL, SPEC)                                                                            \
  ffi::Error KERNEL##Impl(ffi::ThreadPool pool, ffi::RemainingArgs args, ffi::RemainingRets rets) { \
    return Run<KERNEL##Typed<float>, KERNEL##Typed<double>>(SPEC, pool, args, rets);                  \
  }

}  // namespace

#define SELFID_HANDLER(NAME, IMPL) \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(NAME, IMPL,                                                                 \
                                ffi::Ffi::Bind()                                                            \
                                    .Ctx<ffi::ThreadPool>()                                                 \
                                    .RemainingArgs()                                                        \
                                    .RemainingRets());
#endif  // SELFID_KERNELS

#endif  // SELFID_ESTIMATOR_KERNELS_H_
