// Whole time steps of a lattice scene, and their exact reverse-mode derivative, as XLA
// FFI custom calls (CPU): springs (neighbour families of a lattice), air drag, gravity
// and the penalty ground, integrated by semi-implicit Euler, `steps` steps per call.
//
// Layout (jaxspring's grid layout): positions and velocities are (3, N), component
// first, the N particles in C order of the lattice (up to 3 axes). The springs of a
// family with lattice offset o join every particle a to b = a + shift(o); each family
// runs as one unit-stride loop over a range of a (see `Layout`), which vectorises.
//
// No scatter: a step is a spring pass and a particle pass. The spring pass writes each
// spring's force into its family's row, indexed by its particle a (`Rows`); the particle
// pass gathers, for every particle i, the sum over families of row(i) - row(i - shift)
// (+ on a, - on b) and integrates. Both are unit-stride loops free of dependences.
//
// Per step, with F the total force (same formulas as jaxspring/sim/forces.py):
// v' = free ? v + (dt F) / m : 0, x' = x + dt v'.
//
// Reverse mode: the forward call can return the state every `stride` steps; the
// backward call replays one such segment at a time, keeping its states, and runs the
// exact reverse pass over it (memory ~2 sqrt(steps) states for stride ~sqrt(steps)).
// The reverse pass is the same two passes backwards: the particle pass gathers the
// springs' cotangent rows of the step after and yields the force's cotangent; the spring
// pass turns it into cotangent rows (for x and v) and parameter cotangents. It computes
// only the cotangents asked for (`needs`, from JAX's symbolic zeros): with ks and kd
// given as one value each (a scalar parameter) and no rest-length cotangent, the spring
// pass sums their cotangents per lane instead of per spring (`Wanted`).
//
// Threads: a batch (vmap) is split over threads by members, each thread taking the next
// as it comes free. One large lattice is split by particle ranges (two barriers per
// step). One small lattice runs forward on one thread; its backward call replays the
// next segment on a second thread while the first runs the reverse pass (and replays
// what the second has not begun, or all that is left when the second is slow).
#if defined(__linux__)
#include <sys/mman.h>
#if defined(MADV_HUGEPAGE)
#define JAXSPRING_HUGE_PAGES
#endif
#endif

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

// The loops below touch each index once; this tells the compiler so (the arrays are
// components of one buffer, which defeats its own alias analysis).
#if defined(__clang__)
#define JAXSPRING_INDEPENDENT _Pragma("clang loop vectorize(assume_safety)")
#elif defined(__GNUC__)
#define JAXSPRING_INDEPENDENT _Pragma("GCC ivdep")
#else
#define JAXSPRING_INDEPENDENT
#endif

