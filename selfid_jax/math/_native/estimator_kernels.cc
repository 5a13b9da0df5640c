// XLA FFI handlers for the CPU backend: the estimator's per-sample update and Eq. 14's closed form from the
// statistics, each over a batch of estimators in one call (selfid_jax.math.native registers and calls them).
//
// XLA's CPU code generator runs a vmapped estimator one scalar at a time; these kernels run the same operations
// on 8 float32 (4 float64) estimators per instruction. The arithmetic is estimator_kernels.inc, compiled twice:
// for the x86-64 baseline (SSE2) and, where the CPU has them, AVX2 and FMA (chosen at run time).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

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

// Per-estimator stride of an input holding `size` values per estimator: 0 if it holds one set for the whole batch.
bool Stride(const ffi::AnyBuffer& x, int64_t size, int64_t batch, int64_t* stride) {
  int64_t count = static_cast<int64_t>(x.element_count());
  if (count == size * batch) {
    *stride = size;
    return true;
  }
  if (count == size) {
    *stride = 0;
    return true;
  }
  return false;
}

template <typename T>
void ClosedFormTyped(int64_t batch, int64_t n, int64_t m, const ffi::AnyBuffer* in, int64_t* st, T* out) {
  const T *S = in[0].typed_data<T>(), *St = in[1].typed_data<T>(), *J0 = in[2].typed_data<T>(),
          *rc = in[3].typed_data<T>();
#define SELFID_CF(NS, M) NS::ClosedFormBatch<T, M>(batch, n, S, st[0], St, st[1], J0, st[2], rc, st[3], out)
#define SELFID_CF_SWITCH(NS)        \
  switch (m) {                      \
    case 1: SELFID_CF(NS, 1); break; \
    case 2: SELFID_CF(NS, 2); break; \
    case 3: SELFID_CF(NS, 3); break; \
    case 4: SELFID_CF(NS, 4); break; \
    case 5: SELFID_CF(NS, 5); break; \
    default: SELFID_CF(NS, 6); break; \
  }
#ifdef SELFID_AVX2
  if (HasAvx2()) {
    SELFID_CF_SWITCH(avx2)
    return;
  }
#endif
  SELFID_CF_SWITCH(base)
#undef SELFID_CF_SWITCH
#undef SELFID_CF
}

ffi::Error ClosedFormImpl(ffi::AnyBuffer S_vv, ffi::AnyBuffer S_tv, ffi::AnyBuffer J0, ffi::AnyBuffer rcond,
                          ffi::Result<ffi::AnyBuffer> J) {
  auto dims = S_tv.dimensions();
  if (dims.size() < 2) return ffi::Error::InvalidArgument("S_tv: expected shape (..., n, m)");
  const int64_t n = dims[dims.size() - 2], m = dims[dims.size() - 1];
  if (m < 1 || m > kMaxM || n < 1 || n > kMaxN)
    return ffi::Error::InvalidArgument("S_tv: expected 1 <= m <= 6 and 1 <= n <= 64");
  const int64_t batch = static_cast<int64_t>(S_tv.element_count()) / (n * m);
  const ffi::AnyBuffer in[4] = {S_vv, S_tv, J0, rcond};
  const int64_t sizes[4] = {m * m, n * m, n * m, 1};
  int64_t st[4];
  for (int k = 0; k < 4; ++k) {
    if (in[k].element_type() != S_tv.element_type())
      return ffi::Error::InvalidArgument("closed form: every input must have S_tv's dtype");
    if (!Stride(in[k], sizes[k], batch, &st[k]))
      return ffi::Error::InvalidArgument("closed form: an input's size does not match the batch of S_tv");
  }
  if (static_cast<int64_t>(J->element_count()) != batch * n * m || J->element_type() != S_tv.element_type())
    return ffi::Error::InvalidArgument("closed form: the result must have S_tv's shape and dtype");
  switch (S_tv.element_type()) {
    case ffi::DataType::F32:
      ClosedFormTyped<float>(batch, n, m, in, st, J->typed_data<float>());
      return ffi::Error::Success();
    case ffi::DataType::F64:
      ClosedFormTyped<double>(batch, n, m, in, st, J->typed_data<double>());
      return ffi::Error::Success();
    default:
      return ffi::Error::InvalidArgument("closed form: float32 or float64 only");
  }
}

