// The spring law and its adjoint, written once for every native kernel.
//
// For a spring from particle a to particle b: d = x_b - x_a, w = v_b - v_a, L = |d|,
// u = d / L (u = d where L = 0, as jaxspring's safe norm), extension e = L - L0,
// closing speed c = w . u, magnitude m = ks e + kd c; the force on a is f = m u, and
// -f on b.
//
// The adjoint (reverse mode; the formulas of jaxspring/steppers/native_kernels.py):
// given the cotangent cf of the force on a minus that on b (cf = ct_a - ct_b),
//   uc = u . cf,  cc = kd uc (the cotangent of c),
//   cl = ks uc - (m uc + c cc) / L (of L; u . (m cf + w cc) = m uc + c cc),
//   ct_d = (m cf + cc w) / L + cl u,  ct_w = cc u,
//   ct_ks = e uc,  ct_kd = c uc,  ct_L0 = -ks uc,
// ct_d and ct_w going + on b and - on a.
//
// Every function takes V = a floating-point scalar or a GCC / Clang vector of them (one
// spring a lane), and K (ks, kd) = V or its scalar (one value for every lane). Masks
// (padding springs, lanes already counted) are products, applied by the callers to m and
// uc: a vector conditional is not offered by every compiler.
#ifndef JAXSPRING_NATIVE_SPRING_LAW_H_
#define JAXSPRING_NATIVE_SPRING_LAW_H_

#include <cmath>
#include <type_traits>

namespace jaxspring::native {

// One spring's state (or one per lane).
template <typename V>
struct Spring {
  V u0, u1, u2;  // direction d / L (d itself at L = 0)
  V w0, w1, w2;  // relative velocity v_b - v_a
  V inv;         // 1 / L (1 at L = 0)
  V e;           // extension L - L0
  V closing;     // closing speed w . u
};

// 1 / length, 1 at length 0 (a length is never negative).
template <typename V>
inline V SafeInverse(V length) {
  if constexpr (std::is_arithmetic_v<V>) {
    return V(1) / (length > 0 ? length : V(1));
  } else {
    // (length == 0) is -1 in the lanes where it holds, 0 elsewhere
    using E = std::remove_reference_t<decltype(length[0])>;
    return E(1) / (length - __builtin_convertvector(length == 0, V));
  }
}

template <typename V>
inline V SquareRoot(V value) {
  if constexpr (std::is_arithmetic_v<V>) {
    return std::sqrt(value);
  } else {
    V root;
    for (int l = 0; l < static_cast<int>(sizeof(V) / sizeof(value[0])); ++l) root[l] = std::sqrt(value[l]);
    return root;
  }
}

// The spring with d = (d0, d1, d2) and w = (w0, w1, w2), its length computed.
template <typename V>
inline Spring<V> Measure(V d0, V d1, V d2, V w0, V w1, V w2, V rest) {
  const V length = SquareRoot(d0 * d0 + d1 * d1 + d2 * d2);
  Spring<V> s;
  s.w0 = w0;
  s.w1 = w1;
  s.w2 = w2;
  s.inv = SafeInverse(length);
  s.u0 = d0 * s.inv;
  s.u1 = d1 * s.inv;
  s.u2 = d2 * s.inv;
  s.e = length - rest;
  s.closing = w0 * s.u0 + w1 * s.u1 + w2 * s.u2;
  return s;
}

// The same with 1 / length known (kept from an earlier pass: no square root, no
// division), length = |d|^2 inv. An inv of 0 (padding) makes u, e and c zero.
template <typename V>
inline Spring<V> MeasureKnown(V d0, V d1, V d2, V w0, V w1, V w2, V rest, V inv) {
  Spring<V> s;
  s.w0 = w0;
  s.w1 = w1;
  s.w2 = w2;
  s.inv = inv;
  s.u0 = d0 * inv;
  s.u1 = d1 * inv;
  s.u2 = d2 * inv;
  s.e = (d0 * d0 + d1 * d1 + d2 * d2) * inv - rest;
  s.closing = w0 * s.u0 + w1 * s.u1 + w2 * s.u2;
  return s;
}

// m = ks e + kd c: the force on a is m u.
template <typename V, typename K>
inline V Magnitude(const Spring<V>& s, K ks, K kd) {
  return ks * s.e + kd * s.closing;
}

// uc = u . cf, cf = (c0, c1, c2) the cotangent of the force on a minus that on b.
template <typename V>
inline V Along(const Spring<V>& s, V c0, V c1, V c2) {
  return s.u0 * c0 + s.u1 * c1 + s.u2 * c2;
}

// The cotangents of one spring's inputs.
template <typename V>
struct SpringCotangent {
  V d0, d1, d2;  // of d (+ on b, - on a)
  V w0, w1, w2;  // of w (+ on b, - on a)
  V ks, kd;      // of ks, kd
  V rest;        // of L0
};

// The adjoint of f = m u, from cf = (c0, c1, c2), m = Magnitude(s, ks, kd) and uc =
// Along(s, c0, c1, c2) (either masked by the caller).
template <typename V, typename K>
inline SpringCotangent<V> Adjoint(const Spring<V>& s, K ks, K kd, V m, V uc, V c0, V c1, V c2) {
  const V cc = kd * uc;
  const V cl = ks * uc - s.inv * (m * uc + s.closing * cc);
  const V p = s.inv * m, q = s.inv * cc;
  SpringCotangent<V> ct;
  ct.d0 = p * c0 + q * s.w0 + cl * s.u0;
  ct.d1 = p * c1 + q * s.w1 + cl * s.u1;
  ct.d2 = p * c2 + q * s.w2 + cl * s.u2;
  ct.w0 = s.u0 * cc;
  ct.w1 = s.u1 * cc;
  ct.w2 = s.u2 * cc;
  ct.ks = s.e * uc;
  ct.kd = s.closing * uc;
  ct.rest = -(ks * uc);
  return ct;
}

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_SPRING_LAW_H_