namespace {

constexpr int64_t kRun = 256;  // longest run of springs or particles processed at once
constexpr int64_t kDrag = 1, kGravity = 2, kGround = 4;  // flags
// `needs` of a backward call: the inputs whose cotangents are asked for (bit i: the i-th
// parameter input, rest = 0 .. height = 9); the others may be returned as zeros
constexpr int64_t kNeedRest = 1 << 0, kNeedMass = 1 << 3;
// Springs in one lattice above which a second thread pays for its two barriers a step
// (measured, 2,000 steps: a 100 x 100 cloth, 39k springs, 42-45 ms on two threads against
// 80-85 on one; at 45 x 45 and 60 x 60 two threads were often twice as slow, as the
// cores exchange the cache lines at their boundary every step; even at 80 x 80).
constexpr int64_t kSpringsForThreads = 30000;
// Largest buffer of replayed spring lengths kept for the reverse pass (per segment):
// while it stays in the cache it saves the reverse pass a square root and a division
// per spring; beyond (measured: 7 MB for a 100 x 100 cloth) it costs more than it saves.
constexpr int64_t kKeepBytes = 1 << 20;

struct Run {
  int64_t a, k, len;  // springs k .. k+len-1 join particles a+j and a+j+shift
  int64_t family = 0;
};

// A family with shift s is stepped as one run over the particle range [first, first +
// count): every a there, b = a + s, including "padding" springs that join the end of a
// lattice row to the start of the next. Those get ks = kd = 0 (zero force, zero
// derivatives), and the loops run long and unit-stride instead of row by row. The range
// is cut where blocks of kRun particles begin: a pass takes its springs block by block.
struct Layout {
  int64_t n = 0, springs = 0, padded = 0;  // particles, springs, springs with padding
  int64_t margin = 0;                      // the largest |shift|
  bool ascending = true;                   // every shift > 0: a spring's b comes after its a
  std::vector<int64_t> shift;
  std::vector<std::vector<Run>> blocks;  // per block of kRun particles: the runs whose a lie in it
  std::vector<Run> valid;                // the real springs: a = padded index, k = spring index
};

ffi::ErrorOr<Layout> BuildLayout(ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets) {
  const int64_t dims = static_cast<int64_t>(shape.size());
  if (dims < 1 || dims > 3 || offsets.size() % dims != 0) {
    return ffi::Unexpected(ffi::Error::InvalidArgument("lattice: shape must have 1 to 3 axes and offsets a multiple of them"));
  }
  int64_t s[3] = {1, 1, 1};
  for (int64_t d = 0; d < dims; ++d) s[3 - dims + d] = shape[d];
  Layout layout;
  layout.n = s[0] * s[1] * s[2];
  int64_t start = 0;
  for (size_t f = 0; f < offsets.size() / dims; ++f) {
    int64_t o[3] = {0, 0, 0}, lo[3], r[3];
    for (int64_t d = 0; d < dims; ++d) o[3 - dims + d] = offsets[f * dims + d];
    for (int d = 0; d < 3; ++d) {
      lo[d] = std::max<int64_t>(0, -o[d]);
      r[d] = s[d] - std::abs(o[d]);
      if (r[d] <= 0) return ffi::Unexpected(ffi::Error::InvalidArgument("lattice: a spring family is empty"));
    }
    const int64_t first = (lo[0] * s[1] + lo[1]) * s[2] + lo[2];
    const int64_t count = ((lo[0] + r[0] - 1) * s[1] + lo[1] + r[1] - 1) * s[2] + lo[2] + r[2] - first;
    for (int64_t i0 = 0; i0 < r[0]; ++i0) {
      for (int64_t i1 = 0; i1 < r[1]; ++i1) {
        const int64_t a = ((lo[0] + i0) * s[1] + lo[1] + i1) * s[2] + lo[2];
        layout.valid.push_back({layout.padded + a - first, start + (i0 * r[1] + i1) * r[2], r[2]});
      }
    }
    layout.blocks.resize((layout.n + kRun - 1) / kRun);
    for (int64_t a = first; a < first + count;) {  // k = padded spring index
      const int64_t end = std::min(first + count, (a / kRun + 1) * kRun);
      layout.blocks[a / kRun].push_back({a, layout.padded + a - first, end - a, static_cast<int64_t>(f)});
      a = end;
    }
    const int64_t shift = (o[0] * s[1] + o[1]) * s[2] + o[2];
    layout.shift.push_back(shift);
    layout.margin = std::max(layout.margin, std::abs(shift));
    layout.ascending = layout.ascending && shift > 0;
    layout.padded += count;
    start += r[0] * r[1] * r[2];
  }
  layout.springs = start;
  return layout;
}

// The layout of a (shape, offsets) pair, built once per process (calls repeat them).
ffi::ErrorOr<const Layout*> MakeLayout(ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets) {
  static std::mutex mutex;
  static std::map<std::vector<int64_t>, std::unique_ptr<Layout>> cache;
  std::vector<int64_t> key(shape.begin(), shape.end());
  key.push_back(-1);
  key.insert(key.end(), offsets.begin(), offsets.end());
  std::lock_guard<std::mutex> lock(mutex);
  auto found = cache.find(key);
  if (found != cache.end()) return found->second.get();
  auto built = BuildLayout(shape, offsets);
  if (built.has_error()) return ffi::Unexpected(built.error());
  auto stored = std::make_unique<Layout>(std::move(built.value()));
  const Layout* layout = stored.get();
  cache.emplace(std::move(key), std::move(stored));
  return layout;
}

// Per-spring rows of every family, indexed by the spring's particle a: `comps` rows of
// `width` = n + 2 margin values per family, so that row(i - shift) is in bounds for
// every particle i. Entries without a spring stay zero.
// Rows start on 64-byte boundaries at particle 0 (so blocks of particles do too).
template <typename T>
struct Rows {
  static constexpr int64_t kAlign = 64 / sizeof(T);
  std::vector<T> data;
  T* base = nullptr;  // data's first 64-byte boundary
  int64_t width = 0, margin = 0;
  int comps = 0;
  void Allocate(const Layout& layout, int components) {
    comps = components;
    margin = (layout.margin + kAlign - 1) / kAlign * kAlign;
    width = (layout.n + 2 * margin + kAlign - 1) / kAlign * kAlign;
    if (width * sizeof(T) % 4096 == 0) width += kAlign;  // rows 4 KiB apart would share cache sets
    data.assign(layout.shift.size() * comps * width + kAlign, T(0));
    const auto address = reinterpret_cast<std::uintptr_t>(data.data());
    base = data.data() + (64 - address % 64) % 64 / sizeof(T);
  }
  T* At(size_t family) { return base + family * comps * width + margin; }  // component 0, particle 0
  const T* At(size_t family) const { return base + family * comps * width + margin; }
};

template <typename T>
struct Inputs {  // one batch member's parameters
  const T *rest, *ks, *kd, *mass, *free, *cdm, *gravity, *kg, *kgd, *height;
};

struct Config {
  int64_t steps, flags;
  double dt;
  int64_t stride;  // the forward call stores the state every `stride` steps
};

// One turn of a thread's wait for another: spin (telling the core so, which lets a
// hypervisor run another virtual CPU), yielding from the 2000th turn.
inline void Wait(int turn) {
  if (turn > 2000) {
    std::this_thread::yield();
    return;
  }
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  asm volatile("yield");
#endif
}

// A barrier for the threads of one call.
class Team {
 public:
  explicit Team(int size) : size_(size) {}
  int size() const { return size_; }
  void Sync() {
    if (size_ == 1) return;
    const int generation = generation_.load(std::memory_order_acquire);
    if (arrived_.fetch_add(1, std::memory_order_acq_rel) + 1 == size_) {
      arrived_.store(0, std::memory_order_relaxed);
      generation_.fetch_add(1, std::memory_order_release);
      return;
    }
    for (int spins = 0; generation_.load(std::memory_order_acquire) == generation; ++spins) Wait(spins);
  }
  template <typename Body>
  void Launch(Body body) {  // body(thread index)
    std::vector<std::thread> pool;
    for (int t = 1; t < size_; ++t) pool.emplace_back(body, t);
    body(0);
    for (auto& thread : pool) thread.join();
  }

