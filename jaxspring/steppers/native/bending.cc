// The bending term's force and its reverse-mode derivative as XLA FFI custom calls (CPU).
//
// Bend triple (a, b, c): e1 = x_b - x_a, e2 = x_c - x_b, D = |e1| |e2| + e1 . e2, the
// curvature binormal kappa = 2 (e1 x e2) / D, u = kappa / |kappa| (0 at 0), and J^T c the
// gradient of c . kappa by the triple's 9 coordinates (jaxspring/sim/forces.py `Bending`).
// With A = J^T (kappa - kappa_0 u) (the gradient of (|kappa| - kappa_0)^2 / 2) and
// g = J^T u (the gradient of |kappa|), the force on the triple is
//     F = -(kb / l) A - (kbd / l) (g . V) g.
// Its reverse pass needs the transposed derivative of F by X. A and g are gradients of
// scalars, so their derivatives by X are symmetric (Hessians): H_A w and H_g w are the
// derivatives of A and g along w, which forward-mode dual numbers with two directions
// (the cotangent and V) give in one pass:
//     X' = -(kb / l) H_A F' - (kbd / l) [(g . F') H_g V + (g . V) H_g F']
//     V' = -(kbd / l) (g . F') g,  kb' = -(A . F') / l,  kbd' = -(g . V)(g . F') / l,
//     kappa_0' = (kb / l) (g . F'),  l' = -(F . F') / l.
// Inputs carry leading batch dimensions (vmap broadcasts every input): the kernels loop
// over them.
#include <algorithm>
#include <cmath>
#include <cstdint>

#include "support.h"
#include "xla/ffi/api/ffi.h"

