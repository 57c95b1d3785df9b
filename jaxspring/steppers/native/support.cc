// What the native kernels share (support.h): the number of CPUs this process may use.
#include "support.h"

#include <algorithm>
#include <thread>

#if defined(__linux__)
#include <sched.h>
#endif

namespace jaxspring::native {

int UsableThreads() {
  static const int count = [] {  // system calls: once
#if defined(__linux__)
    cpu_set_t set;
    CPU_ZERO(&set);
    if (sched_getaffinity(0, sizeof(set), &set) == 0) {
      const int allowed = CPU_COUNT(&set);
      if (allowed > 0) return allowed;
    }
#endif
    return static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  }();
  return count;
}

}  // namespace jaxspring::native