 private:
  int size_;
  std::atomic<int> arrived_{0}, generation_{0};
};

int HardwareThreads() {
  static const int count = std::max(1u, std::thread::hardware_concurrency());  // a system call: once
  return count;
}

// One spring's geometry from the positions and velocities (components `stride` apart) of
// its ends a and b: w = v_b - v_a, inv = 1 / length (1 at length 0), u = d * inv (so d
// itself at length 0, as safe_direction), extension e = length - rest, closing = w . u.
template <typename T>
struct Geometry {
  T u0, u1, u2, w0, w1, w2, inv, e, closing;
};

// With kKnown, inv is given (stored by a replay: no square root, no division) and
// length = |d|^2 inv.
template <typename T, bool kKnown = false>
inline Geometry<T> SpringGeometry(const T* x, const T* v, int64_t stride, int64_t a, int64_t b, T rest,
                                  T known = T(0)) {
  const T d0 = x[b] - x[a], d1 = x[stride + b] - x[stride + a], d2 = x[2 * stride + b] - x[2 * stride + a];
  Geometry<T> g;
  g.w0 = v[b] - v[a];
  g.w1 = v[stride + b] - v[stride + a];
  g.w2 = v[2 * stride + b] - v[2 * stride + a];
  T length;
  if (kKnown) {
    g.inv = known;
    length = (d0 * d0 + d1 * d1 + d2 * d2) * known;
  } else {
    length = std::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    g.inv = T(1) / (length > 0 ? length : T(1));
  }
  g.u0 = d0 * g.inv;
  g.u1 = d1 * g.inv;
  g.u2 = d2 * g.inv;
  g.e = length - rest;
  g.closing = g.w0 * g.u0 + g.w1 * g.u1 + g.w2 * g.u2;
  return g;
}

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
    const Geometry<T> g = SpringGeometry(x, v, n, a + j, b + j, rest[j]);
    const T m = ks[j] * g.e + kd[j] * g.closing;
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

// Blocks [lo, hi) of kRun particles (and the springs whose a lie in them) that thread t
// of `threads` handles.
inline void Share(const Layout& layout, int t, int threads, int64_t* lo, int64_t* hi) {
  const int64_t blocks = static_cast<int64_t>(layout.blocks.size());
  *lo = blocks * t / threads;
  *hi = blocks * (t + 1) / threads;
}

// The particles of block b: [b kRun, b kRun + BlockLength(b)).
inline int64_t BlockLength(const Layout& layout, int64_t b) { return std::min(kRun, layout.n - b * kRun); }

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

// What a step needs besides the state: flags resolved, shared parameters read once.
template <typename T>
struct StepConstants {
  T dt, g0, g1, g2, height;
  bool drag, gravity, ground;
  StepConstants(const Inputs<T>& p, const Config& config)
      : dt(static_cast<T>(config.dt)),
        g0(config.flags & kGravity ? p.gravity[0] : T(0)),
        g1(config.flags & kGravity ? p.gravity[1] : T(0)),
        g2(config.flags & kGravity ? p.gravity[2] : T(0)),
        height(config.flags & kGround ? p.height[0] : T(0)),
        drag(config.flags & kDrag),
        gravity(config.flags & kGravity),
        ground(config.flags & kGround) {}
};

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

// Cotangents accumulated over the steps of one member (pointers into the outputs).
template <typename T>
struct Cotangents {
  T *x, *v, *rest, *ks, *kd, *mass, *cdm, *gravity, *kg, *kgd, *height;
};

// What the reverse pass computes besides the state's cotangents: all parameter
// cotangents, but not the masses' unless asked; and with `lean` (ks and kd one value
// per member, no rest-length cotangent asked for) the springs' pass reads the scalars
// instead of per-spring ks and kd, and sums their cotangents per lane (`Partials`)
// instead of per spring: no stream of memory for them instead of five. `valid` (1 for a
// spring, 0 for padding, padded order) masks the kept 1 / lengths, or the springs when
// those are not kept.
template <typename T>
struct Wanted {
  bool mass = true, lean = false;
  T ks = T(0), kd = T(0);
  const T* valid = nullptr;
  const T* dt_m = nullptr;  // dt / m of every particle (the reverse pass then divides by none)
};

// One thread's sums for the parameters shared by all particles (gravity's three
// components, the ground height) and, in a lean reverse pass (`Wanted`), by all springs
// (ks, kd), kept per lane of a block: Partials[q * kRun + j] sums quantity q over
// particles (springs) i0 + j of every block (run) and step (a sum into one scalar would
// not vectorise).
template <typename T>
struct Partials {
  static constexpr int kGravity = 0, kHeight = 3, kKs = 4, kKd = 5;
  std::vector<T> lanes = std::vector<T>(6 * kRun, T(0));
  T Total(int q) const {
    T sum = 0;
    for (int64_t j = 0; j < kRun; ++j) sum += lanes[q * kRun + j];
    return sum;
  }
};

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

// The 16 instances Of::Fn<b0, b1, b2, b3> of a function template with four flags, as a
// table indexed b0 + 2 b1 + 4 b2 + 8 b3.
template <typename Of, size_t... I>
constexpr auto FlagTable(std::index_sequence<I...>) {
  return std::array{Of::template Fn<(I & 1) != 0, (I & 2) != 0, (I & 4) != 0, (I & 8) != 0>...};
}
template <typename Of>
auto Pick(bool b0, bool b1, bool b2, bool b3) {
  static constexpr auto table = FlagTable<Of>(std::make_index_sequence<16>{});
  return table[(b0 ? 1 : 0) + (b1 ? 2 : 0) + (b2 ? 4 : 0) + (b3 ? 8 : 0)];
}

template <typename T>
struct ReverseParticlesOf {
  template <bool kDragOn, bool kGravityOn, bool kGroundOn, bool kMass>
  static constexpr ReverseParticlesFn<T> Fn = ReverseParticles<T, kDragOn, kGravityOn, kGroundOn, kMass>;
};

template <typename T>
ReverseParticlesFn<T> PickReverseParticles(const StepConstants<T>& k, bool mass) {
  return Pick<ReverseParticlesOf<T>>(k.drag, k.gravity, k.ground, mass);
}

// Spring j's entries of the reverse rows (`width` apart): the cotangent of d, p c + q w +
// cl u, then of w, cc u (c: the force's cotangent).
template <typename T>
inline void ReverseRows(T* out, int64_t width, int64_t j, const Geometry<T>& g, T p, T q, T cl, T cc, T c0, T c1,
                        T c2) {
  out[j] = p * c0 + q * g.w0 + cl * g.u0;
  out[width + j] = p * c1 + q * g.w1 + cl * g.u1;
  out[2 * width + j] = p * c2 + q * g.w2 + cl * g.u2;
  out[3 * width + j] = g.u0 * cc;
  out[4 * width + j] = g.u1 * cc;
  out[5 * width + j] = g.u2 * cc;
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
    const Geometry<T> g = SpringGeometry<T, kKnown>(x, v, n, a + j, b + j, rest[j], kKnown ? inv_in[j] : T(0));
    const T u0 = g.u0, u1 = g.u1, u2 = g.u2, inv = g.inv;
    const T e = g.e, closing = g.closing;
    const T m = ks[j] * e + kd[j] * closing;
    const T c0 = gf[a + j] - gf[b + j], c1 = gf[n + a + j] - gf[n + b + j], c2 = gf[2 * n + a + j] - gf[2 * n + b + j];
    const T uc = u0 * c0 + u1 * c1 + u2 * c2;
    const T cc = kd[j] * uc;  // m = ks e + kd closing
    // with cu = m c + w cc (cotangent of u): u . cu = m uc + closing cc
    const T cl = ks[j] * uc - inv * (m * uc + closing * cc);  // u = d / length
    const T p = inv * m, q = inv * cc;
    cks[j] += e * uc;
    ckd[j] += closing * uc;
    crest[j] -= ks[j] * uc;
    ReverseRows(out, width, j, g, p, q, cl, cc, c0, c1, c2);
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
    const Geometry<T> g = SpringGeometry<T>(x, v, n, a + j, b + j, rest[j]);
    const T u0 = g.u0, u1 = g.u1, u2 = g.u2, inv = g.inv;
    const T e = g.e, closing = g.closing, on = valid[j];
    const T m = (ks * e + kd * closing) * on;  // zero for padding, as below
    const T c0 = gf[a + j] - gf[b + j], c1 = gf[n + a + j] - gf[n + b + j], c2 = gf[2 * n + a + j] - gf[2 * n + b + j];
    const T uc = (u0 * c0 + u1 * c1 + u2 * c2) * on;
    const T cc = kd * uc;
    const T cl = ks * uc - inv * (m * uc + closing * cc);
    const T p = inv * m, q = inv * cc;
    cks[j] += e * uc;
    ckd[j] += closing * uc;
    ReverseRows(out, width, j, g, p, q, cl, cc, c0, c1, c2);
  }
}