namespace jaxspring::native {
namespace {

// A value with its derivatives along two directions (forward mode). The operators are
// hidden friends, so a float converts to a constant Dual where one meets the other.
template <typename T>
struct Dual {
  T v, a, b;
  Dual(T value = T(0), T da = T(0), T db = T(0)) : v(value), a(da), b(db) {}
  friend Dual operator+(Dual p, Dual q) { return {p.v + q.v, p.a + q.a, p.b + q.b}; }
  friend Dual operator-(Dual p, Dual q) { return {p.v - q.v, p.a - q.a, p.b - q.b}; }
  friend Dual operator-(Dual p) { return {-p.v, -p.a, -p.b}; }
  friend Dual operator*(Dual p, Dual q) { return {p.v * q.v, p.a * q.v + p.v * q.a, p.b * q.v + p.v * q.b}; }
  friend Dual Reciprocal(Dual p) {
    const T r = T(1) / p.v, d = -r * r;
    return {r, d * p.a, d * p.b};
  }
  friend Dual Sqrt(Dual p) {  // p.v > 0
    const T s = std::sqrt(p.v), d = T(0.5) / s;
    return {s, d * p.a, d * p.b};
  }
  friend T Value(Dual p) { return p.v; }
};

inline float Reciprocal(float p) { return 1.0f / p; }
inline double Reciprocal(double p) { return 1.0 / p; }
inline float Sqrt(float p) { return std::sqrt(p); }
inline double Sqrt(double p) { return std::sqrt(p); }
inline float Value(float p) { return p; }
inline double Value(double p) { return p; }

// S is the scalar (a float type or a Dual of one), T the float type underneath.
template <typename S>
struct Triple {
  S e1[3], e2[3], d1[3], d2[3];  // edges; dD / de1 and dD / de2
  S two_over;                    // 2 / D (0 where the triple is degenerate)
  S kappa[3], u[3];
};

template <typename S>
inline void Cross(const S* p, const S* q, S* out) {
  out[0] = p[1] * q[2] - p[2] * q[1];
  out[1] = p[2] * q[0] - p[0] * q[2];
  out[2] = p[0] * q[1] - p[1] * q[0];
}

template <typename S>
inline S Dot3(const S* p, const S* q) {
  return p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
}

// The curvature of the triple with coordinates x[0..9) (a, b, c), as forces.py's
// `_bend_geometry`: degenerate triples (an edge of length 0, or folded back, D = 0)
// have kappa = 0 and J = 0.
template <typename S>
inline Triple<S> Measure(const S* x) {
  Triple<S> t;
  for (int k = 0; k < 3; ++k) {
    t.e1[k] = x[3 + k] - x[k];
    t.e2[k] = x[6 + k] - x[3 + k];
  }
  const S s1 = Dot3(t.e1, t.e1), s2 = Dot3(t.e2, t.e2);
  const S zero(0);
  S n1 = zero, n2 = zero;
  if (Value(s1) > 0) n1 = Sqrt(s1);
  if (Value(s2) > 0) n2 = Sqrt(s2);
  const S denominator = n1 * n2 + Dot3(t.e1, t.e2);
  const bool usable = Value(denominator) > 0 && Value(n1) > 0 && Value(n2) > 0;
  t.two_over = usable ? S(2) * Reciprocal(denominator) : zero;
  const S ratio = usable ? n2 * Reciprocal(n1) : zero;          // |e2| / |e1|
  const S inverse = usable ? n1 * Reciprocal(n2) : zero;        // |e1| / |e2|
  S w[3];
  Cross(t.e1, t.e2, w);
  for (int k = 0; k < 3; ++k) {
    t.d1[k] = ratio * t.e1[k] + t.e2[k];
    t.d2[k] = inverse * t.e2[k] + t.e1[k];
    t.kappa[k] = t.two_over * w[k];
  }
  const S squared = Dot3(t.kappa, t.kappa);
  const S over = Value(squared) > 0 ? Reciprocal(Sqrt(squared)) : zero;
  for (int k = 0; k < 3; ++k) t.u[k] = t.kappa[k] * over;
  return t;
}

// J^T c: the gradient of c . kappa by the triple's coordinates, out[0..9) (a, b, c).
template <typename S>
inline void Transpose(const Triple<S>& t, const S* c, S* out) {
  const S scale = S(0.5) * t.two_over * Dot3(c, t.kappa);
  S p[3], q[3];
  Cross(t.e2, c, p);
  Cross(c, t.e1, q);
  for (int k = 0; k < 3; ++k) {
    const S g1 = t.two_over * p[k] - scale * t.d1[k];  // d(c . kappa) / de1
    const S g2 = t.two_over * q[k] - scale * t.d2[k];
    out[k] = -g1;
    out[3 + k] = g1 - g2;
    out[6 + k] = g2;
  }
}


// The triple's 9 coordinates of a (particle, component) array.
template <typename T>
inline void Gather(const T* x, const int32_t* triple, T* out) {
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) out[3 * j + k] = x[3 * triple[j] + k];
}

template <typename T>
inline void Scatter(const T* local, const int32_t* triple, T* out) {
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k) out[3 * triple[j] + k] += local[3 * j + k];
}

// The buffers of one call, batch element by batch element (every input has the same
// leading batch dimensions; kb and kbd hold one value or one per triple).
template <ffi::DataType DT>
struct Batch {
  using T = ffi::NativeType<DT>;
  int64_t batch, particles, triples, kb_count, kbd_count;

  Batch(const ffi::Buffer<DT>& x, const ffi::Buffer<DT>& length, const ffi::Buffer<DT>& kb,
        const ffi::Buffer<DT>& kbd) {
    const auto dims = x.dimensions();
    particles = dims.size() >= 2 ? dims[dims.size() - 2] : 0;
    batch = particles > 0 ? x.element_count() / (3 * particles) : 0;
    triples = batch > 0 ? length.element_count() / batch : 0;
    kb_count = batch > 0 ? kb.element_count() / batch : 0;
    kbd_count = batch > 0 ? kbd.element_count() / batch : 0;
  }
};

