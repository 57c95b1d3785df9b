// Spring forces and their reverse-mode derivative as XLA FFI custom calls (CPU).
//
// For spring s = (a, b): d = x_b - x_a, L = |d|, u = d / L (u = d where L = 0, as
// jaxspring's safe norm), e = L - L0, c = (v_b - v_a) . u, m = ks e + kd c,
// f = m u; force_a += f, force_b -= f. The backward kernel is the exact transpose
// of this map's derivative. Both take the law and its adjoint from spring_law.h.
#include <algorithm>
#include <cstdint>
#include <exception>
#include <thread>
#include <vector>

#include "spring_law.h"
#include "support.h"
#include "xla/ffi/api/ffi.h"

namespace jaxspring::native {
namespace {

// Spring s of the (particle, component) arrays x and v (positions, velocities), a, b
// its ends.
template <typename T>
inline Spring<T> MeasureAt(const T* x, const T* v, int64_t a, int64_t b, T rest) {
  return Measure(x[3 * b] - x[3 * a], x[3 * b + 1] - x[3 * a + 1], x[3 * b + 2] - x[3 * a + 2], v[3 * b] - v[3 * a],
                 v[3 * b + 1] - v[3 * a + 1], v[3 * b + 2] - v[3 * a + 2], rest);
}

// The i-th spring of [first, last) in processing order: the even ones, then the odd
// ones. In a chain or lattice neighbouring springs share a particle; alternating keeps
// consecutive force updates independent.
inline int64_t spring_at(int64_t i, int64_t first, int64_t last) {
  const int64_t half = (last - first + 1) / 2;
  return first + (i < half ? 2 * i : 2 * (i - half) + 1);
}

// Springs per thread below which one thread is faster than starting a second one.
constexpr int64_t kSpringsPerThread = 50000;

inline int thread_count(int64_t springs) {
  if (springs < 2 * kSpringsPerThread) return 1;
  const int64_t usable = UsableThreads();
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(usable, springs / kSpringsPerThread)));
}

