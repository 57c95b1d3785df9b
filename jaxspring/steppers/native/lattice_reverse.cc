// The reverse pass of one lattice member: the reverse particle pass, the reverse spring
// pass (spring_law.h's adjoint, per spring, or lean in vectors), over replayed
// segments, on one team or pipelined with a second thread's replays.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <exception>

#include "lattice.h"
#include "lattice_reverse.h"
#include "lattice_step.h"
#include "lattice_threads.h"
#include "spring_law.h"

namespace jaxspring::native {
namespace {

// Reverse of `ParticleBlock` over particles i0 .. i0 + len - 1: adds the springs' part
// of the step after (-springs[6][kRun]: x then v) to the cotangents of x', v' in out.x,
// out.v, then writes those of x, v through the integrator, drag, gravity and ground
// (the springs' part of this step follows in the next particle pass) and the cotangent
// of the force to gf.
template <typename T, bool kDragOn, bool kGravityOn, bool kGroundOn, bool kMass>
void ReverseParticles(const Inputs<T>& p, const StepConstants<T>& k, const Cotangents<T>& out, const T* x,
                             const T* v, const T* v_next, T* gf, const T* springs, int64_t n, int64_t i0, int64_t len,
                             T* sums, const T* dt_m) {
  T* cx0 = out.x;
  T* cx1 = out.x + n;
  T* cx2 = out.x + 2 * n;
  T* cv0 = out.v;
  T* cv1 = out.v + n;
  T* cv2 = out.v + 2 * n;
  T* gf0 = gf;
  T* gf1 = gf + n;
  T* gf2 = gf + 2 * n;
  T* cmass = out.mass;
  T* ccdm = out.cdm;
  T* ckg = out.kg;
  T* ckgd = out.kgd;
  const T* mass = p.mass;
  const T* free = p.free;
  const T* cdm = p.cdm;
  const T* kg = p.kg;
  const T* kgd = p.kgd;
  const T dt = k.dt, g0 = k.g0, g1 = k.g1, g2 = k.g2, height = k.height;
  T* cg0 = sums;
  T* cg1 = sums + kRun;
  T* cg2 = sums + 2 * kRun;
  T* ch = sums + 3 * kRun;
  JAXSPRING_INDEPENDENT
  for (int64_t j = 0; j < len; ++j) {
    const int64_t i = i0 + j;
    const bool on = free[i] != T(0);
    const T w0 = v[i], w1 = v[n + i], w2 = v[2 * n + i];
    const T x0 = cx0[i] - springs[j], x1 = cx1[i] - springs[kRun + j], x2 = cx2[i] - springs[2 * kRun + j];
    const T y0 = cv0[i] - springs[3 * kRun + j], y1 = cv1[i] - springs[4 * kRun + j],
            y2 = cv2[i] - springs[5 * kRun + j];
    // v' feeds x' = x + dt v'; v' = v + (dt F) / m
    T c0 = on ? y0 + dt * x0 : T(0);
    T c1 = on ? y1 + dt * x1 : T(0);
    T c2 = on ? y2 + dt * x2 : T(0);
    const T f0 = c0 * dt_m[i], f1 = c1 * dt_m[i], f2 = c2 * dt_m[i];  // dt / m, prepared
    // dv'/dm = -(dt F) / m^2 = -(v' - v) / m for free particles
    T cm = kMass ? -(c0 * (v_next[i] - w0) + c1 * (v_next[n + i] - w1) + c2 * (v_next[2 * n + i] - w2)) / mass[i]
                 : T(0);
    T cx1_out = x1;
    if (kGravityOn) {  // m f = dt c
      cg0[j] += dt * c0;
      cg1[j] += dt * c1;
      cg2[j] += dt * c2;
      if (kMass) cm += g0 * f0 + g1 * f1 + g2 * f2;
    }
    if (kDragOn) {
      const T speed = std::sqrt(w0 * w0 + w1 * w1 + w2 * w2);
      const T wf = w0 * f0 + w1 * f1 + w2 * f2;
      ccdm[i] -= speed * wf;
      const T along = wf / (speed > 0 ? speed : T(1));  // d|v|/dv = 0 at v = 0, as safe_norm
      c0 -= cdm[i] * (speed * f0 + along * w0);
      c1 -= cdm[i] * (speed * f1 + along * w1);
      c2 -= cdm[i] * (speed * f2 + along * w2);
    }
    if (kGroundOn) {
      const T depth = height - x[n + i];
      const T normal = depth > 0 ? f1 : T(0);
      ckg[i] += depth * normal;
      ckgd[i] -= w1 * normal;
      ch[j] += kg[i] * normal;
      cx1_out -= kg[i] * normal;
      c1 -= kgd[i] * normal;
    }
    if (kMass) cmass[i] += cm;
    cx0[i] = x0;
    cx1[i] = cx1_out;
    cx2[i] = x2;
    cv0[i] = c0;
    cv1[i] = c1;
    cv2[i] = c2;
    gf0[i] = f0;
    gf1[i] = f1;
    gf2[i] = f2;
  }
}

template <typename T>
using ReverseParticlesFn = void (*)(const Inputs<T>&, const StepConstants<T>&, const Cotangents<T>&, const T*,
                                    const T*, const T*, T*, const T*, int64_t, int64_t, int64_t, T*, const T*);

template <typename T>
struct ReverseParticlesOf {
  template <bool kDragOn, bool kGravityOn, bool kGroundOn, bool kMass>
  static constexpr ReverseParticlesFn<T> Fn = ReverseParticles<T, kDragOn, kGravityOn, kGroundOn, kMass>;
};

template <typename T>
ReverseParticlesFn<T> PickReverseParticles(const StepConstants<T>& k, bool mass) {
  return Pick<ReverseParticlesOf<T>>(k.drag, k.gravity, k.ground, mass);
}

// Spring j's entries of the reverse rows (`width` apart): the cotangent of d, then of w.
template <typename T>
inline void ReverseRows(T* out, int64_t width, int64_t j, const SpringCotangent<T>& c) {
  out[j] = c.d0;
  out[width + j] = c.d1;
  out[2 * width + j] = c.d2;
  out[3 * width + j] = c.w0;
  out[4 * width + j] = c.w1;
  out[5 * width + j] = c.w2;
}

// Reverse of `SpringRun`: from gf, the cotangent of the force, writes the springs'
// cotangent rows (6 rows at out, `width` apart: the cotangent g of d = x_b - x_a, then h
// of w = v_b - v_a; + on b, - on a) and adds their cotangents of rest length, ks and kd
// (to ct.*[k..]). With kKnown, 1 / length of spring j is inv[j].
template <typename T, bool kKnown>
void ReverseRun(const T* x, const T* v, const T* gf, int64_t n, int64_t a, int64_t b, const T* rest, const T* ks,
                const T* kd, int64_t len, const Cotangents<T>& ct, int64_t k, T* out, int64_t width, const T* inv_in) {
  T* crest = ct.rest + k;
  T* cks = ct.ks + k;
  T* ckd = ct.kd + k;
  JAXSPRING_INDEPENDENT
  for (int64_t j = 0; j < len; ++j) {
    Spring<T> g;
    if constexpr (kKnown) {
      g = SpringKnownAt(x, v, n, a + j, b + j, rest[j], inv_in[j]);
    } else {
      g = SpringAt(x, v, n, a + j, b + j, rest[j]);
    }
    const T c0 = gf[a + j] - gf[b + j], c1 = gf[n + a + j] - gf[n + b + j], c2 = gf[2 * n + a + j] - gf[2 * n + b + j];
    const SpringCotangent<T> c = Adjoint(g, ks[j], kd[j], Magnitude(g, ks[j], kd[j]), Along(g, c0, c1, c2), c0, c1, c2);
    cks[j] += c.ks;
    ckd[j] += c.kd;
    crest[j] += c.rest;
    ReverseRows(out, width, j, c);
  }
}

// `ReverseRun` for scalar ks, kd (`Wanted::lean`), lengths computed: valid[j] masks
// padding; the cotangents of ks and kd go to sums[j], sums[kRun + j]; none for the rest
// lengths. (With kept 1 / lengths: `ReverseRunLeanPacked`.)
template <typename T>
void ReverseRunLean(const T* x, const T* v, const T* gf, int64_t n, int64_t a, int64_t b, const T* rest, T ks, T kd,
                    const T* valid, int64_t len, T* sums, T* out, int64_t width) {
  T* cks = sums;
  T* ckd = sums + kRun;
  JAXSPRING_INDEPENDENT
  for (int64_t j = 0; j < len; ++j) {
    const Spring<T> g = SpringAt(x, v, n, a + j, b + j, rest[j]);
    const T on = valid[j];
    const T m = Magnitude(g, ks, kd) * on;  // zero for padding, as uc
    const T c0 = gf[a + j] - gf[b + j], c1 = gf[n + a + j] - gf[n + b + j], c2 = gf[2 * n + a + j] - gf[2 * n + b + j];
    const SpringCotangent<T> c = Adjoint(g, ks, kd, m, Along(g, c0, c1, c2) * on, c0, c1, c2);
    cks[j] += c.ks;
    ckd[j] += c.kd;
    ReverseRows(out, width, j, c);
  }
}

// `ReverseRunLean` with kept 1 / lengths for the springs j .. j + kLanes - 1 of a run,
// as one vector V (or for spring j alone, V = T; j's offset already applied to every
// pointer; `width` apart rows at out): the cotangents of ks, kd added to sum_ks, sum_kd, with kMasked times `counted`
// (1 or 0 a lane).
template <typename T, typename V, bool kMasked = false>
inline void LeanSprings(const T* x, const T* v, const T* gf, int64_t n, int64_t a, int64_t b, const T* rest,
                        const T* inv_in, T ks, T kd, T* out, int64_t width, V& sum_ks, V& sum_kd,
                        const V& counted = V{}) {
  const V d0 = Read<V>(x + b) - Read<V>(x + a), d1 = Read<V>(x + n + b) - Read<V>(x + n + a),
          d2 = Read<V>(x + 2 * n + b) - Read<V>(x + 2 * n + a);
  const V w0 = Read<V>(v + b) - Read<V>(v + a), w1 = Read<V>(v + n + b) - Read<V>(v + n + a),
          w2 = Read<V>(v + 2 * n + b) - Read<V>(v + 2 * n + a);
  const Spring<V> g = MeasureKnown(d0, d1, d2, w0, w1, w2, Read<V>(rest), Read<V>(inv_in));  // inv 0: padding
  const V c0 = Read<V>(gf + a) - Read<V>(gf + b), c1 = Read<V>(gf + n + a) - Read<V>(gf + n + b),
          c2 = Read<V>(gf + 2 * n + a) - Read<V>(gf + 2 * n + b);
  const SpringCotangent<V> c = Adjoint(g, ks, kd, Magnitude(g, ks, kd), Along(g, c0, c1, c2), c0, c1, c2);
  if constexpr (kMasked) {
    sum_ks += counted * c.ks;
    sum_kd += counted * c.kd;
  } else {
    sum_ks += c.ks;
    sum_kd += c.kd;
  }
  Write(out, c.d0);
  Write(out + width, c.d1);
  Write(out + 2 * width, c.d2);
  Write(out + 3 * width, c.w0);
  Write(out + 4 * width, c.w1);
  Write(out + 5 * width, c.w2);
}

// The lean spring pass with kept 1 / lengths (zero for padding), in whole vectors, the
// ks and kd sums kept in registers. A run that does not fill its last vector ends with
// the vector of its last springs, which overlaps the one before: its rows are written
// twice (the same values), and the springs counted already are masked out of the sums.
// Runs shorter than a vector go spring by spring.
template <typename T>
void ReverseRunLeanPacked(const T* x, const T* v, const T* gf, int64_t n, int64_t a, int64_t b, const T* rest, T ks,
                          T kd, int64_t len, T* sums, T* out, int64_t width, const T* inv_in) {
  using V = typename Pack<T>::V;
  constexpr int64_t L = Pack<T>::kLanes;
  if (len < L) {
    for (int64_t j = 0; j < len; ++j) {
      LeanSprings<T, T>(x, v, gf, n, a + j, b + j, rest + j, inv_in + j, ks, kd, out + j, width, sums[j],
                        sums[kRun + j]);
    }
    return;
  }
  V sum_ks{}, sum_kd{};
  int64_t j = 0;
  for (; j + L <= len; j += L) {
    LeanSprings<T, V>(x, v, gf, n, a + j, b + j, rest + j, inv_in + j, ks, kd, out + j, width, sum_ks, sum_kd);
  }
  if (j < len) {
    const int64_t last = len - L;  // lanes below j - last were counted
    V lane;
    for (int64_t l = 0; l < L; ++l) lane[l] = l >= j - last ? T(1) : T(0);
    LeanSprings<T, V, true>(x, v, gf, n, a + last, b + last, rest + last, inv_in + last, ks, kd, out + last, width,
                            sum_ks, sum_kd, lane);
  }
  for (int64_t l = 0; l < L; ++l) {
    sums[l] += sum_ks[l];
    sums[kRun + l] += sum_kd[l];
  }
}

// Particle state of the reverse pass at one step: the state (x, v) at its start, and
// after it (x_after, v_after; x_after null when this is the last step of the rollout:
// nothing after it to take the springs' part from).
template <typename T>
struct ReverseStep {
  const T *x, *v, *x_after, *v_after;
  const T* inv_after = nullptr;  // 1 / length of every (padded) spring at x_after, if kept
};

// One iteration of the reverse pass, thread t of the team: the spring pass of the step
// after (from its state and gf_after, the cotangent of its force), then the particle
// pass of this step (writing gf, the cotangent of this step's force), or with
// finish = true only the springs' part added to out.x, out.v (after the first step).
// Alone, a thread runs both passes block by block (the rows it writes are read straight
// away, from cache); a team runs them one after the other with a barrier in between.
template <typename T>
void ReverseIteration(const Layout& layout, const Inputs<T>& p, const StepConstants<T>& k, const ReverseStep<T>& at,
                      bool finish, const T* gf_after, T* gf, const Cotangents<T>& out, const Wanted<T>& wanted,
                      Rows<T>& rows, Partials<T>& partials, Team& team, int t) {
  const int64_t n = layout.n;
  int64_t lo, hi;
  Share(layout, t, team.size(), &lo, &hi);
  const auto reverse_particles = PickReverseParticles(k, wanted.mass);
  const bool springs_after = at.x_after != nullptr, fused = team.size() == 1 && layout.ascending;
  alignas(64) T springs[6 * kRun];
  const auto reverse_run = at.inv_after ? ReverseRun<T, true> : ReverseRun<T, false>;
  T* spring_sums = partials.lanes.data() + Partials<T>::kKs * kRun;
  auto spring_pass = [&](int64_t block) {
    for (const Run& run : layout.blocks[block]) {
      const int64_t a = run.a, b = a + layout.shift[run.family];  // its springs join a + j, b + j
      if (wanted.lean && at.inv_after) {
        ReverseRunLeanPacked(at.x_after, at.v_after, gf_after, n, a, b, p.rest + run.k, wanted.ks, wanted.kd,
                             run.len, spring_sums, rows.At(run.family) + a, rows.width, at.inv_after + run.k);
        continue;
      }
      if (wanted.lean) {
        ReverseRunLean(at.x_after, at.v_after, gf_after, n, a, b, p.rest + run.k, wanted.ks, wanted.kd,
                       wanted.valid + run.k, run.len, spring_sums, rows.At(run.family) + a, rows.width);
        continue;
      }
      reverse_run(at.x_after, at.v_after, gf_after, n, a, b, p.rest + run.k, p.ks + run.k, p.kd + run.k, run.len,
                  out, run.k, rows.At(run.family) + a, rows.width, at.inv_after ? at.inv_after + run.k : nullptr);
    }
  };
  auto particle_pass = [&](int64_t b) {
    const int64_t i0 = b * kRun, len = BlockLength(layout, b);
    if (springs_after) {
      Differences(layout, rows, i0, len, springs);
    } else {
      std::fill(springs, springs + 6 * kRun, T(0));
    }
    if (!finish) {
      reverse_particles(p, k, out, at.x, at.v, at.v_after, gf, springs, n, i0, len, partials.lanes.data(),
                        wanted.dt_m);
      return;
    }
    for (int c = 0; c < 3; ++c) {
      JAXSPRING_INDEPENDENT
      for (int64_t j = 0; j < len; ++j) {
        out.x[c * n + i0 + j] -= springs[c * kRun + j];
        out.v[c * n + i0 + j] -= springs[(3 + c) * kRun + j];
      }
    }
  };
  for (int64_t b = lo; b < hi; ++b) {
    if (springs_after) spring_pass(b);
    if (fused) particle_pass(b);  // its rows (a = i - shift < i) are written
  }
  if (fused) return;
  team.Sync();
  for (int64_t b = lo; b < hi; ++b) particle_pass(b);
  team.Sync();
}

// The reverse pass over one replayed segment (`length` states from `states`), from its
// last step to its first. `after`: the state that follows the segment (the next stored
// one), null after the rollout's last step (then v_final). `parity` alternates the two
// force-cotangent buffers of work.gf from iteration to iteration. invs: what `Replay`
// kept, or null.
template <typename T>
void ReverseSegment(const Layout& layout, const Inputs<T>& p, const StepConstants<T>& k, const T* states,
                    const T* invs, int64_t length, const T* after, const T* v_final, const Cotangents<T>& out,
                    Workspace<T>& work, int& parity, Team& team, int t) {
  const int64_t n = layout.n;
  for (int64_t step = length - 1; step >= 0; --step) {
    const T* x = states + step * 6 * n;
    const T* next = step + 1 < length ? states + (step + 1) * 6 * n : after;
    const bool kept = invs && step + 2 < length;  // the replay stepped from state step + 1
    const ReverseStep<T> at{x, x + 3 * n, next, next ? next + 3 * n : v_final,
                            kept ? invs + (step + 1) * layout.padded : nullptr};
    T* gf_after = work.gf.data() + parity * 3 * n;
    T* gf = work.gf.data() + (1 - parity) * 3 * n;
    ReverseIteration(layout, p, k, at, false, gf_after, gf, out, work.wanted, work.reverse, work.partials[t], team, t);
    parity = 1 - parity;
  }
}

// After the reverse pass over the first segment: the springs' part of the first step.
template <typename T>
void FinishReverse(const Layout& layout, const Inputs<T>& p, const StepConstants<T>& k, const T* first,
                   const Cotangents<T>& out, Workspace<T>& work, int parity, Team& team, int t) {
  const int64_t n = layout.n;
  const ReverseStep<T> at{nullptr, nullptr, first, first + 3 * n};
  ReverseIteration(layout, p, k, at, true, work.gf.data() + parity * 3 * n, static_cast<T*>(nullptr), out, work.wanted,
                   work.reverse,
                   work.partials[t], team, t);
}

// The state stored after segment `segment`, or null after the last one.
template <typename T>
const T* StoredAfter(const Config& config, const T* stored, int64_t segment, int64_t n) {
  const int64_t segments = (config.steps + config.stride - 1) / config.stride;
  return segment + 1 < segments ? stored + (segment + 1) * 6 * n : nullptr;
}

}  // namespace

template <typename T>
void BackwardMember(const Layout& layout, const Inputs<T>& p, const Config& config, const T* stored,
                    const T* v_final, const Cotangents<T>& out, Workspace<T>& work, Team& team, int t) {
  const int64_t n = layout.n;
  const int64_t segments = (config.steps + config.stride - 1) / config.stride;
  const StepConstants<T> k(p, config);
  int parity = 0;
  for (int64_t segment = segments - 1; segment >= 0; --segment) {
    T* invs = work.invs[0].empty() ? nullptr : work.invs[0].data();
    const int64_t length =
        Replay(layout, p, config, stored, segment, work.forward, work.states[0].data(), invs, work.valid.data(), team, t);
    ReverseSegment(layout, p, k, work.states[0].data(), invs, length, StoredAfter(config, stored, segment, n),
                   v_final, out, work, parity, team, t);
  }
  FinishReverse(layout, p, k, work.states[0].data(), out, work, parity, team, t);
}

namespace {

// `BackwardPipelined`: the second thread replays segment s - 1 while the first runs the
// reverse pass over segment s (double-buffered states). The first
// replays the last segment itself (no wait for the second to start), and any replay not
// yet begun. When it has waited for one longer than it takes to replay one itself, the
// second core is slow (busy, or descheduled by a hypervisor): it then replays every
// segment left itself, into buffers of its own.
}  // namespace

template <typename T>
void BackwardPipelined(const Layout& layout, const Inputs<T>& p, const Config& config, const T* stored,
                       const T* v_final, const Cotangents<T>& out, Workspace<T>& work) {
  using Clock = std::chrono::steady_clock;
  const int64_t n = layout.n;
  const int64_t segments = (config.steps + config.stride - 1) / config.stride;
  T* buffers[2] = {work.states[0].data(), work.states[1].data()};
  T* invs[2] = {work.invs[0].empty() ? nullptr : work.invs[0].data(),
                work.invs[1].empty() ? nullptr : work.invs[1].data()};
  int64_t lengths[2] = {0, 0};
  // replays go in order j = 0, 1, .. (segment segments - 1 - j), into buffer j % 2
  std::atomic<int64_t> taken{1};     // replays j < taken are claimed (j = 0 by the first thread)
  std::atomic<int64_t> reversed{0};  // reverse passes j < reversed are done (their buffers free)
  std::atomic<int64_t> ready[2] = {-1, -1};  // the replay each buffer holds, once complete
  auto replay = [&](int64_t j, Rows<T>& rows, T* states, T* inv) {
    Team solo(1);
    return Replay(layout, p, config, stored, segments - 1 - j, rows, states, inv, work.valid.data(), solo, 0);
  };
  Team pair(2);
  pair.Launch([&](int t) {
    if (t == 1) {  // replays ahead while buffers are free
      for (int64_t j = taken.load(); j < segments; j = taken.load()) {
        int turn = 0;
        while (reversed.load(std::memory_order_acquire) < j - 1 && taken.load() == j) Wait(turn++);
        if (!taken.compare_exchange_strong(j, j + 1)) continue;
        lengths[j % 2] = replay(j, work.forward, buffers[j % 2], invs[j % 2]);
        ready[j % 2].store(j, std::memory_order_release);
      }
      return;
    }
    try {
      const StepConstants<T> k(p, config);
      Team solo(1);
      int parity = 0;
      const auto start = Clock::now();
      lengths[0] = replay(0, work.second, buffers[0], invs[0]);
      const auto patience = (Clock::now() - start) * config.stride / std::max<int64_t>(lengths[0], 1);
      // a test hook: let the other thread take replay 1, then give up on it at once
      const bool impatient = config.test & kTestImpatient;
      int64_t alone = segments;      // replays from here on are this thread's, into its own buffers
      Uninitialised<T> own[2];        // those buffers: states, 1 / lengths
      const T* states = buffers[0];  // the states of the latest reverse pass
      for (int64_t j = 0; j < segments; ++j) {
        for (int turn = 0; impatient && j == 1 && taken.load() < 2; ++turn) Wait(turn);
        bool mine = j >= alone;
        int64_t next = j;
        if (j == 0 || mine) {
          // replayed above, or below
        } else if (taken.compare_exchange_strong(next, j + 1)) {  // not begun by the other thread
          lengths[j % 2] = replay(j, work.second, buffers[j % 2], invs[j % 2]);
        } else {
          const auto since = Clock::now();
          bool late = impatient;
          for (int turn = 0; !late && ready[j % 2].load(std::memory_order_acquire) != j; ++turn) {
            Wait(turn);
            late = turn % 64 == 63 && Clock::now() - since > patience;
          }
          if (late) {
            alone = std::min(alone, taken.exchange(segments));  // the other thread begins no more
            mine = true;
          }
        }
        states = buffers[j % 2];
        T* inv = invs[j % 2];
        int64_t length = 0;
        if (mine) {  // the other thread may still write buffer j % 2
          if (own[0].empty()) {
            own[0].Allocate(work.states[0].count);
            if (inv) own[1].Allocate(work.invs[0].count);
          }
          states = own[0].data();
          inv = inv ? own[1].data() : nullptr;
          length = replay(j, work.second, own[0].data(), inv);
        } else {
          length = lengths[j % 2];
        }
        ReverseSegment(layout, p, k, states, inv, length, StoredAfter(config, stored, segments - 1 - j, n), v_final,
                       out, work, parity, solo, 0);
        reversed.store(j + 1, std::memory_order_release);
      }
      FinishReverse(layout, p, k, states, out, work, parity, solo, 0);
    } catch (...) {
      taken.store(segments);  // the other thread begins no more replays (nor waits for a buffer)
      throw;
    }
  });
}


#define JAXSPRING_INSTANTIATE(T)                                                                               \
  template void BackwardMember<T>(const Layout&, const Inputs<T>&, const Config&, const T*, const T*,           \
                                  const Cotangents<T>&, Workspace<T>&, Team&, int);                             \
  template void BackwardPipelined<T>(const Layout&, const Inputs<T>&, const Config&, const T*, const T*,        \
                                     const Cotangents<T>&, Workspace<T>&);
JAXSPRING_INSTANTIATE(float)
JAXSPRING_INSTANTIATE(double)
#undef JAXSPRING_INSTANTIATE

}  // namespace jaxspring::native