template <ffi::DataType DT>
ffi::Error Forward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> bends, ffi::Buffer<DT> length,
                   ffi::Buffer<DT> kappa0, ffi::Buffer<DT> kb, ffi::Buffer<DT> kbd, ffi::ResultBuffer<DT> force) {
  using T = ffi::NativeType<DT>;
  const Batch<DT> shape(x, length, kb, kbd);
  T* out = force->typed_data();
  std::fill(out, out + x.element_count(), T(0));
  const int64_t n3 = 3 * shape.particles, nb = shape.triples;
  for (int64_t r = 0; r < shape.batch; ++r) {
    const T* xs = x.typed_data() + r * n3;
    const T* vs = v.typed_data() + r * n3;
    const int32_t* triple = bends.typed_data() + r * 3 * nb;
    const T* l = length.typed_data() + r * nb;
    const T* k0 = kappa0.typed_data() + r * nb;
    const T* k_b = kb.typed_data() + r * shape.kb_count;
    const T* k_d = kbd.typed_data() + r * shape.kbd_count;
    T* f = out + r * n3;
    for (int64_t i = 0; i < nb; ++i) {
      T X[9], V[9], A[9], G[9], F[9], c[3];
      Gather(xs, triple + 3 * i, X);
      Gather(vs, triple + 3 * i, V);
      const Triple<T> t = Measure(X);
      for (int k = 0; k < 3; ++k) c[k] = t.kappa[k] - k0[i] * t.u[k];
      Transpose(t, c, A);
      Transpose(t, t.u, G);
      T rate = 0;
      for (int j = 0; j < 9; ++j) rate += G[j] * V[j];
      const T stiff = k_b[shape.kb_count > 1 ? i : 0] / l[i], damp = k_d[shape.kbd_count > 1 ? i : 0] / l[i];
      for (int j = 0; j < 9; ++j) F[j] = -stiff * A[j] - damp * rate * G[j];
      Scatter(F, triple + 3 * i, f);
    }
  }
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error Backward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> bends, ffi::Buffer<DT> length,
                    ffi::Buffer<DT> kappa0, ffi::Buffer<DT> kb, ffi::Buffer<DT> kbd, ffi::Buffer<DT> cotangent,
                    ffi::ResultBuffer<DT> ct_x, ffi::ResultBuffer<DT> ct_v, ffi::ResultBuffer<DT> ct_length,
                    ffi::ResultBuffer<DT> ct_kappa0, ffi::ResultBuffer<DT> ct_kb, ffi::ResultBuffer<DT> ct_kbd) {
  using T = ffi::NativeType<DT>;
  using D = Dual<T>;
  const Batch<DT> shape(x, length, kb, kbd);
  std::fill(ct_x->typed_data(), ct_x->typed_data() + x.element_count(), T(0));
  std::fill(ct_v->typed_data(), ct_v->typed_data() + x.element_count(), T(0));
  std::fill(ct_kb->typed_data(), ct_kb->typed_data() + kb.element_count(), T(0));
  std::fill(ct_kbd->typed_data(), ct_kbd->typed_data() + kbd.element_count(), T(0));
  const int64_t n3 = 3 * shape.particles, nb = shape.triples;
  for (int64_t r = 0; r < shape.batch; ++r) {
    const T* xs = x.typed_data() + r * n3;
    const T* vs = v.typed_data() + r * n3;
    const T* cs = cotangent.typed_data() + r * n3;
    const int32_t* triple = bends.typed_data() + r * 3 * nb;
    const T* l = length.typed_data() + r * nb;
    const T* k0 = kappa0.typed_data() + r * nb;
    const bool kb_each = shape.kb_count > 1, kbd_each = shape.kbd_count > 1;
    const T* k_b = kb.typed_data() + r * shape.kb_count;
    const T* k_d = kbd.typed_data() + r * shape.kbd_count;
    T* gx = ct_x->typed_data() + r * n3;
    T* gv = ct_v->typed_data() + r * n3;
    T* gl = ct_length->typed_data() + r * nb;
    T* gk0 = ct_kappa0->typed_data() + r * nb;
    T* gkb = ct_kb->typed_data() + r * shape.kb_count;
    T* gkd = ct_kbd->typed_data() + r * shape.kbd_count;
    for (int64_t i = 0; i < nb; ++i) {
      T X[9], V[9], C[9];
      Gather(xs, triple + 3 * i, X);
      Gather(vs, triple + 3 * i, V);
      Gather(cs, triple + 3 * i, C);
      D Xd[9], c[3], A[9], G[9];
      for (int j = 0; j < 9; ++j) Xd[j] = D(X[j], C[j], V[j]);  // directions: the cotangent, V
      const Triple<D> t = Measure(Xd);
      for (int k = 0; k < 3; ++k) c[k] = t.kappa[k] - D(k0[i]) * t.u[k];
      Transpose(t, c, A);
      Transpose(t, t.u, G);
      T rate = 0, along = 0, work = 0;  // g . V, g . F', A . F'
      for (int j = 0; j < 9; ++j) {
        rate += G[j].v * V[j];
        along += G[j].v * C[j];
        work += A[j].v * C[j];
      }
      const T stiffness = k_b[kb_each ? i : 0], damping = k_d[kbd_each ? i : 0];
      const T stiff = stiffness / l[i], damp = damping / l[i];
      T local_x[9], local_v[9];
      for (int j = 0; j < 9; ++j) {
        local_x[j] = -stiff * A[j].a - damp * (along * G[j].b + rate * G[j].a);
        local_v[j] = -damp * along * G[j].v;
      }
      Scatter(local_x, triple + 3 * i, gx);
      Scatter(local_v, triple + 3 * i, gv);
      const T force_work = -stiff * work - damp * rate * along;  // F . F'
      gl[i] = -force_work / l[i];
      gk0[i] = stiff * along;
      gkb[kb_each ? i : 0] += -work / l[i];
      gkd[kbd_each ? i : 0] += -rate * along / l[i];
    }
  }
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error GuardedForward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> bends, ffi::Buffer<DT> length,
                          ffi::Buffer<DT> kappa0, ffi::Buffer<DT> kb, ffi::Buffer<DT> kbd,
                          ffi::ResultBuffer<DT> force) {
  return Guarded("bending", [&] { return Forward<DT>(x, v, bends, length, kappa0, kb, kbd, force); });
}