// Runs body(first, last, slot) over [0, springs) split into contiguous ranges, one per
// thread; slot 0 writes the caller's buffers, the others private ones summed afterwards.
// An exception (a thread that cannot start, or one thrown by body) is rethrown once
// every thread started has ended.
template <typename Body>
void parallel_springs(int64_t springs, Body body) {
  const int threads = thread_count(springs);
  if (threads == 1) {
    body(0, springs, 0);
    return;
  }
  std::vector<std::exception_ptr> failures(threads);
  auto guarded = [&](int64_t first, int64_t last, int slot) {
    try {
      body(first, last, slot);
    } catch (...) {
      failures[slot] = std::current_exception();
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  const int64_t chunk = (springs + threads - 1) / threads;
  try {
    for (int t = 1; t < threads; ++t) {
      pool.emplace_back(guarded, t * chunk, std::min(springs, (t + 1) * chunk), t);
    }
    guarded(0, std::min(springs, chunk), 0);
  } catch (...) {
    failures[0] = std::current_exception();
  }
  for (auto& thread : pool) thread.join();
  for (const auto& failure : failures) {
    if (failure) std::rethrow_exception(failure);
  }
}

template <ffi::DataType DT>
ffi::Error Forward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> pairs, ffi::Buffer<DT> rest,
                   ffi::Buffer<DT> ks, ffi::Buffer<DT> kd, ffi::ResultBuffer<DT> force) {
  using T = ffi::NativeType<DT>;
  const int64_t n = x.element_count(), springs = rest.element_count();
  const T* xs = x.typed_data();
  const T* vs = v.typed_data();
  const int32_t* p = pairs.typed_data();
  const T* r = rest.typed_data();
  const T* k_s = ks.typed_data();
  const T* k_d = kd.typed_data();
  const bool ks_each = ks.element_count() > 1, kd_each = kd.element_count() > 1;
  const int threads = thread_count(springs);
  std::vector<std::vector<T>> extra(threads - 1, std::vector<T>(n, T(0)));
  T* out = force->typed_data();
  std::fill(out, out + n, T(0));
  parallel_springs(springs, [&](int64_t first, int64_t last, int slot) {
    T* f = slot == 0 ? out : extra[slot - 1].data();
    for (int64_t i = 0; i < last - first; ++i) {
      const int64_t s = spring_at(i, first, last);
      const int64_t a = p[2 * s], b = p[2 * s + 1];
      const Spring<T> g = MeasureAt(xs, vs, a, b, r[s]);
      const T m = Magnitude(g, k_s[ks_each ? s : 0], k_d[kd_each ? s : 0]);
      const T f0 = m * g.u0, f1 = m * g.u1, f2 = m * g.u2;
      f[3 * a] += f0;
      f[3 * a + 1] += f1;
      f[3 * a + 2] += f2;
      f[3 * b] -= f0;
      f[3 * b + 1] -= f1;
      f[3 * b + 2] -= f2;
    }
  });
  for (const auto& buffer : extra)
    for (int64_t i = 0; i < n; ++i) out[i] += buffer[i];
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error Backward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> pairs, ffi::Buffer<DT> rest,
                    ffi::Buffer<DT> ks, ffi::Buffer<DT> kd, ffi::Buffer<DT> cotangent, ffi::ResultBuffer<DT> ct_x,
                    ffi::ResultBuffer<DT> ct_v, ffi::ResultBuffer<DT> ct_ks, ffi::ResultBuffer<DT> ct_kd,
                    ffi::ResultBuffer<DT> ct_rest) {
  using T = ffi::NativeType<DT>;
  const int64_t n = x.element_count(), springs = rest.element_count();
  const T* xs = x.typed_data();
  const T* vs = v.typed_data();
  const T* ct = cotangent.typed_data();
  const int32_t* p = pairs.typed_data();
  const T* r = rest.typed_data();
  const T* k_s = ks.typed_data();
  const T* k_d = kd.typed_data();
  const bool ks_each = ks.element_count() > 1, kd_each = kd.element_count() > 1;
  T* out_x = ct_x->typed_data();
  T* out_v = ct_v->typed_data();
  T* gks = ct_ks->typed_data();
  T* gkd = ct_kd->typed_data();
  T* grest = ct_rest->typed_data();
  const int threads = thread_count(springs);
  std::vector<std::vector<T>> extra_x(threads - 1, std::vector<T>(n, T(0)));
  std::vector<std::vector<T>> extra_v(threads - 1, std::vector<T>(n, T(0)));
  std::fill(out_x, out_x + n, T(0));
  std::fill(out_v, out_v + n, T(0));
  parallel_springs(springs, [&](int64_t first, int64_t last, int slot) {
    T* gx = slot == 0 ? out_x : extra_x[slot - 1].data();
    T* gv = slot == 0 ? out_v : extra_v[slot - 1].data();
    for (int64_t i = 0; i < last - first; ++i) {
      const int64_t s = spring_at(i, first, last);
      const int64_t a = p[2 * s], b = p[2 * s + 1];
      const T spring_ks = k_s[ks_each ? s : 0], spring_kd = k_d[kd_each ? s : 0];
      const Spring<T> g = MeasureAt(xs, vs, a, b, r[s]);
      const T c0 = ct[3 * a] - ct[3 * b], c1 = ct[3 * a + 1] - ct[3 * b + 1], c2 = ct[3 * a + 2] - ct[3 * b + 2];
      const SpringCotangent<T> c =
          Adjoint(g, spring_ks, spring_kd, Magnitude(g, spring_ks, spring_kd), Along(g, c0, c1, c2), c0, c1, c2);
      const T dd[3] = {c.d0, c.d1, c.d2}, dw[3] = {c.w0, c.w1, c.w2};
      for (int k = 0; k < 3; ++k) {
        gx[3 * b + k] += dd[k];
        gx[3 * a + k] -= dd[k];
        gv[3 * b + k] += dw[k];
        gv[3 * a + k] -= dw[k];
      }
      gks[s] = c.ks;
      gkd[s] = c.kd;
      grest[s] = c.rest;
    }
  });
  for (int t = 0; t < threads - 1; ++t) {
    for (int64_t i = 0; i < n; ++i) {
      out_x[i] += extra_x[t][i];
      out_v[i] += extra_v[t][i];
    }
  }
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error GuardedForward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> pairs, ffi::Buffer<DT> rest,
                          ffi::Buffer<DT> ks, ffi::Buffer<DT> kd, ffi::ResultBuffer<DT> force) {
  return Guarded("springs", [&] { return Forward<DT>(x, v, pairs, rest, ks, kd, force); });
}

template <ffi::DataType DT>
ffi::Error GuardedBackward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> pairs, ffi::Buffer<DT> rest,
                           ffi::Buffer<DT> ks, ffi::Buffer<DT> kd, ffi::Buffer<DT> cotangent,
                           ffi::ResultBuffer<DT> ct_x, ffi::ResultBuffer<DT> ct_v, ffi::ResultBuffer<DT> ct_ks,
                           ffi::ResultBuffer<DT> ct_kd, ffi::ResultBuffer<DT> ct_rest) {
  return Guarded("springs backward", [&] {
    return Backward<DT>(x, v, pairs, rest, ks, kd, cotangent, ct_x, ct_v, ct_ks, ct_kd, ct_rest);
  });
}

}  // namespace
}  // namespace jaxspring::native

namespace ffi = xla::ffi;
using jaxspring::native::GuardedBackward;
using jaxspring::native::GuardedForward;

#define JAXSPRING_FORWARD(name, DT)                                                                   \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, GuardedForward<DT>,                                                 \
                                ffi::Ffi::Bind()                                                      \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<ffi::S32>>()                                     \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>());

#define JAXSPRING_BACKWARD(name, DT)                                                                  \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, GuardedBackward<DT>,                                                \
                                ffi::Ffi::Bind()                                                      \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<ffi::S32>>()                                     \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>());

JAXSPRING_FORWARD(JaxspringSpringsF32, ffi::F32)
JAXSPRING_FORWARD(JaxspringSpringsF64, ffi::F64)
JAXSPRING_BACKWARD(JaxspringSpringsBackwardF32, ffi::F32)
JAXSPRING_BACKWARD(JaxspringSpringsBackwardF64, ffi::F64)