// One 64-byte vector of T (a GCC / Clang vector extension), for loops that keep sums
// in registers across their iterations (which the compilers vectorise only by
// reassociating, as their flags forbid). The helpers below take V = T too.
template <typename T>
struct Pack {
  typedef T V __attribute__((vector_size(64)));
  static constexpr int64_t kLanes = 64 / sizeof(T);
};

// Loads and stores of a Pack<T>::V (or a T) at any alignment.
template <typename V, typename T>
inline V Read(const T* at) {
  V value;
  std::memcpy(&value, at, sizeof(V));
  return value;
}
template <typename T, typename V>
inline void Write(T* at, const V& value) {
  std::memcpy(at, &value, sizeof(V));
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
  const V inv = Read<V>(inv_in);  // zero for padding: so are u, e, closing and all below
  const V u0 = d0 * inv, u1 = d1 * inv, u2 = d2 * inv;
  const V e = (d0 * d0 + d1 * d1 + d2 * d2) * inv - Read<V>(rest);
  const V closing = w0 * u0 + w1 * u1 + w2 * u2;
  const V m = ks * e + kd * closing;
  const V c0 = Read<V>(gf + a) - Read<V>(gf + b), c1 = Read<V>(gf + n + a) - Read<V>(gf + n + b),
          c2 = Read<V>(gf + 2 * n + a) - Read<V>(gf + 2 * n + b);
  const V uc = u0 * c0 + u1 * c1 + u2 * c2;
  const V cc = kd * uc;
  const V cl = ks * uc - inv * (m * uc + closing * cc);
  const V p = inv * m, q = inv * cc;
  if constexpr (kMasked) {
    sum_ks += counted * (e * uc);
    sum_kd += counted * (closing * uc);
  } else {
    sum_ks += e * uc;
    sum_kd += closing * uc;
  }
  Write(out, p * c0 + q * w0 + cl * u0);
  Write(out + width, p * c1 + q * w1 + cl * u1);
  Write(out + 2 * width, p * c2 + q * w2 + cl * u2);
  Write(out + 3 * width, u0 * cc);
  Write(out + 4 * width, u1 * cc);
  Write(out + 5 * width, u2 * cc);
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

// Threads for a call: members over threads when batched, one lattice split when large.
inline int Threads(int64_t batch, const Layout& layout) {
  if (batch > 1) return static_cast<int>(std::min<int64_t>(HardwareThreads(), batch));
  return layout.springs >= kSpringsForThreads ? std::min(2, HardwareThreads()) : 1;
}

// An array left uninitialised (std::vector would zero it on the calling thread first),
// from 1 MiB in huge pages where the system offers them: its first touch then costs a
// few page faults instead of one per 4 KiB (measured: ~1.5 us each here, 1.7 ms per
// backward call of the seed cloth; with huge pages 0.7 ms).
template <typename T>
struct Uninitialised {
  static constexpr size_t kHuge = size_t(2) << 20;
  struct Free {
    void operator()(T* p) const { std::free(p); }
  };
  std::unique_ptr<T, Free> values;
  size_t count = 0;
  void Allocate(size_t n) {
    const bool huge = n * sizeof(T) >= kHuge / 2;
    const size_t align = huge ? kHuge : 64, bytes = (n * sizeof(T) + align - 1) / align * align;
    values.reset(static_cast<T*>(std::aligned_alloc(align, bytes)));
    if (!values) throw std::bad_alloc();
#ifdef JAXSPRING_HUGE_PAGES
    if (huge) madvise(values.get(), bytes, MADV_HUGEPAGE);
#endif
    count = n;
  }
  T* data() { return values.get(); }
  bool empty() const { return count == 0; }
};

// Buffers of one team working on one member at a time.
template <typename T>
struct Workspace {
  // segment > 0: for backward calls; pipelined: two buffers of replayed states
  Workspace(const Layout& layout, int threads, int64_t segment, bool pipelined) : partials(threads) {
    forward.Allocate(layout, 3);
    if (segment > 0) {
      const int64_t n = layout.n;
      gf.resize(6 * n);  // two: the cotangent of the force at a step and at the step after
      // 1 / length of every spring at every replayed state, while it stays small
      const bool keep = segment * layout.padded * static_cast<int64_t>(sizeof(T)) <= kKeepBytes;
      for (int b = 0; b < (pipelined ? 2 : 1); ++b) {
        states[b].Allocate(segment * 6 * n);
        if (keep) invs[b].Allocate(segment * layout.padded);
      }
      reverse.Allocate(layout, 6);
      if (pipelined) second.Allocate(layout, 3);
    }
  }
  // the member's spring parameters in padded order (zero for padding), and their
  // cotangents cleared (the rows need no clearing: a pass writes every spring's entry
  // before it reads it, and entries without a spring stay zero); for a backward call dt
  // / m of every particle and the mask of real springs
  void Pad(const Layout& layout, const Inputs<T>& p, bool cotangents, double dt = 0) {
    for (auto* buffer : {&rest, &ks, &kd}) buffer->assign(layout.padded, T(0));
    for (const Run& r : layout.valid) {
      std::copy(p.rest + r.k, p.rest + r.k + r.len, rest.data() + r.a);
      std::copy(p.ks + r.k, p.ks + r.k + r.len, ks.data() + r.a);
      std::copy(p.kd + r.k, p.kd + r.k + r.len, kd.data() + r.a);
    }
    if (cotangents) {
      ct.assign(3 * layout.padded, T(0));
      dt_m.resize(layout.n);
      for (int64_t i = 0; i < layout.n; ++i) dt_m[i] = static_cast<T>(dt) / p.mass[i];
      wanted.dt_m = dt_m.data();
      valid.assign(layout.padded, T(0));
      for (const Run& r : layout.valid) std::fill(valid.begin() + r.a, valid.begin() + r.a + r.len, T(1));
      wanted.valid = valid.data();
    }
    if (wanted.lean) {
      wanted.ks = p.ks[0];
      wanted.kd = p.kd[0];
    }
  }
  Inputs<T> Padded(Inputs<T> p) const {
    p.rest = rest.data();
    p.ks = ks.data();
    p.kd = kd.data();
    return p;
  }
  Cotangents<T> Padded(Cotangents<T> out, int64_t padded) {
    out.rest = ct.data();
    out.ks = ct.data() + padded;
    out.kd = ct.data() + 2 * padded;
    return out;
  }
  // adds the real springs' cotangents (one sum for a scalar ks or kd), with the lanes'
  void Unpad(const Layout& layout, const Cotangents<T>& out, bool ks_scalar, bool kd_scalar) const {
    const int64_t padded = layout.padded;
    for (const Run& r : layout.valid) {
      for (int64_t j = 0; j < r.len; ++j) {
        out.rest[r.k + j] += ct[r.a + j];
        out.ks[ks_scalar ? 0 : r.k + j] += ct[padded + r.a + j];
        out.kd[kd_scalar ? 0 : r.k + j] += ct[2 * padded + r.a + j];
      }
    }
    for (const Partials<T>& sums : partials) {
      for (int c = 0; c < 3; ++c) out.gravity[c] += sums.Total(Partials<T>::kGravity + c);
      out.height[0] += sums.Total(Partials<T>::kHeight);
      out.ks[0] += sums.Total(Partials<T>::kKs);  // zero unless lean
      out.kd[0] += sums.Total(Partials<T>::kKd);
    }
  }
  Rows<T> forward, reverse;  // spring rows of the forward steps (and replays), of the reverse pass
  Rows<T> second;            // pipelined: those of the replays by the thread of the reverse pass
  // replayed states (and 1 / lengths), twice when pipelined; left uninitialised (a replay
  // writes every entry before the reverse pass reads it), so that their pages are first
  // touched, and zeroed by the system, on the replaying thread
  Uninitialised<T> states[2], invs[2];
  std::vector<T> gf, rest, ks, kd, ct, valid, dt_m;
  Wanted<T> wanted;
  std::vector<Partials<T>> partials;
};

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

// The reverse pass of one member from its stored states (one every config.stride steps):
// segment by segment from the last, replay the segment keeping every state, then run
// the reverse pass over it. Thread t of the team (which splits every pass by particles).
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

// The same for a small lattice on two threads: the second replays segment s - 1 while
// the first runs the reverse pass over segment s (double-buffered states). The first
// replays the last segment itself (no wait for the second to start), and any replay not
// yet begun. When it has waited for one longer than it takes to replay one itself, the
// second core is slow (busy, or descheduled by a hypervisor): it then replays every
// segment left itself, into buffers of its own.
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
    const StepConstants<T> k(p, config);
    Team solo(1);
    int parity = 0;
    const auto start = Clock::now();
    lengths[0] = replay(0, work.second, buffers[0], invs[0]);
    const auto patience = (Clock::now() - start) * config.stride / std::max<int64_t>(lengths[0], 1);
    // a test hook: let the other thread take replay 1, then give up on it at once
    const bool impatient = std::getenv("JAXSPRING_IMPATIENT") != nullptr;
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
  });
}

