// The lattice kernel's XLA FFI entry points (forward and backward, float32 and float64):
// the parameter buffers of a call, member by member, and the threads that step them.

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <functional>
#include <tuple>
#include <vector>

#include "lattice.h"
#include "lattice_groups.h"
#include "lattice_reverse.h"
#include "lattice_step.h"
#include "lattice_threads.h"
#include "support.h"
#include "xla/ffi/api/ffi.h"

namespace jaxspring::native {
namespace {

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
void ForMembers(int64_t batch, const Layout& layout, int64_t segment, bool pipelined, int64_t test, Work work) {
  const int threads = Threads(batch, layout);
  Team pool(threads);
  if (batch > 1) {
    std::atomic<int64_t> next{0};  // members go to whichever thread is free
    pool.Launch([&](int) {
      Team solo(1);
      Workspace<T> space(layout, 1, segment, false, test);
      for (int64_t i = next++; i < batch; i = next++) work(i, space, solo, 0);
    });
    return;
  }
  Workspace<T> space(layout, threads, segment, pipelined, test);
  pool.Launch([&](int t) { work(0, space, pool, t); });
}

template <ffi::DataType DT>
ffi::Error Advance(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks,
                   ffi::Buffer<DT> kd, ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm,
                   ffi::Buffer<DT> gravity, ffi::Buffer<DT> kg, ffi::Buffer<DT> kgd, ffi::Buffer<DT> height,
                   ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets, int64_t steps, double dt,
                   int64_t flags, int64_t stride, int64_t test, ffi::ResultBuffer<DT> x_out, ffi::ResultBuffer<DT> v_out,
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
  const Config config{steps, flags, dt, stride, test};
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
  ForMembers<T>(batch, layout, 0, false, test, [&](int64_t i, Workspace<T>& work, Team& team, int t) {
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
                           int64_t test, int64_t needs, ffi::ResultBuffer<DT> out_x, ffi::ResultBuffer<DT> out_v, ffi::ResultBuffer<DT> out_rest,
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
  const Config config{steps, flags, dt, stride, test};
  const int64_t per_member = (steps + stride - 1) / stride * 6 * n;
  std::copy(ct_x.typed_data(), ct_x.typed_data() + ct_x.element_count(), out_x->typed_data());
  std::copy(ct_v.typed_data(), ct_v.typed_data() + ct_v.element_count(), out_v->typed_data());
  for (auto* buffer : {&out_rest, &out_ks, &out_kd, &out_mass, &out_cdm, &out_gravity, &out_kg, &out_kgd,
                       &out_height}) {
    std::fill((*buffer)->typed_data(), (*buffer)->typed_data() + (*buffer)->element_count(), T(0));
  }
  if (steps == 0) return ffi::Error::Success();
  // one small lattice: replay and reverse pass on two threads at once
  const bool pipelined = batch == 1 && Threads(batch, layout) == 1 && UsableThreads() > 1 && steps > stride;
  ForMembers<T>(batch, layout, std::min(stride, steps), pipelined, test, [&](int64_t i, Workspace<T>& work, Team& team, int t) {
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

// The entry points: any exception becomes an error for XLA (support.h).
template <ffi::DataType DT>
ffi::Error GuardedAdvance(ffi::Buffer<DT> x, ffi::Buffer<DT> v, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks,
                          ffi::Buffer<DT> kd, ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm,
                          ffi::Buffer<DT> gravity, ffi::Buffer<DT> kg, ffi::Buffer<DT> kgd, ffi::Buffer<DT> height,
                          ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets, int64_t steps, double dt,
                          int64_t flags, int64_t stride, int64_t test, ffi::ResultBuffer<DT> x_out,
                          ffi::ResultBuffer<DT> v_out, ffi::ResultBuffer<DT> stored) {
  return Guarded("lattice", [&] {
    return Advance<DT>(x, v, rest, ks, kd, mass, free, cdm, gravity, kg, kgd, height, shape, offsets, steps, dt, flags,
                       stride, test, x_out, v_out, stored);
  });
}

template <ffi::DataType DT>
ffi::Error GuardedAdvanceBackward(
    ffi::Buffer<DT> stored, ffi::Buffer<DT> v_final, ffi::Buffer<DT> rest, ffi::Buffer<DT> ks, ffi::Buffer<DT> kd,
    ffi::Buffer<DT> mass, ffi::Buffer<DT> free, ffi::Buffer<DT> cdm, ffi::Buffer<DT> gravity, ffi::Buffer<DT> kg,
    ffi::Buffer<DT> kgd, ffi::Buffer<DT> height, ffi::Buffer<DT> ct_x, ffi::Buffer<DT> ct_v,
    ffi::Span<const int64_t> shape, ffi::Span<const int64_t> offsets, int64_t steps, double dt, int64_t flags,
    int64_t stride, int64_t test, int64_t needs, ffi::ResultBuffer<DT> out_x, ffi::ResultBuffer<DT> out_v,
    ffi::ResultBuffer<DT> out_rest, ffi::ResultBuffer<DT> out_ks, ffi::ResultBuffer<DT> out_kd,
    ffi::ResultBuffer<DT> out_mass, ffi::ResultBuffer<DT> out_cdm, ffi::ResultBuffer<DT> out_gravity,
    ffi::ResultBuffer<DT> out_kg, ffi::ResultBuffer<DT> out_kgd, ffi::ResultBuffer<DT> out_height) {
  return Guarded("lattice backward", [&] {
    return AdvanceBackward<DT>(stored, v_final, rest, ks, kd, mass, free, cdm, gravity, kg, kgd, height, ct_x, ct_v,
                               shape, offsets, steps, dt, flags, stride, test, needs, out_x, out_v, out_rest, out_ks,
                               out_kd, out_mass, out_cdm, out_gravity, out_kg, out_kgd, out_height);
  });
}

}  // namespace
}  // namespace jaxspring::native

namespace ffi = xla::ffi;
using jaxspring::native::GuardedAdvance;
using jaxspring::native::GuardedAdvanceBackward;

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
      .Attr<int64_t>("stride")                                                              \
      .Attr<int64_t>("test")

#define JAXSPRING_ADVANCE(name, DT)                                                         \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, GuardedAdvance<DT>,                                   \
                                ffi::Ffi::Bind()                                            \
                                    .Arg<ffi::Buffer<DT>>()                                 \
                                    .Arg<ffi::Buffer<DT>>() JAXSPRING_PARAMETER_ARGS(DT)    \
                                        JAXSPRING_LATTICE_ATTRS.Ret<ffi::Buffer<DT>>()      \
                                    .Ret<ffi::Buffer<DT>>()                                 \
                                    .Ret<ffi::Buffer<DT>>());

#define JAXSPRING_ADVANCE_BACKWARD(name, DT)                                                \
  XLA_FFI_DEFINE_HANDLER_SYMBOL(name, GuardedAdvanceBackward<DT>,                           \
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
