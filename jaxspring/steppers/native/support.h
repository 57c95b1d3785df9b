// What the native kernels share besides the spring law: how many threads they may use,
// and the guard that turns a C++ exception into an error for XLA.
#ifndef JAXSPRING_NATIVE_SUPPORT_H_
#define JAXSPRING_NATIVE_SUPPORT_H_

#include <exception>
#include <new>
#include <string>
#include <system_error>
#include <utility>

#include "xla/ffi/api/ffi.h"

namespace jaxspring::native {

namespace ffi = xla::ffi;

// The CPUs this process may run on (its affinity mask where the system has one, else
// the hardware's thread count); at least 1. Read once per process.
int UsableThreads();

// Runs body() (which returns an ffi::Error) and returns its error, or an error for any
// exception it throws: an exception must not leave a handler (XLA calls it from C, and
// std::terminate would end the Python process).
template <typename Body>
ffi::Error Guarded(const char* kernel, Body&& body) noexcept {
  try {
    return std::forward<Body>(body)();
  } catch (const std::bad_alloc&) {
    return ffi::Error(ffi::ErrorCode::kResourceExhausted, std::string(kernel) + ": out of memory");
  } catch (const std::system_error& e) {  // std::thread could not start one
    return ffi::Error(ffi::ErrorCode::kResourceExhausted, std::string(kernel) + ": " + e.what());
  } catch (const std::exception& e) {
    return ffi::Error::Internal(std::string(kernel) + ": " + e.what());
  } catch (...) {
    return ffi::Error::Internal(std::string(kernel) + ": unknown exception");
  }
}

}  // namespace jaxspring::native

#endif  // JAXSPRING_NATIVE_SUPPORT_H_