// The parameter buffers of a call, member by member. ks and kd hold one value per spring
// of every member, or one per member (a scalar: expanded here for the steps, and its
// cotangent is one sum per member).
template <ffi::DataType DT>
class Parameters {
 public:
  using T = ffi::NativeType<DT>;
  Parameters(int64_t batch, int64_t springs, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks, ffi::Buffer<DT> kd,
             ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm, ffi::Buffer<DT> gravity,
             ffi::Buffer<DT> kg, ffi::Buffer<DT> kgd, ffi::Buffer<DT> height)
      : batch_(batch), springs_(springs), rest_(rest), mass_(mass), free_(free), cdm_(cdm), gravity_(gravity),
        kg_(kg), kgd_(kgd), height_(height) {
    valid_ = static_cast<int64_t>(rest.element_count()) == batch * springs;
    for (auto [buffer, full, data, scalar] : {std::tuple{&ks, &ks_, &ks_data_, &ks_scalar_},
                                              std::tuple{&kd, &kd_, &kd_data_, &kd_scalar_}}) {
      const int64_t count = static_cast<int64_t>(buffer->element_count());
      *scalar = count == batch;
      valid_ = valid_ && (*scalar || count == batch * springs);
      *data = buffer->typed_data();  // per spring: read in place
      if (*scalar && valid_) {
        full->resize(batch * springs);
        for (int64_t i = 0; i < batch; ++i) {
          std::fill(full->begin() + i * springs, full->begin() + (i + 1) * springs, buffer->typed_data()[i]);
        }
        *data = full->data();
      }
    }
  }
  Parameters(const Parameters&) = delete;  // points into its own expansions
  Parameters& operator=(const Parameters&) = delete;
  bool valid() const { return valid_; }  // one rest length per spring, ks and kd as above
  bool ks_scalar() const { return ks_scalar_; }
  bool kd_scalar() const { return kd_scalar_; }
  Inputs<T> operator()(int64_t i) const {
    auto at = [&](const ffi::Buffer<DT>& buffer) {
      return buffer.typed_data() + i * (buffer.element_count() / batch_);
    };
    return {at(rest_), ks_data_ + i * springs_, kd_data_ + i * springs_, at(mass_), at(free_), at(cdm_),
            at(gravity_), at(kg_), at(kgd_), at(height_)};
  }

