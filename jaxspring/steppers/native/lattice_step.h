// Forward steps of one lattice member: the spring pass, the particle pass, whole steps,
// and the replay of a stored segment for the reverse pass.
#ifndef JAXSPRING_NATIVE_LATTICE_STEP_H_
#define JAXSPRING_NATIVE_LATTICE_STEP_H_

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "lattice.h"
#include "lattice_threads.h"
#include "spring_law.h"

namespace jaxspring::native {

// Force of springs k.. on their particle a (the one on b is minus it), into the three
// rows at out (components `width` apart), entries a..; with kKeep their 1 / length to
// inv[j] too (for the reverse pass), times valid[j]: zero for padding, whose reverse
// pass then yields zeros whatever the parameters.
template <typename T, bool kKeep>
void SpringRun(const T* x, const T* v, int64_t n, int64_t a, int64_t b, const T* rest, const T* ks, const T* kd,
               int64_t len, T* out, int64_t width, T* inv, const T* valid) {
  T* o0 = out;
  T* o1 = out + width;
  T* o2 = out + 2 * width;
  JAXSPRING_INDEPENDENT
  for (int64_t j = 0; j < len; ++j) {
    const Spring<T> g = SpringAt(x, v, n, a + j, b + j, rest[j]);
    const T m = Magnitude(g, ks[j], kd[j]);
    o0[j] = m * g.u0;
    o1[j] = m * g.u1;
    o2[j] = m * g.u2;
    if (kKeep) inv[j] = g.inv * valid[j];
  }
}

// out[c][j] (+)= sum over NF families of row_c(i) - row_c(i - shift), i = i0 + j, for
// each of `comps` components (out's rows kRun apart).
template <typename T, int NF, bool kInit>
void FamilyDifferences(const Rows<T>& rows, const int64_t* shifts, size_t first, int64_t i0, int64_t len, T* out) {
  for (int c = 0; c < rows.comps; ++c) {
    const T* here[NF];
    const T* there[NF];
    for (int f = 0; f < NF; ++f) {
      here[f] = rows.At(first + f) + c * rows.width + i0;
      there[f] = here[f] - shifts[first + f];
    }
    T* o = out + c * kRun;
    JAXSPRING_INDEPENDENT
    for (int64_t j = 0; j < len; ++j) {
      T sum = kInit ? T(0) : o[j];
      for (int f = 0; f < NF; ++f) sum = sum + here[f][j] - there[f][j];  // jaxspring/sim/forces.py's order
      o[j] = sum;
    }
  }
}

// out[c][j] = sum over all families of row_c(i0 + j) - row_c(i0 + j - shift): for the
// forward rows the spring force on particle i0 + j, for the reverse rows minus the
// springs' cotangent of its position and velocity.
template <typename T>
void Differences(const Layout& layout, const Rows<T>& rows, int64_t i0, int64_t len, T* out) {
  using Fn = void (*)(const Rows<T>&, const int64_t*, size_t, int64_t, int64_t, T*);
  static const Fn first[4] = {FamilyDifferences<T, 1, true>, FamilyDifferences<T, 2, true>,
                              FamilyDifferences<T, 3, true>, FamilyDifferences<T, 4, true>};
  static const Fn more[4] = {FamilyDifferences<T, 1, false>, FamilyDifferences<T, 2, false>,
                             FamilyDifferences<T, 3, false>, FamilyDifferences<T, 4, false>};
  const size_t families = layout.shift.size();
  for (size_t f = 0; f < families; f += 4) {
    const size_t count = std::min<size_t>(4, families - f);
    (f == 0 ? first : more)[count - 1](rows, layout.shift.data(), f, i0, len, out);
  }
}

// One particle's step from x, v to xo, vo (which may be x, v): adds drag, gravity and
// ground to its spring force (a0, a1, a2) and integrates, v' = free ? v + (dt F) / m : 0,
// x' = x + dt v'. Components are `stride` apart.
template <typename T, bool kDragOn, bool kGravityOn, bool kGroundOn>
inline void Integrate(const T* x, const T* v, T* xo, T* vo, int64_t stride, int64_t e, T a0, T a1, T a2, T m,
                      T free, T cdm, T kg, T kgd, T g0, T g1, T g2, T height, T dt) {
  const T w0 = v[e], w1 = v[stride + e], w2 = v[2 * stride + e];
  if (kDragOn) {
    const T c = -cdm * std::sqrt(w0 * w0 + w1 * w1 + w2 * w2);
    a0 += c * w0;
    a1 += c * w1;
    a2 += c * w2;
  }
  if (kGravityOn) {
    a0 += m * g0;
    a1 += m * g1;
    a2 += m * g2;
  }
  if (kGroundOn) {
    const T depth = height - x[stride + e];
    a1 += depth > 0 ? kg * depth - kgd * w1 : T(0);
  }
  const bool on = free != T(0);
  const T n0 = on ? w0 + dt * a0 / m : T(0), n1 = on ? w1 + dt * a1 / m : T(0), n2 = on ? w2 + dt * a2 / m : T(0);
  vo[e] = n0;
  vo[stride + e] = n1;
  vo[2 * stride + e] = n2;
  xo[e] = x[e] + dt * n0;
  xo[stride + e] = x[stride + e] + dt * n1;
  xo[2 * stride + e] = x[2 * stride + e] + dt * n2;
}

// `Integrate` over particles i0 .. i0 + len - 1 of one member, spring forces in force[3][kRun].
template <typename T, bool kDragOn, bool kGravityOn, bool kGroundOn>
void ParticleBlock(const Inputs<T>& p, const StepConstants<T>& k, const T* x, const T* v, T* xo, T* vo,
                   const T* force, int64_t n, int64_t i0, int64_t len) {
  JAXSPRING_INDEPENDENT
  for (int64_t j = 0; j < len; ++j) {
    const int64_t i = i0 + j;
    Integrate<T, kDragOn, kGravityOn, kGroundOn>(x, v, xo, vo, n, i, force[j], force[kRun + j], force[2 * kRun + j],
                                                 p.mass[i], p.free[i], p.cdm[i], p.kg[i], p.kgd[i], k.g0, k.g1, k.g2,
                                                 k.height, k.dt);
  }
}

template <typename T>
using ParticleBlockFn = void (*)(const Inputs<T>&, const StepConstants<T>&, const T*, const T*, T*, T*, const T*,
                                 int64_t, int64_t, int64_t);

template <typename T>
ParticleBlockFn<T> PickParticleBlock(const StepConstants<T>& k) {
  static const ParticleBlockFn<T> table[8] = {
      ParticleBlock<T, false, false, false>, ParticleBlock<T, true, false, false>, ParticleBlock<T, false, true, false>,
      ParticleBlock<T, true, true, false>,   ParticleBlock<T, false, false, true>, ParticleBlock<T, true, false, true>,
      ParticleBlock<T, false, true, true>,   ParticleBlock<T, true, true, true>};
  return table[(k.drag ? 1 : 0) + (k.gravity ? 2 : 0) + (k.ground ? 4 : 0)];
}

// One step of one member from (x, v) to (xo, vo) (the same arrays, or the next stored
// state); thread t of the team, blocks [lo, hi). `rows` holds 3 components.
template <typename T>
void Step(const Layout& layout, const Inputs<T>& p, const StepConstants<T>& k, const T* x, const T* v, T* xo, T* vo,
          Rows<T>& rows, Team& team, int64_t lo, int64_t hi, T* inv = nullptr, const T* valid = nullptr) {
  const int64_t n = layout.n;
  const auto spring_run = inv ? SpringRun<T, true> : SpringRun<T, false>;
  for (int64_t b = lo; b < hi; ++b) {
    for (const Run& run : layout.blocks[b]) {
      spring_run(x, v, n, run.a, run.a + layout.shift[run.family], p.rest + run.k, p.ks + run.k, p.kd + run.k,
                 run.len, rows.At(run.family) + run.a, rows.width, inv ? inv + run.k : nullptr,
                 inv ? valid + run.k : nullptr);
    }
  }
  team.Sync();
  const auto particles = PickParticleBlock(k);
  alignas(64) T force[3 * kRun];
  for (int64_t b = lo; b < hi; ++b) {
    const int64_t len = BlockLength(layout, b);
    Differences(layout, rows, b * kRun, len, force);
    particles(p, k, x, v, xo, vo, force, n, b * kRun, len);
  }
  team.Sync();
}

// `steps` steps of one member in place; thread t of the team. traj (ceil(steps /
// stride), 2, 3, n) or null: the state at the start of every stride-th step.
template <typename T>
void Simulate(const Layout& layout, const Inputs<T>& p, const Config& config, T* x, T* v, Rows<T>& rows, T* traj,
              Team& team, int t) {
  const int64_t n = layout.n;
  const StepConstants<T> k(p, config);
  int64_t lo, hi;
  Share(layout, t, team.size(), &lo, &hi);
  const int64_t first = lo * kRun, last = std::min(n, hi * kRun);  // the particles
  for (int64_t step = 0; step < config.steps; ++step) {
    if (traj && step % config.stride == 0) {
      T* state = traj + step / config.stride * 6 * n;
      for (int c = 0; c < 3; ++c) {
        std::copy(x + c * n + first, x + c * n + last, state + c * n + first);
        std::copy(v + c * n + first, v + c * n + last, state + (3 + c) * n + first);
      }
    }
    Step(layout, p, k, x, v, x, v, rows, team, lo, hi);
  }
}

// Re-runs segment `segment` (config.stride steps, fewer for the last) from its stored
// starting state, writing the starting state of each of its steps to `states` (and,
// unless invs is null, 1 / length of every padded spring at each but the last to invs).
template <typename T>
int64_t Replay(const Layout& layout, const Inputs<T>& p, const Config& config, const T* stored, int64_t segment,
               Rows<T>& rows, T* states, T* invs, const T* valid, Team& team, int t) {
  const int64_t n = layout.n;
  int64_t lo, hi;
  Share(layout, t, team.size(), &lo, &hi);
  const int64_t first = lo * kRun, last = std::min(n, hi * kRun);
  const int64_t length = std::min(config.stride, config.steps - segment * config.stride);
  const T* start = stored + segment * 6 * n;
  for (int c = 0; c < 6; ++c) std::copy(start + c * n + first, start + c * n + last, states + c * n + first);
  team.Sync();
  const StepConstants<T> k(p, config);
  for (int64_t step = 0; step + 1 < length; ++step) {
    const T* x = states + step * 6 * n;
    T* next = states + (step + 1) * 6 * n;
    Step(layout, p, k, x, x + 3 * n, next, next + 3 * n, rows, team, lo, hi,
         invs ? invs + step * layout.padded : static_cast<T*>(nullptr), valid);
  }
  return length;
}

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_LATTICE_STEP_H_
