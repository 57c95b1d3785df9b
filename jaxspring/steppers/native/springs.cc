// Spring forces and their reverse-mode derivative as XLA FFI custom calls (CPU).
//
// For spring s = (a, b): d = x_b - x_a, L = |d|, u = d / L (u = d where L = 0, as
// jaxspring's safe norm), e = L - L0, c = (v_b - v_a) . u, m = ks e + kd c,
// f = m u; force_a += f, force_b -= f. The backward kernel is the exact transpose
// of this map's derivative (see jaxspring/steppers/native_kernels.py for the formulas).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

template <typename T>
struct Geometry {
  T d[3], dv[3], u[3], inv, e, c, m;
};

template <typename T>
inline Geometry<T> geometry(const T* x, const T* v, int64_t a, int64_t b, T rest, T ks, T kd) {
  Geometry<T> g;
  T sq = 0;
  for (int k = 0; k < 3; ++k) {
    g.d[k] = x[3 * b + k] - x[3 * a + k];
    g.dv[k] = v[3 * b + k] - v[3 * a + k];
    sq += g.d[k] * g.d[k];
  }
  T length = sq > 0 ? std::sqrt(sq) : T(0);
  g.inv = length > 0 ? T(1) / length : T(1);
  g.c = 0;
  for (int k = 0; k < 3; ++k) {
    g.u[k] = g.d[k] * g.inv;
    g.c += g.dv[k] * g.u[k];
  }
  g.e = length - rest;
  g.m = ks * g.e + kd * g.c;
  return g;
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
  static const int64_t hardware = std::max(1u, std::thread::hardware_concurrency());  // a system call: once
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(hardware, springs / kSpringsPerThread)));
}

// Runs body(first, last, slot) over [0, springs) split into contiguous ranges, one per
// thread; slot 0 writes the caller's buffers, the others private ones summed afterwards.
template <typename Body>
void parallel_springs(int64_t springs, Body body) {
  const int threads = thread_count(springs);
  if (threads == 1) {
    body(0, springs, 0);
    return;
  }
  std::vector<std::thread> pool;
  const int64_t chunk = (springs + threads - 1) / threads;
  for (int t = 1; t < threads; ++t) {
    pool.emplace_back(body, t * chunk, std::min(springs, (t + 1) * chunk), t);
  }
  body(0, std::min(springs, chunk), 0);
  for (auto& thread : pool) thread.join();
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
      Geometry<T> g = geometry(xs, vs, a, b, r[s], k_s[ks_each ? s : 0], k_d[kd_each ? s : 0]);
      for (int k = 0; k < 3; ++k) {
        const T fk = g.m * g.u[k];
        f[3 * a + k] += fk;
        f[3 * b + k] -= fk;
      }
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
      Geometry<T> g = geometry(xs, vs, a, b, r[s], spring_ks, spring_kd);
      T cf[3], uc = 0;
      for (int k = 0; k < 3; ++k) {
        cf[k] = ct[3 * a + k] - ct[3 * b + k];
        uc += g.u[k] * cf[k];
      }
      const T ct_c = spring_kd * uc;  // m = ks e + kd c
      T ct_u[3], u_ct_u = 0;
      for (int k = 0; k < 3; ++k) {
        ct_u[k] = g.m * cf[k] + g.dv[k] * ct_c;  // from f = m u and c = dv . u
        u_ct_u += g.u[k] * ct_u[k];
      }
      const T ct_length = spring_ks * uc - g.inv * u_ct_u;  // u = d / L
      for (int k = 0; k < 3; ++k) {
        const T ct_d = g.inv * ct_u[k] + g.u[k] * ct_length;
        const T ct_dv = g.u[k] * ct_c;
        gx[3 * b + k] += ct_d;
        gx[3 * a + k] -= ct_d;
        gv[3 * b + k] += ct_dv;
        gv[3 * a + k] -= ct_dv;
      }
      gks[s] = g.e * uc;
      gkd[s] = g.c * uc;
      grest[s] = -spring_ks * uc;
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

}  // namespace

#define JAXSPRING_FORWARD(name, DT)                                                                   \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, Forward<DT>,                                                    \
                                ffi::Ffi::Bind()                                                      \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<ffi::S32>>()                                     \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>());

#define JAXSPRING_BACKWARD(name, DT)                                                                  \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, Backward<DT>,                                                   \
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
