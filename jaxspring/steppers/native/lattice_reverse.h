// The buffers of a team (`Workspace`) and the reverse pass of one lattice member
// (lattice_reverse.cc).
#ifndef JAXSPRING_NATIVE_LATTICE_REVERSE_H_
#define JAXSPRING_NATIVE_LATTICE_REVERSE_H_

#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#include "lattice.h"
#include "lattice_threads.h"

namespace jaxspring::native {

// Buffers of one team working on one member at a time.
template <typename T>
struct Workspace {
  // segment > 0: for backward calls; pipelined: two buffers of replayed states; test:
  // the call's kTest* bits
  Workspace(const Layout& layout, int threads, int64_t segment, bool pipelined, int64_t test = 0)
      : partials(threads) {
    forward.Allocate(layout, 3);
    if (segment > 0) {
      const int64_t n = layout.n;
      gf.resize(6 * n);  // two: the cotangent of the force at a step and at the step after
      // 1 / length of every spring at every replayed state, while it stays small
      const bool keep = segment * layout.padded * static_cast<int64_t>(sizeof(T)) <= kKeepBytes;
      for (int b = 0; b < (pipelined ? 2 : 1); ++b) {
        const size_t impossible = std::numeric_limits<size_t>::max() / 4 / sizeof(T);
        states[b].Allocate(test & kTestOutOfMemory ? impossible : segment * 6 * n);
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

// The reverse pass of one member from its stored states (one every config.stride steps):
// segment by segment from the last, replay the segment keeping every state, then run
// the reverse pass over it. Thread t of the team (which splits every pass by particles).
template <typename T>
void BackwardMember(const Layout& layout, const Inputs<T>& p, const Config& config, const T* stored,
                    const T* v_final, const Cotangents<T>& out, Workspace<T>& work, Team& team, int t);

// The same for a small lattice on two threads: the second replays segment s - 1 while
// the first runs the reverse pass over segment s (`work` made with `pipelined`).
template <typename T>
void BackwardPipelined(const Layout& layout, const Inputs<T>& p, const Config& config, const T* stored,
                       const T* v_final, const Cotangents<T>& out, Workspace<T>& work);

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_LATTICE_REVERSE_H_
