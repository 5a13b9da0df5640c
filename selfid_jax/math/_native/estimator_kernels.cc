// XLA FFI handlers for the CPU backend: the estimator's per-sample update and Eq. 14's closed form from the
// statistics, each over a batch of estimators in one call (selfid_jax.math.native registers and calls them).
//
// XLA's CPU code generator runs a vmapped estimator one scalar at a time; these kernels run the same operations
// on 8 float32 (4 float64) estimators per instruction. The arithmetic is estimator_kernels.inc, compiled for x86-64
// with AVX2 and FMA: SelfidKernelsSupported() says whether this CPU has them (selfid_jax.math.native registers the
// handlers only then). On another CPU or compiler the library holds no kernels and the pure-JAX functions run.
//
// This file holds the update, closed-form and record handlers; step_kernel.cc the step's (setup.py compiles the
// two side by side).
#include "estimator_kernels.h"

#ifdef SELFID_KERNELS
namespace {
SELFID_TYPED(ClosedForm)
SELFID_TYPED(Update)
SELFID_TYPED(Record)
SELFID_IMPL(ClosedForm, kClosedForm)
SELFID_IMPL(Update, kUpdate)
SELFID_IMPL(Record, kRecord)
}  // namespace

SELFID_HANDLER(SelfidClosedForm, ClosedFormImpl)
SELFID_HANDLER(SelfidUpdate, UpdateImpl)
SELFID_HANDLER(SelfidRecord, RecordImpl)
#endif  // SELFID_KERNELS

// The handlers' argument lists' version: selfid_jax.math.native refuses a library built from other sources (an
// editable checkout pulled without a rebuild) instead of calling it with arguments it does not take.
extern "C" int SelfidKernelsAbi() { return 3; }

// Whether this library holds the kernels and this CPU runs them (x86-64 with AVX2 and FMA).
extern "C" int SelfidKernelsSupported() {
#ifdef SELFID_KERNELS
  return HasAvx2() ? 1 : 0;
#else
  return 0;
#endif
}
