// One physics step of a batch of Go1s in C MuJoCo, callable from inside a compiled JAX program (an XLA FFI
// target), so that a whole trial runs as one program: controller, physics step, record, tick after tick.
//
// The step is the arithmetic of cpgjax.sim.native.BatchPhysics.step, in the same order and precision:
//   controls <- torques (float32 -> float64), mjb_step on MuJoCo's thread pool, the failure test on the clock,
//   the warm start recovered as (qvel' - qvel) * (1/h), a failed instance put back to standing;
// then the controller's input row [physics state | sensor data | failed] as float32, as
// cpgjax.sim.native.NativeBackend packs it on the host.
//
// Built by cpgjax/sim/ffi_step.py against the headers of the installed mujoco and jaxlib wheels.

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include <mujoco/mjbatch.h>
#include <mujoco/mujoco.h>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

extern "C" {
// Where a batch state row (mjSTATE_INTEGRATION) keeps what the step reads and writes (RowOffsets in ffi_step.py).
struct Offsets {
  int nphysics;      // mjSTATE_FULLPHYSICS (clock, qpos, qvel), at the start of a row
  int qvel_at;       // qvel, within the row and the physics state alike
  int nv;
  int warmstart_at;  // qacc_warmstart
  int ctrl_at;
  int nsensordata;
};
}

