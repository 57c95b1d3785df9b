// Forward batches with their members side by side: groups of Lanes<T>() members, the
// member innermost, stepped with one vector operation across the group.

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <functional>
#include <vector>

#include "lattice.h"
#include "lattice_groups.h"
#include "lattice_step.h"
#include "lattice_threads.h"
#include "spring_law.h"

namespace jaxspring::native {

template <typename T>
Sharing FindSharing(const Layout& layout, int64_t batch, const std::function<Inputs<T>(int64_t)>& member) {
  const int64_t n = layout.n, springs = layout.springs;
  const Inputs<T> first = member(0);
  Sharing sharing{true, true};
  for (int64_t i = 0; i < batch && (sharing.springs || sharing.particles); ++i) {
    const Inputs<T> p = member(i);
    if (sharing.springs) {
      sharing.springs = std::equal(p.rest, p.rest + springs, first.rest) &&
                        std::all_of(p.ks, p.ks + springs, [&](T k) { return k == p.ks[0]; }) &&
                        std::all_of(p.kd, p.kd + springs, [&](T k) { return k == p.kd[0]; });
    }
    if (sharing.particles) {
      sharing.particles = std::equal(p.mass, p.mass + n, first.mass) && std::equal(p.free, p.free + n, first.free) &&
                          std::equal(p.cdm, p.cdm + n, first.cdm) && std::equal(p.kg, p.kg + n, first.kg) &&
                          std::equal(p.kgd, p.kgd + n, first.kgd);
    }
  }
  return sharing;
}

namespace {

template <typename T>
struct Group {  // the inputs and state of Lanes<T>() members, member innermost
  std::vector<T> x, v, force, rest, ks, kd, mass, free, cdm, kg, kgd, gravity, height;
  // with Sharing::springs: rest (padded) and valid (1 for a spring, 0 for padding) once,
  // ks, kd once per lane; with Sharing::particles: mass .. kgd once per particle
  std::vector<T> valid;
  // the spring forces of a step, particle q at q (up to the margin a block's springs
  // reach past the lattice's end), components `stride` lanes apart (not a multiple of 4
  // KiB, whose three components would share cache sets); a particle's entry is cleared
  // once it has moved. All particles, not a ring of the blocks under way: a run's springs
  // then address both their ends from one base, and the loop keeps no ring index.
  int64_t stride = 0;
  void AllocateForce(const Layout& layout) {
    stride = (layout.n + layout.margin + 5) * Lanes<T>();
    force.assign(3 * stride, T(0));
  }
};

// `Integrate` for particles [lo, hi) of a group in place, their force then cleared
// (lanes innermost; gravity and ground height per lane; kShared: particle parameters once).
template <typename T, bool kDragOn, bool kGravityOn, bool kGroundOn, bool kShared>
void GroupParticles(Group<T>& g, int64_t n, T dt, int64_t lo, int64_t hi) {
  constexpr int64_t L = Lanes<T>();
  const int64_t nl = n * L, rl = g.stride;
  const T* gravity = g.gravity.data();
  T* x = g.x.data();
  T* v = g.v.data();
  for (int64_t q = lo; q < hi; ++q) {
    T* f = g.force.data() + q * L;
    JAXSPRING_INDEPENDENT
    for (int64_t l = 0; l < L; ++l) {
      const int64_t e = q * L + l, o = kShared ? q : e;
      Integrate<T, kDragOn, kGravityOn, kGroundOn>(x, v, x, v, nl, e, f[l], f[rl + l], f[2 * rl + l], g.mass[o],
                                                   g.free[o], g.cdm[o], g.kg[o], g.kgd[o], gravity[l], gravity[L + l],
                                                   gravity[2 * L + l], g.height[l], dt);
      f[l] = T(0);
      f[rl + l] = T(0);
      f[2 * rl + l] = T(0);
    }
  }
}

// The springs whose a lie in block b of a group, their forces added to g.force (kShared:
// Sharing::springs).
template <typename T, bool kShared>
void GroupSprings(const Layout& layout, Group<T>& g, int64_t block) {
  constexpr int64_t L = Lanes<T>();
  const int64_t nl = layout.n * L, rl = g.stride;
  const T* rest = g.rest.data();
  const T* ks = g.ks.data();
  const T* kd = g.kd.data();
  const T* valid = g.valid.data();
  alignas(64) T ks_lanes[L], kd_lanes[L];  // shared: one value a lane, held in registers
  if (kShared) {
    std::copy(ks, ks + L, ks_lanes);
    std::copy(kd, kd + L, kd_lanes);
  }
  for (const Run& run : layout.blocks[block]) {
    const int64_t sl = layout.shift[run.family] * L;
    const T* x = g.x.data() + run.a * L;
    const T* v = g.v.data() + run.a * L;
    T* f = g.force.data() + run.a * L;
    for (int64_t j = 0; j < run.len; ++j) {
      const int64_t o = j * L, k = (run.k + j) * L;
      JAXSPRING_INDEPENDENT
      for (int64_t l = 0; l < L; ++l) {
        Spring<T> s;
        T m;
        if (kShared) {  // valid is 1 for a spring (m exactly ks e + kd closing), 0 for padding
          s = SpringAt(x, v, nl, o + l, o + sl + l, rest[run.k + j]);
          m = valid[run.k + j] * Magnitude(s, ks_lanes[l], kd_lanes[l]);
        } else {
          s = SpringAt(x, v, nl, o + l, o + sl + l, rest[k + l]);
          m = Magnitude(s, ks[k + l], kd[k + l]);
        }
        const T f0 = m * s.u0, f1 = m * s.u1, f2 = m * s.u2;
        f[o + l] += f0;
        f[rl + o + l] += f1;
        f[2 * rl + o + l] += f2;
        f[o + sl + l] -= f0;
        f[rl + o + sl + l] -= f1;
        f[2 * rl + o + sl + l] -= f2;
      }
    }
  }
}

// `config.steps` steps of a group, block by block: the springs whose a lie in a block
// complete the forces on its particles (every shift is positive), which then move;
// springs still to come read only positions after the block.
template <typename T>
struct GroupParticlesOf {
  template <bool kDragOn, bool kGravityOn, bool kGroundOn, bool kShared>
  static constexpr void (*Fn)(Group<T>&, int64_t, T, int64_t, int64_t) =
      GroupParticles<T, kDragOn, kGravityOn, kGroundOn, kShared>;
};

template <typename T>
void SimulateGroup(const Layout& layout, const Config& config, Sharing sharing, Group<T>& g) {
  const T dt = static_cast<T>(config.dt);
  const auto particles = Pick<GroupParticlesOf<T>>(config.flags & kDrag, config.flags & kGravity,
                                                  config.flags & kGround, sharing.particles);
  const auto springs = sharing.springs ? GroupSprings<T, true> : GroupSprings<T, false>;
  const int64_t blocks = static_cast<int64_t>(layout.blocks.size());
  for (int64_t step = 0; step < config.steps; ++step) {
    for (int64_t block = 0; block < blocks; ++block) {
      springs(layout, g, block);
      particles(g, layout.n, dt, block * kRun, block * kRun + BlockLength(layout, block));
    }
  }
}

}  // namespace

template <typename T>
void AdvanceGroups(const Layout& layout, const Config& config, int64_t batch, Sharing sharing,
                   const std::function<Inputs<T>(int64_t)>& member, T* x, T* v) {
  constexpr int64_t L = Lanes<T>();
  const int64_t n = layout.n, groups = (batch + L - 1) / L;
  const int threads = static_cast<int>(std::min<int64_t>(UsableThreads(), groups));
  Team pool(threads);
  std::atomic<int64_t> next{0};  // groups go to whichever thread is free (a core may be slow)
  pool.Launch([&](int) {
    Group<T> g;
    for (auto* buffer : {&g.x, &g.v}) buffer->assign(3 * n * L, T(0));
    g.AllocateForce(layout);
    const Inputs<T> first = member(0);
    if (sharing.springs) {
      for (auto* buffer : {&g.rest, &g.valid}) buffer->assign(layout.padded, T(0));
      for (auto* buffer : {&g.ks, &g.kd}) buffer->assign(L, T(0));
      for (const Run& r : layout.valid) {
        std::copy(first.rest + r.k, first.rest + r.k + r.len, g.rest.begin() + r.a);
        std::fill(g.valid.begin() + r.a, g.valid.begin() + r.a + r.len, T(1));
      }
    } else {
      for (auto* buffer : {&g.rest, &g.ks, &g.kd}) buffer->assign(layout.padded * L, T(0));
    }
    if (sharing.particles) {
      g.mass.assign(first.mass, first.mass + n);
      g.free.assign(first.free, first.free + n);
      g.cdm.assign(first.cdm, first.cdm + n);
      g.kg.assign(first.kg, first.kg + n);
      g.kgd.assign(first.kgd, first.kgd + n);
    } else {
      for (auto* buffer : {&g.mass, &g.free, &g.cdm, &g.kg, &g.kgd}) buffer->assign(n * L, T(0));
    }
    g.gravity.assign(3 * L, T(0));
    g.height.assign(L, T(0));
    for (int64_t group = next++; group < groups; group = next++) {
      for (int64_t l = 0; l < L; ++l) {  // gather the members, lane l
        const int64_t i = std::min(group * L + l, batch - 1);
        const Inputs<T> p = member(i);
        for (int64_t c = 0; c < 3 * n; ++c) {
          g.x[c * L + l] = x[i * 3 * n + c];
          g.v[c * L + l] = v[i * 3 * n + c];
        }
        if (sharing.springs) {
          g.ks[l] = p.ks[0];
          g.kd[l] = p.kd[0];
        } else {
          for (const Run& r : layout.valid) {
            for (int64_t j = 0; j < r.len; ++j) {
              g.rest[(r.a + j) * L + l] = p.rest[r.k + j];
              g.ks[(r.a + j) * L + l] = p.ks[r.k + j];
              g.kd[(r.a + j) * L + l] = p.kd[r.k + j];
            }
          }
        }
        if (!sharing.particles) {
          for (int64_t q = 0; q < n; ++q) {
            g.mass[q * L + l] = p.mass[q];
            g.free[q * L + l] = p.free[q];
            g.cdm[q * L + l] = p.cdm[q];
            g.kg[q * L + l] = p.kg[q];
            g.kgd[q * L + l] = p.kgd[q];
          }
        }
        for (int c = 0; c < 3; ++c) g.gravity[c * L + l] = p.gravity[c];
        g.height[l] = p.height[0];
      }
      SimulateGroup(layout, config, sharing, g);
      for (int64_t l = 0; l < L && group * L + l < batch; ++l) {  // scatter them back
        const int64_t i = group * L + l;
        for (int64_t c = 0; c < 3 * n; ++c) {
          x[i * 3 * n + c] = g.x[c * L + l];
          v[i * 3 * n + c] = g.v[c * L + l];
        }
      }
    }
  });
}

#define JAXSPRING_INSTANTIATE(T)                                                                                \
  template Sharing FindSharing<T>(const Layout&, int64_t, const std::function<Inputs<T>(int64_t)>&);             \
  template void AdvanceGroups<T>(const Layout&, const Config&, int64_t, Sharing,                                 \
                                 const std::function<Inputs<T>(int64_t)>&, T*, T*);
JAXSPRING_INSTANTIATE(float)
JAXSPRING_INSTANTIATE(double)
#undef JAXSPRING_INSTANTIATE

}  // namespace jaxspring::native
