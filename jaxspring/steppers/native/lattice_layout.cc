// The spring runs of a lattice (`Layout`, lattice.h), built from its shape and the
// lattice offsets of its spring families.

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <map>
#include <memory>
#include <mutex>
#include <utility>
#include <vector>

#include "lattice.h"

namespace jaxspring::native {
namespace {

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

}  // namespace

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

}  // namespace jaxspring::native
