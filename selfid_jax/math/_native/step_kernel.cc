// The step's XLA FFI handler: update, Eq. 13, Eq. 14 and record in one pass over a batch of estimators
// (selfid_jax.identify.step calls it through selfid_jax.math.native). Its own translation unit: it inlines every
// function it calls (GCC's flatten), the largest part of the library's build, which setup.py runs beside
// estimator_kernels.cc's.
#include "estimator_kernels.h"

#ifdef SELFID_KERNELS
namespace {
SELFID_TYPED(Step)
SELFID_IMPL(Step, kStep)
}  // namespace

SELFID_HANDLER(SelfidStep, StepImpl)
#endif  // SELFID_KERNELS