template <typename T>
void UpdateTyped(int64_t batch, int64_t n, int64_t m, const ffi::AnyBuffer* in, const int64_t* st,
                 ffi::Result<ffi::AnyBuffer>* out) {
#define SELFID_UPDATE_ARGS(NS)                                                                                 \
  NS::UpdateArgs<T> a;                                                                                         \
  a.sign_net = in[0].typed_data<T>();                                                                          \
  a.mag_sum = in[1].typed_data<T>();                                                                           \
  a.mag_count = in[2].typed_data<T>();                                                                         \
  a.S_vv = in[3].typed_data<T>();                                                                              \
  a.S_tv = in[4].typed_data<T>();                                                                              \
  a.s_tt = in[5].typed_data<T>();                                                                              \
  a.count = in[6].typed_data<int32_t>();                                                                       \
  a.rejected = in[7].typed_data<int32_t>();                                                                    \
  a.v_tol = in[8].typed_data<T>();                                                                             \
  a.forget = in[9].typed_data<T>();                                                                            \
  a.dtheta = in[10].typed_data<T>();                                                                           \
  a.V = in[11].typed_data<T>();                                                                                \
  for (int k = 0; k < 12; ++k) a.in_stride[k] = st[k];                                                        \
  a.o_sign_net = out[0]->typed_data<T>();                                                                      \
  a.o_mag_sum = out[1]->typed_data<T>();                                                                       \
  a.o_mag_count = out[2]->typed_data<T>();                                                                     \
  a.o_S_vv = out[3]->typed_data<T>();                                                                          \
  a.o_S_tv = out[4]->typed_data<T>();                                                                          \
  a.o_s_tt = out[5]->typed_data<T>();                                                                          \
  a.o_count = out[6]->typed_data<int32_t>();                                                                   \
  a.o_rejected = out[7]->typed_data<int32_t>();
#define SELFID_UPDATE_SWITCH(NS)                          \
  {                                                       \
    SELFID_UPDATE_ARGS(NS)                                \
    switch (m) {                                          \
      case 1: NS::UpdateBatch<T, 1>(batch, n, a); break;  \
      case 2: NS::UpdateBatch<T, 2>(batch, n, a); break;  \
      case 3: NS::UpdateBatch<T, 3>(batch, n, a); break;  \
      case 4: NS::UpdateBatch<T, 4>(batch, n, a); break;  \
      case 5: NS::UpdateBatch<T, 5>(batch, n, a); break;  \
      default: NS::UpdateBatch<T, 6>(batch, n, a); break; \
    }                                                     \
  }
#ifdef SELFID_AVX2
  if (HasAvx2()) {
    SELFID_UPDATE_SWITCH(avx2)
    return;
  }
#endif
  SELFID_UPDATE_SWITCH(base)
#undef SELFID_UPDATE_SWITCH
#undef SELFID_UPDATE_ARGS
}