 private:
  int64_t batch_, springs_;
  ffi::Buffer<DT> rest_, mass_, free_, cdm_, gravity_, kg_, kgd_, height_;
  std::vector<T> ks_, kd_;  // the expansions of scalars
  const T *ks_data_ = nullptr, *kd_data_ = nullptr;
  bool ks_scalar_ = false, kd_scalar_ = false, valid_ = false;
};

// Runs work(member, workspace, team, thread) for every member: when batched, each
// thread takes the next member as it comes free (each alone), else one member by the
// whole team.
template <typename T, typename Work>
void ForMembers(int64_t batch, const Layout& layout, int64_t segment, bool pipelined, Work work) {
  const int threads = Threads(batch, layout);
  Team pool(threads);
  if (batch > 1) {
    std::atomic<int64_t> next{0};  // members go to whichever thread is free
    pool.Launch([&](int) {
      Team solo(1);
      Workspace<T> space(layout, 1, segment, false);
      for (int64_t i = next++; i < batch; i = next++) work(i, space, solo, 0);
    });
    return;
  }
  Workspace<T> space(layout, threads, segment, pipelined);
  pool.Launch([&](int t) { work(0, space, pool, t); });
}

// --- Batches: members side by side ---------------------------------------------------
// A forward call on a batch runs groups of Lanes<T>() members together, the member
// innermost (arrays (3, n, lanes)): every spring and particle update is then one aligned
// vector operation across the group, with no scratch rows (a spring's two particles are
// different, so their lanes never overlap). Threads take the next group as they come
// free.

template <typename T>
constexpr int64_t Lanes() {
  return 64 / sizeof(T);  // one 64-byte vector: 16 float32 or 8 float64 members
}

// What the members of a batch share, found when a call starts: the same rest lengths
// and ks, kd uniform over each member's springs (`springs`: a batch over those scalars,
// the usual sweep), the same particle parameters (`particles`). A group keeps shared
// values once instead of once per lane, which keeps its working set in the caches.
struct Sharing {
  bool springs = false, particles = false;
};

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