namespace {

struct Stepper {
  mjBatch* batch = nullptr;
  int nsim = 0;
  int nstate = 0;  // length of a batch row (mjSTATE_INTEGRATION)
  Offsets at{};    // where a row keeps what the step reads and writes
  std::vector<int> actuator;  // control index of each motor, in motor order
  double timestep_s = 0.0;
  mjtNum* rows = nullptr;                   // the batch's state rows (nsim x nstate), stepped in place
  const mjtNum* step_sensordata = nullptr;  // refreshed by every step (nsim x nsensordata)
  std::vector<mjtNum> sensordata;           // the current sensor data (nsim x nsensordata)
  std::vector<mjtNum> standing_physics;
  std::vector<mjtNum> standing_sensordata;
  std::vector<mjtNum> before;  // the physics state before the step (nsim x nphysics)
};

// The step; torque (nsim x nact) float32; host_in (nsim x (nphysics + nsensordata + 1)) float32, or failed (nsim)
// bytes, or both, may be null. Returns the number of failed instances, or -1 where MuJoCo raised an error (its
// message in error).
int Step(Stepper* s, const float* torque, float* host_in, uint8_t* failed_out, char* error, int error_sz) {
  const int nact = static_cast<int>(s->actuator.size());
  for (int i = 0; i < s->nsim; ++i) {
    mjtNum* row = s->rows + static_cast<size_t>(i) * s->nstate;
    for (int j = 0; j < nact; ++j) row[s->at.ctrl_at + s->actuator[j]] = torque[i * nact + j];
    std::memcpy(s->before.data() + static_cast<size_t>(i) * s->at.nphysics, row,
                sizeof(mjtNum) * s->at.nphysics);
  }
  if (mjb_step(s->batch, nullptr, s->nsim, 1, mjSTAGE_NONE) > 0) {
    for (int i = 0; i < s->nsim; ++i) {
      if (mjb_status(s->batch)[i]) {
        std::snprintf(error, error_sz, "simulation %d: %s", i, mjb_error(s->batch, i));
        break;
      }
    }
    return -1;
  }
  std::memcpy(s->sensordata.data(), s->step_sensordata, sizeof(mjtNum) * s->sensordata.size());
  const double h = s->timestep_s;
  const double inv_h = 1.0 / h;
  int nfailed = 0;
  const int width = s->at.nphysics + s->at.nsensordata + 1;
  for (int i = 0; i < s->nsim; ++i) {
    mjtNum* row = s->rows + static_cast<size_t>(i) * s->nstate;
    const mjtNum* before = s->before.data() + static_cast<size_t>(i) * s->at.nphysics;
    mjtNum* sensordata = s->sensordata.data() + static_cast<size_t>(i) * s->at.nsensordata;
    const bool failed = std::fabs(row[0] - before[0] - h) > 0.5 * h;
    for (int k = 0; k < s->at.nv; ++k) {
      row[s->at.warmstart_at + k] = (row[s->at.qvel_at + k] - before[s->at.qvel_at + k]) * inv_h;
    }
    if (failed_out) failed_out[i] = failed;
    if (failed) {
      ++nfailed;
      std::memcpy(row, s->standing_physics.data() + static_cast<size_t>(i) * s->at.nphysics,
                  sizeof(mjtNum) * s->at.nphysics);
      std::memcpy(sensordata, s->standing_sensordata.data() + static_cast<size_t>(i) * s->at.nsensordata,
                  sizeof(mjtNum) * s->at.nsensordata);
      for (int k = 0; k < s->at.nv; ++k) row[s->at.warmstart_at + k] = 0.0;
    }
    if (host_in) {
      float* out = host_in + static_cast<size_t>(i) * width;
      for (int k = 0; k < s->at.nphysics; ++k) out[k] = static_cast<float>(row[k]);
      for (int k = 0; k < s->at.nsensordata; ++k) out[s->at.nphysics + k] = static_cast<float>(sensordata[k]);
      out[width - 1] = failed ? 1.0f : 0.0f;
    }
  }
  return nfailed;
}

ffi::Error BatchStep(ffi::Buffer<ffi::U32> handle, ffi::Buffer<ffi::F32> torque,
                     ffi::ResultBuffer<ffi::F32> host_in) {
  const uint32_t* h = handle.typed_data();
  auto* s = reinterpret_cast<Stepper*>(static_cast<uintptr_t>(h[0]) | (static_cast<uintptr_t>(h[1]) << 32));
  const size_t width = s->at.nphysics + s->at.nsensordata + 1;
  if (torque.element_count() != s->nsim * s->actuator.size() ||
      host_in->element_count() != s->nsim * width) {
    return ffi::Error::InvalidArgument("cpgjax_batch_step: buffer sizes do not match the stepper's batch");
  }
  char error[1000] = "";
  if (Step(s, torque.typed_data(), host_in->typed_data(), nullptr, error, sizeof(error)) < 0) {
    return ffi::Error::Internal(std::string("MuJoCo: ") + error);
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(cpgjax_batch_step, BatchStep,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());

extern "C" {

void* cpgjax_stepper_new(const mjModel* const* models, int nsim, int nthread, const Offsets* offsets,
                         const int* actuator, int nact, const double* standing_physics,
                         const double* standing_sensordata, char* error, int error_sz) {
  mjBatchConfig config;
  mjb_defaultConfig(&config);
  config.nthread = nthread;
  config.persistent = 0;
  mjBatch* batch = mjb_makeBatch(models[0], nsim, &config, error, error_sz);
  if (!batch) return nullptr;
  mjb_setModels(batch, models);
  int nsensordata = 0;
  const mjtNum* step_sensordata = static_cast<const mjtNum*>(mjb_output(batch, "sensordata", &nsensordata, nullptr));
  if (!step_sensordata || nsensordata != offsets->nsensordata) {
    std::snprintf(error, error_sz, "mjb_output(sensordata) gave %d numbers per simulation, expected %d",
                  nsensordata, offsets->nsensordata);
    mjb_deleteBatch(batch);
    return nullptr;
  }
  auto* s = new Stepper;
  s->batch = batch;
  s->nsim = nsim;
  s->nstate = mjb_nstate(batch);
  s->at = *offsets;
  s->actuator.assign(actuator, actuator + nact);
  s->timestep_s = models[0]->opt.timestep;
  s->rows = mjb_state(batch);
  s->step_sensordata = step_sensordata;
  s->standing_physics.assign(standing_physics, standing_physics + static_cast<size_t>(nsim) * s->at.nphysics);
  s->standing_sensordata.assign(standing_sensordata,
                                standing_sensordata + static_cast<size_t>(nsim) * s->at.nsensordata);
  s->sensordata = s->standing_sensordata;
  s->before.resize(static_cast<size_t>(nsim) * s->at.nphysics);
  return s;
}

int cpgjax_stepper_nstate(void* s) { return static_cast<Stepper*>(s)->nstate; }
double* cpgjax_stepper_rows(void* s) { return static_cast<Stepper*>(s)->rows; }
double* cpgjax_stepper_sensordata(void* s) { return static_cast<Stepper*>(s)->sensordata.data(); }
int cpgjax_stepper_step(void* s, const float* torque, uint8_t* failed, char* error, int error_sz) {
  return Step(static_cast<Stepper*>(s), torque, nullptr, failed, error, error_sz);
}
void cpgjax_stepper_delete(void* s) {
  auto* stepper = static_cast<Stepper*>(s);
  mjb_deleteBatch(stepper->batch);
  delete stepper;
}

}  // extern "C"
