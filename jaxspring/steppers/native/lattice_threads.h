// Threads of the lattice kernel: waits, the barrier of a team, how many threads a call
// takes.
#ifndef JAXSPRING_NATIVE_LATTICE_THREADS_H_
#define JAXSPRING_NATIVE_LATTICE_THREADS_H_

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <thread>
#include <vector>

#include "lattice.h"
#include "support.h"

namespace jaxspring::native {

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

// Thrown out of a barrier when another thread of the team has failed (its exception is
// the one that counts).
struct Abandoned {};

// A barrier for the threads of one call.
class Team {
 public:
  explicit Team(int size) : size_(size) {}
  int size() const { return size_; }
  // Waits for every thread of the team; throws Abandoned once one of them has failed
  // (it would never arrive).
  void Sync() {
    if (size_ == 1) return;
    const int generation = generation_.load(std::memory_order_acquire);
    if (arrived_.fetch_add(1, std::memory_order_acq_rel) + 1 == size_) {
      arrived_.store(0, std::memory_order_relaxed);
      generation_.fetch_add(1, std::memory_order_release);
      return;
    }
    for (int spins = 0; generation_.load(std::memory_order_acquire) == generation; ++spins) {
      if (failed_.load(std::memory_order_relaxed)) throw Abandoned();
      Wait(spins);
    }
  }
  // Runs body(thread index) on size() threads (this one is 0). An exception thrown by
  // one, or a thread that cannot start, is rethrown here once every thread started has
  // ended; the others leave at their next barrier.
  template <typename Body>
  void Launch(Body body) {
    std::vector<std::exception_ptr> failures(size_);
    auto run = [&](int t) {
      try {
        body(t);
      } catch (const Abandoned&) {
      } catch (...) {
        failures[t] = std::current_exception();
        failed_.store(true, std::memory_order_relaxed);
      }
    };
    std::vector<std::thread> pool;
    pool.reserve(size_ - 1);
    try {
      for (int t = 1; t < size_; ++t) pool.emplace_back(run, t);
    } catch (...) {
      failed_.store(true, std::memory_order_relaxed);
      for (auto& thread : pool) thread.join();
      throw;
    }
    run(0);
    for (auto& thread : pool) thread.join();
    for (const auto& failure : failures) {
      if (failure) std::rethrow_exception(failure);
    }
  }

 private:
  int size_;
  std::atomic<int> arrived_{0}, generation_{0};
  std::atomic<bool> failed_{false};
};

// Threads for a call: members over threads when batched, one lattice split when large.
inline int Threads(int64_t batch, const Layout& layout) {
  if (batch > 1) return static_cast<int>(std::min<int64_t>(UsableThreads(), batch));
  return layout.springs >= kSpringsForThreads ? std::min(2, UsableThreads()) : 1;
}

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_LATTICE_THREADS_H_