// A group's working set (64 bytes for a value in every lane, 4 or 8 for a shared one);
// above kGroupBytes (measured: a 60 x 60 cloth, nothing shared) it leaves the caches and
// members one by one (each thread its own) run faster.
constexpr int64_t kGroupBytes = 4 << 20;
inline int64_t GroupBytes(const Layout& layout, Sharing sharing) {
  const int64_t springs = sharing.springs ? 2 * layout.padded * 8 / 64 : 3 * layout.padded;
  const int64_t particles = sharing.particles ? 5 * layout.n * 8 / 64 : 5 * layout.n;
  return 64 * (6 * layout.n + 3 * (layout.n + layout.margin) + springs + particles);
}

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
  // then address both their ends from one base, and the loop keeps no ring index
  // (measured: batches of 64 seed cloths 5% faster, of jellies 15%).
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
        Geometry<T> g;
        T m;
        if (kShared) {  // valid is 1 for a spring (m exactly ks e + kd closing), 0 for padding
          g = SpringGeometry(x, v, nl, o + l, o + sl + l, rest[run.k + j]);
          m = valid[run.k + j] * (ks_lanes[l] * g.e + kd_lanes[l] * g.closing);
        } else {
          g = SpringGeometry(x, v, nl, o + l, o + sl + l, rest[k + l]);
          m = ks[k + l] * g.e + kd[k + l] * g.closing;
        }
        const T f0 = m * g.u0, f1 = m * g.u1, f2 = m * g.u2;
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

// Forward steps of a batch in groups (no stored states): members first .. first + L - 1
// (the last member repeated to fill a group) in, positions and velocities out.
template <typename T>
void AdvanceGroups(const Layout& layout, const Config& config, int64_t batch, Sharing sharing,
                   const std::function<Inputs<T>(int64_t)>& member, T* x, T* v) {
  constexpr int64_t L = Lanes<T>();
  const int64_t n = layout.n, groups = (batch + L - 1) / L;
  const int threads = static_cast<int>(std::min<int64_t>(HardwareThreads(), groups));
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

template <ffi::DataType DT>
ffi::Error Advance(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks,
                   ffi::Buffer<DT> kd, ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm,
                   ffi::Buffer<DT> gravity, ffi::Buffer<DT> kg, ffi::Buffer<DT> kgd, ffi::Buffer<DT> height,
                   ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets, int64_t steps, double dt,
                   int64_t flags, int64_t stride, ffi::ResultBuffer<DT> x_out, ffi::ResultBuffer<DT> v_out,
                   ffi::ResultBuffer<DT> stored) {
  using T = ffi::NativeType<DT>;
  auto made = MakeLayout(shape, offsets);
  if (made.has_error()) return made.error();
  const Layout& layout = *made.value();
  const int64_t n = layout.n, batch = x.element_count() / (3 * n);
  const Parameters<DT> parameters(batch, layout.springs, rest, ks, kd, mass, free, cdm, gravity, kg, kgd, height);
  if (!parameters.valid() || stride < 1) return ffi::Error::InvalidArgument("lattice: spring count or stride");
  const bool store = stored->element_count() > 0;
  const int64_t per_member = (steps + stride - 1) / stride * 6 * n;
  const Config config{steps, flags, dt, stride};
  std::copy(x.typed_data(), x.typed_data() + x.element_count(), x_out->typed_data());
  std::copy(v.typed_data(), v.typed_data() + v.element_count(), v_out->typed_data());
  const std::function<Inputs<T>(int64_t)> member = [&](int64_t i) { return parameters(i); };
  if (batch > 1 && !store && layout.ascending) {
    const Sharing sharing = FindSharing<T>(layout, batch, member);
    if (GroupBytes(layout, sharing) <= kGroupBytes) {
      AdvanceGroups<T>(layout, config, batch, sharing, member, x_out->typed_data(), v_out->typed_data());
      return ffi::Error::Success();
    }
  }
  ForMembers<T>(batch, layout, 0, false, [&](int64_t i, Workspace<T>& work, Team& team, int t) {
    const Inputs<T> p = parameters(i);
    if (t == 0) work.Pad(layout, p, false);
    team.Sync();
    Simulate(layout, work.Padded(p), config, x_out->typed_data() + i * 3 * n, v_out->typed_data() + i * 3 * n,
             work.forward, store ? stored->typed_data() + i * per_member : nullptr, team, t);
  });
  return ffi::Error::Success();
}

template <ffi::DataType DT>
ffi::Error AdvanceBackward(ffi::Buffer<DT> stored, ffi::Buffer<DT> v_final, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks,
                           ffi::Buffer<DT> kd, ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm,
                           ffi::Buffer<DT> gravity, ffi::Buffer<DT> kg, ffi::Buffer<DT> kgd, ffi::Buffer<DT> height,
                           ffi::Buffer<DT> ct_x, ffi::Buffer<DT> ct_v, ffi::Span<const int64_t> shape,
                           ffi::Span<const int64_t> offsets, int64_t steps, double dt, int64_t flags, int64_t stride,
                           int64_t needs, ffi::ResultBuffer<DT> out_x, ffi::ResultBuffer<DT> out_v, ffi::ResultBuffer<DT> out_rest,
                           ffi::ResultBuffer<DT> out_ks, ffi::ResultBuffer<DT> out_kd,
                           ffi::ResultBuffer<DT> out_mass, ffi::ResultBuffer<DT> out_cdm,
                           ffi::ResultBuffer<DT> out_gravity, ffi::ResultBuffer<DT> out_kg,
                           ffi::ResultBuffer<DT> out_kgd, ffi::ResultBuffer<DT> out_height) {
  using T = ffi::NativeType<DT>;
  auto made = MakeLayout(shape, offsets);
  if (made.has_error()) return made.error();
  const Layout& layout = *made.value();
  const int64_t n = layout.n, batch = ct_x.element_count() / (3 * n);
  const Parameters<DT> parameters(batch, layout.springs, rest, ks, kd, mass, free, cdm, gravity, kg, kgd, height);
  if (!parameters.valid() || stride < 1) return ffi::Error::InvalidArgument("lattice: spring count or stride");
  const Config config{steps, flags, dt, stride};
  const int64_t per_member = (steps + stride - 1) / stride * 6 * n;
  std::copy(ct_x.typed_data(), ct_x.typed_data() + ct_x.element_count(), out_x->typed_data());
  std::copy(ct_v.typed_data(), ct_v.typed_data() + ct_v.element_count(), out_v->typed_data());
  for (auto* buffer : {&out_rest, &out_ks, &out_kd, &out_mass, &out_cdm, &out_gravity, &out_kg, &out_kgd,
                       &out_height}) {
    std::fill((*buffer)->typed_data(), (*buffer)->typed_data() + (*buffer)->element_count(), T(0));
  }
  if (steps == 0) return ffi::Error::Success();
  // one small lattice: replay and reverse pass on two threads at once
  const bool pipelined = batch == 1 && Threads(batch, layout) == 1 && HardwareThreads() > 1 && steps > stride;
  ForMembers<T>(batch, layout, std::min(stride, steps), pipelined, [&](int64_t i, Workspace<T>& work, Team& team, int t) {
    auto at = [&](ffi::ResultBuffer<DT>& buffer) {
      return buffer->typed_data() + i * (buffer->element_count() / batch);
    };
    const Cotangents<T> out{at(out_x),       at(out_v),  at(out_rest), at(out_ks),  at(out_kd),    at(out_mass),
                            at(out_cdm),     at(out_gravity), at(out_kg), at(out_kgd), at(out_height)};
    const Inputs<T> p = parameters(i);
    work.partials[t] = Partials<T>();
    if (t == 0) {
      work.wanted.mass = needs & kNeedMass;
      work.wanted.lean = parameters.ks_scalar() && parameters.kd_scalar() && !(needs & kNeedRest);
      work.Pad(layout, p, true, dt);
    }
    team.Sync();
    const Inputs<T> padded = work.Padded(p);
    const Cotangents<T> inner = work.Padded(out, layout.padded);
    const T* states = stored.typed_data() + i * per_member;
    if (pipelined) {
      BackwardPipelined(layout, padded, config, states, v_final.typed_data(), inner, work);
    } else {
      BackwardMember(layout, padded, config, states, v_final.typed_data() + i * 3 * n, inner, work, team, t);
    }
    team.Sync();
    if (t == 0) work.Unpad(layout, out, parameters.ks_scalar(), parameters.kd_scalar());
  });
  return ffi::Error::Success();
}

}  // namespace