template <ffi::DataType DT>
ffi::Error GuardedBackward(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<ffi::S32> bends,
                           ffi::Buffer<DT> length, ffi::Buffer<DT> kappa0, ffi::Buffer<DT> kb, ffi::Buffer<DT> kbd,
                           ffi::Buffer<DT> cotangent, ffi::ResultBuffer<DT> ct_x, ffi::ResultBuffer<DT> ct_v,
                           ffi::ResultBuffer<DT> ct_length, ffi::ResultBuffer<DT> ct_kappa0,
                           ffi::ResultBuffer<DT> ct_kb, ffi::ResultBuffer<DT> ct_kbd) {
  return Guarded("bending backward", [&] {
    return Backward<DT>(x, v, bends, length, kappa0, kb, kbd, cotangent, ct_x, ct_v, ct_length, ct_kappa0, ct_kb,
                        ct_kbd);
  });
}

}  // namespace
}  // namespace jaxspring::native

namespace ffi = xla::ffi;

#define JAXSPRING_BENDING(name, DT)                                                                   \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, jaxspring::native::GuardedForward<DT>,                          \
                                ffi::Ffi::Bind()                                                      \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<ffi::S32>>()                                     \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>());

#define JAXSPRING_BENDING_BACKWARD(name, DT)                                                          \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, jaxspring::native::GuardedBackward<DT>,                         \
                                ffi::Ffi::Bind()                                                      \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<ffi::S32>>()                                     \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Arg<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>()                                           \
                                    .Ret<ffi::Buffer<DT>>());

JAXSPRING_BENDING(JaxspringBendingF32, ffi::F32)
JAXSPRING_BENDING(JaxspringBendingF64, ffi::F64)
JAXSPRING_BENDING_BACKWARD(JaxspringBendingBackwardF32, ffi::F32)
JAXSPRING_BENDING_BACKWARD(JaxspringBendingBackwardF64, ffi::F64)
