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
//
// Files: lattice.h (this: types and helpers shared by the passes), lattice_threads.h
// (barrier, waits, thread counts), lattice_layout.cc (the lattice's spring runs),
// lattice_step.h (forward steps), lattice_reverse.h/.cc (workspace, replays and the
// reverse pass), lattice_groups.h/.cc (forward batches side by side), lattice_ffi.cc
// (the XLA entry points). The spring law itself is spring_law.h.

#ifndef JAXSPRING_NATIVE_LATTICE_H_
#define JAXSPRING_NATIVE_LATTICE_H_

#if defined(__linux__)
#include <sys/mman.h>
#if defined(MADV_HUGEPAGE)
#define JAXSPRING_HUGE_PAGES
#endif
#endif

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <tuple>
#include <utility>
#include <vector>

#include "spring_law.h"
#include "support.h"
#include "xla/ffi/api/ffi.h"

// The loops below touch each index once; this tells the compiler so (the arrays are
// components of one buffer, which defeats its own alias analysis).
#if defined(__clang__)
#define JAXSPRING_INDEPENDENT _Pragma("clang loop vectorize(assume_safety)")
#elif defined(__GNUC__)
#define JAXSPRING_INDEPENDENT _Pragma("GCC ivdep")
#else
#define JAXSPRING_INDEPENDENT
#endif

namespace jaxspring::native {

constexpr int64_t kRun = 256;  // longest run of springs or particles processed at once
constexpr int64_t kDrag = 1, kGravity = 2, kGround = 4;  // flags
// `needs` of a backward call: the inputs whose cotangents are asked for (bit i: the i-th
// parameter input, rest = 0 .. height = 9); the others may be returned as zeros
constexpr int64_t kNeedRest = 1 << 0, kNeedMass = 1 << 3;
// Springs in one lattice above which a second thread pays for its two barriers a step:
// below, the cores spend more exchanging the cache lines at their boundary every step
// than the second thread saves (a 100 x 100 cloth, 39k springs, is above).
constexpr int64_t kSpringsForThreads = 30000;
// Largest buffer of replayed spring lengths kept for the reverse pass (per segment):
// while it stays in the cache it saves the reverse pass a square root and a division
// per spring; beyond, it leaves the cache and costs more memory traffic than it saves.
constexpr int64_t kKeepBytes = 1 << 20;
// `test` of a call (bits): hooks for the tests, zero otherwise. kTestImpatient: the
// backward call's first thread gives up on the second at its first replay (as when the
// second core is slow); kTestOutOfMemory: the backward call's buffers of replayed states
// are requested at an impossible size (the allocator fails, as it would for a lattice
// too large for memory).
constexpr int64_t kTestImpatient = 1, kTestOutOfMemory = 2;

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

// The layout of a (shape, offsets) pair, built once per process (calls repeat them).
ffi::ErrorOr<const Layout*> MakeLayout(ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets);

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
  int64_t stride;    // the forward call stores the state every `stride` steps
  int64_t test = 0;  // kTest* bits
};

// Blocks [lo, hi) of kRun particles (and the springs whose a lie in them) that thread t
// of `threads` handles.
inline void Share(const Layout& layout, int t, int threads, int64_t* lo, int64_t* hi) {
  const int64_t blocks = static_cast<int64_t>(layout.blocks.size());
  *lo = blocks * t / threads;
  *hi = blocks * (t + 1) / threads;
}

// The particles of block b: [b kRun, b kRun + BlockLength(b)).
inline int64_t BlockLength(const Layout& layout, int64_t b) { return std::min(kRun, layout.n - b * kRun); }

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

// The spring from particle a to b (spring_law.h) of positions x and velocities v whose
// components are `stride` apart; with SpringKnownAt, 1 / length is given.
template <typename T>
inline Spring<T> SpringAt(const T* x, const T* v, int64_t stride, int64_t a, int64_t b, T rest) {
  return Measure(x[b] - x[a], x[stride + b] - x[stride + a], x[2 * stride + b] - x[2 * stride + a], v[b] - v[a],
                 v[stride + b] - v[stride + a], v[2 * stride + b] - v[2 * stride + a], rest);
}
template <typename T>
inline Spring<T> SpringKnownAt(const T* x, const T* v, int64_t stride, int64_t a, int64_t b, T rest, T inv) {
  return MeasureKnown(x[b] - x[a], x[stride + b] - x[stride + a], x[2 * stride + b] - x[2 * stride + a],
                      v[b] - v[a], v[stride + b] - v[stride + a], v[2 * stride + b] - v[2 * stride + a], rest, inv);
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

// An array left uninitialised (std::vector would zero it on the calling thread first),
// from 1 MiB in huge pages where the system offers them: its first touch then costs a
// few page faults instead of one per 4 KiB. Throws std::bad_alloc when the memory is not
// there.
template <typename T>
struct Uninitialised {
  static constexpr size_t kHuge = size_t(2) << 20;
  struct Free {
    void operator()(T* p) const { std::free(p); }
  };
  std::unique_ptr<T, Free> values;
  size_t count = 0;
  void Allocate(size_t n) {
    if (n > std::numeric_limits<size_t>::max() / (2 * sizeof(T))) throw std::bad_alloc();
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

template <typename T>
constexpr int64_t Lanes() {
  return 64 / sizeof(T);  // one 64-byte vector: 16 float32 or 8 float64 members
}

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_LATTICE_H_