#define JAXSPRING_PARAMETER_ARGS(DT)                                                        \
  .Arg<ffi::Buffer<DT>>() /* rest */                                                        \
      .Arg<ffi::Buffer<DT>>() /* ks */                                                      \
      .Arg<ffi::Buffer<DT>>() /* kd */                                                      \
      .Arg<ffi::Buffer<DT>>() /* mass */                                                    \
      .Arg<ffi::Buffer<DT>>() /* free */                                                    \
      .Arg<ffi::Buffer<DT>>() /* cd * drag flag */                                          \
      .Arg<ffi::Buffer<DT>>() /* gravity */                                                 \
      .Arg<ffi::Buffer<DT>>() /* kg */                                                      \
      .Arg<ffi::Buffer<DT>>() /* kgd */                                                     \
      .Arg<ffi::Buffer<DT>>() /* ground height */

#define JAXSPRING_LATTICE_ATTRS                                                             \
  .Attr<ffi::Span<const int64_t>>("shape")                                                  \
      .Attr<ffi::Span<const int64_t>>("offsets")                                            \
      .Attr<int64_t>("steps")                                                               \
      .Attr<double>("dt")                                                                   \
      .Attr<int64_t>("flags")                                                               \
      .Attr<int64_t>("stride")

#define JAXSPRING_ADVANCE(name, DT)                                                         \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, Advance<DT>,                                          \
                                ffi::Ffi::Bind()                                            \
                                    .Arg<ffi::Buffer<DT>>()                                 \
                                    .Arg<ffi::Buffer<DT>>() JAXSPRING_PARAMETER_ARGS(DT)    \
                                        JAXSPRING_LATTICE_ATTRS.Ret<ffi::Buffer<DT>>()      \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>());

#define JAXSPRING_ADVANCE_BACKWARD(name, DT)                                                \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, AdvanceBackward<DT>,                                  \
                                ffi::Ffi::Bind()                                            \
                                    .Arg<ffi::Buffer<DT>>()                                 \
                                    .Arg<ffi::Buffer<DT>>() JAXSPRING_PARAMETER_ARGS(DT)    \
                                        .Arg<ffi::Buffer<DT>>()                             \
                                    .Arg<ffi::Buffer<DT>>() JAXSPRING_LATTICE_ATTRS         \
                                        .Attr<int64_t>("needs")                             \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>());

JAXSPRING_ADVANCE(JaxspringLatticeF32, ffi::F32)
JAXSPRING_ADVANCE(JaxspringLatticeF64, ffi::F64)
JAXSPRING_ADVANCE_BACKWARD(JaxspringLatticeBackwardF32, ffi::F32)
JAXSPRING_ADVANCE_BACKWARD(JaxspringLatticeBackwardF64, ffi::F64)
