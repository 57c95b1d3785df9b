// Forward batches with their members side by side (lattice_groups.cc).
#ifndef JAXSPRING_NATIVE_LATTICE_GROUPS_H_
#define JAXSPRING_NATIVE_LATTICE_GROUPS_H_

#include <cstdint>
#include <functional>

#include "lattice.h"

namespace jaxspring::native {

// --- Batches: members side by side ---------------------------------------------------
// A forward call on a batch runs groups of Lanes<T>() members together, the member
// innermost (arrays (3, n, lanes)): every spring and particle update is then one aligned
// vector operation across the group, with no scratch rows (a spring's two particles are
// different, so their lanes never overlap). Threads take the next group as they come
// free.

// What the members of a batch share, found when a call starts: the same rest lengths
// and ks, kd uniform over each member's springs (`springs`: a batch over those scalars,
// the usual sweep), the same particle parameters (`particles`). A group keeps shared
// values once instead of once per lane, which keeps its working set in the caches.
struct Sharing {
  bool springs = false, particles = false;
};

template <typename T>
Sharing FindSharing(const Layout& layout, int64_t batch, const std::function<Inputs<T>(int64_t)>& member);

// A group's working set (64 bytes for a value in every lane, 4 or 8 for a shared one);
// above kGroupBytes it leaves the caches (a 60 x 60 cloth, nothing shared, is above)
// and members one by one (each thread its own) run faster.
constexpr int64_t kGroupBytes = 4 << 20;
inline int64_t GroupBytes(const Layout& layout, Sharing sharing) {
  const int64_t springs = sharing.springs ? 2 * layout.padded * 8 / 64 : 3 * layout.padded;
  const int64_t particles = sharing.particles ? 5 * layout.n * 8 / 64 : 5 * layout.n;
  return 64 * (6 * layout.n + 3 * (layout.n + layout.margin) + springs + particles);
}

// Forward steps of a batch in groups (no stored states), members in and out of x, v
// ((batch, 3, n) each).
template <typename T>
void AdvanceGroups(const Layout& layout, const Config& config, int64_t batch, Sharing sharing,
                   const std::function<Inputs<T>(int64_t)>& member, T* x, T* v);

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_LATTICE_GROUPS_H_