ffi::Error UpdateImpl(ffi::AnyBuffer sign_net, ffi::AnyBuffer mag_sum, ffi::AnyBuffer mag_count, ffi::AnyBuffer S_vv,
                      ffi::AnyBuffer S_tv, ffi::AnyBuffer s_tt, ffi::AnyBuffer count, ffi::AnyBuffer rejected,
                      ffi::AnyBuffer v_tol, ffi::AnyBuffer forget, ffi::AnyBuffer dtheta, ffi::AnyBuffer V,
                      ffi::Result<ffi::AnyBuffer> o0, ffi::Result<ffi::AnyBuffer> o1, ffi::Result<ffi::AnyBuffer> o2,
                      ffi::Result<ffi::AnyBuffer> o3, ffi::Result<ffi::AnyBuffer> o4, ffi::Result<ffi::AnyBuffer> o5,
                      ffi::Result<ffi::AnyBuffer> o6, ffi::Result<ffi::AnyBuffer> o7) {
  auto dims = S_tv.dimensions();
  if (dims.size() < 2) return ffi::Error::InvalidArgument("S_tv: expected shape (..., n, m)");
  const int64_t n = dims[dims.size() - 2], m = dims[dims.size() - 1];
  if (m < 1 || m > kMaxM || n < 1 || n > kMaxN)
    return ffi::Error::InvalidArgument("S_tv: expected 1 <= m <= 6 and 1 <= n <= 64");
  const int64_t batch = static_cast<int64_t>(S_tv.element_count()) / (n * m);
  const ffi::AnyBuffer in[12] = {sign_net, mag_sum, mag_count, S_vv, S_tv, s_tt, count, rejected, v_tol, forget,
                                 dtheta, V};
  const int64_t sizes[12] = {n * m, n * m, m, m * m, n * m, 1, 1, 1, 1, 1, n, m};
  const ffi::DataType dtype = S_tv.element_type();
  int64_t st[12];
  for (int k = 0; k < 12; ++k) {
    const ffi::DataType want = (k == 6 || k == 7) ? ffi::DataType::S32 : dtype;
    if (in[k].element_type() != want)
      return ffi::Error::InvalidArgument("update: the sums, v_tol, forget and the sample must have S_tv's dtype, "
                                         "the counters int32");
    if (!Stride(in[k], sizes[k], batch, &st[k]))
      return ffi::Error::InvalidArgument("update: an input's size does not match the batch of S_tv");
  }
  ffi::Result<ffi::AnyBuffer> out[8] = {o0, o1, o2, o3, o4, o5, o6, o7};
  for (int k = 0; k < 8; ++k)
    if (static_cast<int64_t>(out[k]->element_count()) != sizes[k] * batch ||
        out[k]->element_type() != in[k].element_type())
      return ffi::Error::InvalidArgument("update: each result must have its input's per-estimator shape and dtype");
  switch (dtype) {
    case ffi::DataType::F32:
      UpdateTyped<float>(batch, n, m, in, st, out);
      return ffi::Error::Success();
    case ffi::DataType::F64:
      UpdateTyped<double>(batch, n, m, in, st, out);
      return ffi::Error::Success();
    default:
      return ffi::Error::InvalidArgument("update: float32 or float64 only");
  }
}

template <typename T>
void RecordTyped(int64_t batch, int64_t n, int64_t m, const ffi::AnyBuffer* in, const int64_t* st,
                 ffi::Result<ffi::AnyBuffer>* out) {
#define SELFID_RECORD_ARGS(NS)                            \
  NS::RecordArgs<T> a;                                    \
  a.J = in[0].typed_data<T>();                            \
  a.estimate = in[1].typed_data<T>();                     \
  a.last_deltas = in[2].typed_data<T>();                  \
  a.last_norms = in[3].typed_data<T>();                   \
  a.last_fresh = in[4].typed_data<bool>();                \
  a.count = in[5].typed_data<int32_t>();                  \
  a.recorded_count = in[6].typed_data<int32_t>();         \
  a.iteration = in[7].typed_data<int32_t>();              \
  a.converged_at = in[8].typed_data<int32_t>();           \
  a.eps = in[9].typed_data<T>();                          \
  a.eps_rel = in[10].typed_data<T>();                     \
  a.min_count = in[11].typed_data<int32_t>();             \
  for (int k = 0; k < 12; ++k) a.in_stride[k] = st[k];   \
  a.o_last_deltas = out[0]->typed_data<T>();              \
  a.o_last_norms = out[1]->typed_data<T>();               \
  a.o_last_fresh = out[2]->typed_data<bool>();            \
  a.o_recorded_count = out[3]->typed_data<int32_t>();     \
  a.o_iteration = out[4]->typed_data<int32_t>();          \
  a.o_converged_at = out[5]->typed_data<int32_t>();
#define SELFID_RECORD_SWITCH(NS)                          \
  {                                                       \
    SELFID_RECORD_ARGS(NS)                                \
    switch (m) {                                          \
      case 1: NS::RecordBatch<T, 1>(batch, n, a); break;  \
      case 2: NS::RecordBatch<T, 2>(batch, n, a); break;  \
      case 3: NS::RecordBatch<T, 3>(batch, n, a); break;  \
      case 4: NS::RecordBatch<T, 4>(batch, n, a); break;  \
      case 5: NS::RecordBatch<T, 5>(batch, n, a); break;  \
      default: NS::RecordBatch<T, 6>(batch, n, a); break; \
    }                                                     \
  }
#ifdef SELFID_AVX2
  if (HasAvx2()) {
    SELFID_RECORD_SWITCH(avx2)
    return;
  }
#endif
  SELFID_RECORD_SWITCH(base)
#undef SELFID_RECORD_SWITCH
#undef SELFID_RECORD_ARGS
}

ffi::Error RecordImpl(ffi::AnyBuffer J, ffi::AnyBuffer estimate, ffi::AnyBuffer last_deltas, ffi::AnyBuffer last_norms,
                      ffi::AnyBuffer last_fresh, ffi::AnyBuffer count, ffi::AnyBuffer recorded_count,
                      ffi::AnyBuffer iteration, ffi::AnyBuffer converged_at, ffi::AnyBuffer eps,
                      ffi::AnyBuffer eps_rel, ffi::AnyBuffer min_count, ffi::Result<ffi::AnyBuffer> o0,
                      ffi::Result<ffi::AnyBuffer> o1, ffi::Result<ffi::AnyBuffer> o2, ffi::Result<ffi::AnyBuffer> o3,
                      ffi::Result<ffi::AnyBuffer> o4, ffi::Result<ffi::AnyBuffer> o5) {
  auto dims = J.dimensions();
  if (dims.size() < 2) return ffi::Error::InvalidArgument("J: expected shape (..., n, m)");
  const int64_t n = dims[dims.size() - 2], m = dims[dims.size() - 1];
  if (m < 1 || m > kMaxM || n < 1 || n > kMaxN)
    return ffi::Error::InvalidArgument("J: expected 1 <= m <= 6 and 1 <= n <= 64");
  const int64_t batch = static_cast<int64_t>(J.element_count()) / (n * m);
  const ffi::AnyBuffer in[12] = {J, estimate, last_deltas, last_norms, last_fresh, count, recorded_count,
                                 iteration, converged_at, eps, eps_rel, min_count};
  const int64_t sizes[12] = {n * m, n * m, 2, 2, 2, 1, 1, 1, 1, 1, 1, 1};
  const ffi::DataType dtype = J.element_type();
  const ffi::DataType want[12] = {dtype, dtype, dtype, dtype, ffi::DataType::PRED, ffi::DataType::S32,
                                  ffi::DataType::S32, ffi::DataType::S32, ffi::DataType::S32, dtype, dtype,
                                  ffi::DataType::S32};
  int64_t st[12];
  for (int k = 0; k < 12; ++k) {
    if (in[k].element_type() != want[k])
      return ffi::Error::InvalidArgument("record: an input's dtype is not the state's");
    if (!Stride(in[k], sizes[k], batch, &st[k]))
      return ffi::Error::InvalidArgument("record: an input's size does not match the batch of J");
  }
  ffi::Result<ffi::AnyBuffer> out[6] = {o0, o1, o2, o3, o4, o5};
  const int64_t out_sizes[6] = {2, 2, 2, 1, 1, 1};
  const ffi::DataType out_types[6] = {dtype, dtype, ffi::DataType::PRED, ffi::DataType::S32, ffi::DataType::S32,
                                      ffi::DataType::S32};
  for (int k = 0; k < 6; ++k)
    if (static_cast<int64_t>(out[k]->element_count()) != out_sizes[k] * batch || out[k]->element_type() != out_types[k])
      return ffi::Error::InvalidArgument("record: a result's shape or dtype is not the state's");
  switch (dtype) {
    case ffi::DataType::F32:
      RecordTyped<float>(batch, n, m, in, st, out);
      return ffi::Error::Success();
    case ffi::DataType::F64:
      RecordTyped<double>(batch, n, m, in, st, out);
      return ffi::Error::Success();
    default:
      return ffi::Error::InvalidArgument("record: float32 or float64 only");
  }
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(SelfidClosedForm, ClosedFormImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(SelfidUpdate, UpdateImpl,
                              ffi::Ffi::Bind()
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
                                  .Ret<ffi::AnyBuffer>());
