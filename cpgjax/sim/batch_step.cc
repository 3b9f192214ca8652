// The physics step of a batch of Go1s in C MuJoCo, callable from inside a compiled JAX program (XLA FFI targets),
// so that a whole trial runs as one program: controller, physics step, record, tick after tick.
//
// The step is the arithmetic of cpgjax.sim.native_physics.BatchPhysics.step, in the same order and precision,
// instance by instance:
//   controls <- torques (float32 -> float64), then `substeps` physics steps each: one mj_step of the instance's
//   state (mjb_step on a one-thread MuJoCo batch, which traps MuJoCo's errors), the failure test on the clock, the
//   warm start recovered as (qvel' - qvel) * (1/h); a failed instance put back to standing;
// then the controller's input row [physics state | sensor data | failed] as float32, as
// cpgjax.sim.native.NativeBackend packs it on the host.
//
// Threads: a queue of instance steps, taken one at a time by nthread - 1 workers and by the caller while it waits
// for a result; each thread steps on its own one-thread MuJoCo batch (a lane), copying the instance's state row in
// and out, so every instance's arithmetic is the same whichever thread runs it. The whole batch's step is one call
// (cpgjax_batch_step). With the batch in two halves, one call (cpgjax_step_alternate) publishes one half's step
// and finishes the other's: between two such calls the caller's program computes the controller of the half just
// finished while the workers step the other, and in a finish the caller steps what the workers have not taken, of
// that half and then of the half just published (cpgjax_step_finish finishes the last).
//
// Profiling timers: MuJoCo reads the clock through mjcb_time to fill mjData.timer, twice for each of the 14 timers a
// Go1 step counts, and the mujoco Python bindings install a clock there with their first MjData. Nothing in cpgjax
// reads the timers, so while a stepper exists mjcb_time is a function that returns 0 (not null, which the bindings
// would replace with their clock at the next MjData they make); the callback found is put back when the last stepper
// goes. The results are the same bit for bit; the step is cheaper by the clock reads.
//
// Accounts: built with CPGJAX_STEPPER_ACCOUNTS defined (ffi_step.request_accounts), each thread counts what it did
// (LaneAccount): the steps it took, the time in them and in their mj_step, the time it waited, and apart the first
// step it took after other work (the caller: the first of each finish, after the program's own kernels; a worker: the
// first after a wait). A wait is counted when it ends. cpgjax_stepper_accounts reads them. Without the define the
// counting compiles to nothing.
//
// Built by cpgjax/sim/ffi_step.py against the headers of the installed mujoco and jaxlib wheels.

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
static inline void CpuPause() { _mm_pause(); }
#elif defined(__aarch64__) || defined(__arm__)
static inline void CpuPause() { __asm__ __volatile__("yield" ::: "memory"); }
#else
static inline void CpuPause() {}
#endif

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
  int substeps;  // physics steps per step (each of the models' timestep), the controls held
};
}

namespace {

mjtNum NoClock() { return 0; }

// Holds mjcb_time at NoClock while any stepper exists (see the top of this file).
class TimersOff {
 public:
  TimersOff() {
    std::lock_guard<std::mutex> lock(mu_);
    if (holders_++ == 0) {
      saved_ = mjcb_time;
      mjcb_time = NoClock;
    }
  }
  ~TimersOff() {
    std::lock_guard<std::mutex> lock(mu_);
    if (--holders_ == 0 && mjcb_time == NoClock) mjcb_time = saved_;
  }
  TimersOff(const TimersOff&) = delete;
  TimersOff& operator=(const TimersOff&) = delete;

 private:
  static inline std::mutex mu_;
  static inline int holders_ = 0;
  static inline mjfTime saved_ = nullptr;
};

#ifdef CPGJAX_STEPPER_ACCOUNTS
constexpr bool kAccounts = true;
#else
constexpr bool kAccounts = false;
#endif

int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

// What one thread did (see the top of this file). Written by its thread only; read after the steps are finished.
struct alignas(64) LaneAccount {
  enum Field { kSteps, kStepNs, kMjStepNs, kWaitNs, kFirstSteps, kFirstStepNs, kFinishes, kFields };
  std::atomic<int64_t> field[kFields] = {};
  bool first = true;  // the next step is the first after other work

  void Add(Field f, int64_t v) {
    if constexpr (kAccounts) field[f].store(field[f].load(std::memory_order_relaxed) + v, std::memory_order_relaxed);
  }
  void Step(int64_t step_ns, int64_t mj_step_ns) {
    Add(kSteps, 1);
    Add(kStepNs, step_ns);
    Add(kMjStepNs, mj_step_ns);
    if (first) {
      Add(kFirstSteps, 1);
      Add(kFirstStepNs, step_ns);
      first = false;
    }
  }
};

int64_t AccountNow() { return kAccounts ? NowNs() : 0; }

// One thread's MuJoCo batch: every instance's model, one mjData, run on the calling thread only.
struct Lane {
  mjBatch* batch = nullptr;
  mjtNum* state = nullptr;              // its state rows (nsim x nstate)
  mjWarningStat* warning = nullptr;     // its warning counters (nsim x mjNWARNING)
  const mjtNum* sensordata = nullptr;   // refreshed by every step (nsim x nsensordata)
};

// Spin until pred holds or about 50 µs pass; return whether it holds.
template <typename Pred>
bool SpinUntil(Pred pred) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::microseconds(50);
  for (int k = 0;; ++k) {
    if (pred()) return true;
    if ((k & 63) == 63 && std::chrono::steady_clock::now() > deadline) return false;
    CpuPause();
  }
}

struct Stepper {
  TimersOff timers_off;  // first: the lanes' steps below run with MuJoCo's timers off
  int nsim = 0;
  int nstate = 0;  // length of a state row (mjSTATE_INTEGRATION)
  Offsets at{};    // where a row keeps what the step reads and writes
  std::vector<int> actuator;  // control index of each motor, in motor order
  double timestep_s = 0.0;
  std::vector<mjtNum> rows;                  // the state each instance's next step starts from (nsim x nstate)
  std::vector<mjWarningStat> warning;        // MuJoCo's warning counters of each instance (nsim x mjNWARNING)
  std::vector<mjtNum> sensordata;            // the current sensor data (nsim x nsensordata)
  std::vector<mjtNum> standing_physics;
  std::vector<mjtNum> standing_sensordata;
  std::vector<mjtNum> before;                // the physics state before the step (nsim x nphysics)
  std::vector<float> host_in;                // the controller's input after the step (nsim x width)
  std::vector<uint8_t> failed;               // the step failed and the instance was reset (nsim)
  std::vector<uint8_t> status;               // MuJoCo raised an error during the step (nsim)
  std::vector<std::string> errors;           // its message (nsim)
  std::vector<Lane> lanes;                   // one per thread; the caller's is the last
  std::unique_ptr<LaneAccount[]> accounts;   // one per lane

  // The queue of instance steps: item k steps instance k mod nsim. Parts of the batch are published in their
  // order in the batch, so that the items of a part are the instances of the part.
  std::atomic<int64_t> published{0};  // items [0, published) may be taken
  std::atomic<int64_t> next{0};       // the next item to take
  std::vector<int> part_of;           // the first instance of the part whose item steps instance i (nsim)
  std::unique_ptr<std::atomic<int>[]> remaining;  // items of the part that starts at instance i still to do (nsim)
  std::atomic<int64_t> done{0};       // items stepped
  std::atomic<int> parked{0};         // workers waiting for items
  std::atomic<bool> stop{false};
  std::mutex mu;                      // guards parking and waking
  std::condition_variable wake;
  std::vector<std::thread> workers;

  int width() const { return at.nphysics + at.nsensordata + 1; }

  // Instance i's step on lane t, counted in its account.
  void StepOne(int t, int i) {
    const int64_t start_ns = AccountNow();
    const int64_t mj_step_ns = StepInstance(t, i);
    if constexpr (kAccounts) accounts[t].Step(NowNs() - start_ns, mj_step_ns);
  }

  // Instance i's step on lane t (its substeps); returns the duration of its mj_steps in ns (0 without accounts).
  int64_t StepInstance(int t, int i) {
    Lane& lane = lanes[t];
    mjtNum* row = rows.data() + static_cast<size_t>(i) * nstate;
    mjWarningStat* warn = warning.data() + static_cast<size_t>(i) * mjNWARNING;
    mjtNum* sd = sensordata.data() + static_cast<size_t>(i) * at.nsensordata;
    mjtNum* prev = before.data() + static_cast<size_t>(i) * at.nphysics;
    const double h = timestep_s;
    const double inv_h = 1.0 / h;
    int64_t mj_step_ns = 0;
    bool fail = false;
    for (int sub = 0; sub < at.substeps && !fail; ++sub) {
      if (sub > 0) std::memcpy(prev, row, sizeof(mjtNum) * at.nphysics);
      std::memcpy(lane.state + static_cast<size_t>(i) * nstate, row, sizeof(mjtNum) * nstate);
      std::memcpy(lane.warning + static_cast<size_t>(i) * mjNWARNING, warn, sizeof(mjWarningStat) * mjNWARNING);
      const int64_t mj_start_ns = AccountNow();
      const int nerror = mjb_step(lane.batch, &i, 1, 1, mjSTAGE_NONE);
      mj_step_ns += AccountNow() - mj_start_ns;
      if (nerror > 0) {
        status[i] = 1;
        errors[i] = mjb_error(lane.batch, i);
        return mj_step_ns;
      }
      std::memcpy(row, lane.state + static_cast<size_t>(i) * nstate, sizeof(mjtNum) * nstate);
      std::memcpy(warn, lane.warning + static_cast<size_t>(i) * mjNWARNING, sizeof(mjWarningStat) * mjNWARNING);
      std::memcpy(sd, lane.sensordata + static_cast<size_t>(i) * at.nsensordata, sizeof(mjtNum) * at.nsensordata);
      fail = std::fabs(row[0] - prev[0] - h) > 0.5 * h;
      for (int k = 0; k < at.nv; ++k) row[at.warmstart_at + k] = (row[at.qvel_at + k] - prev[at.qvel_at + k]) * inv_h;
    }
    failed[i] = fail;
    if (fail) {
      std::memcpy(row, standing_physics.data() + static_cast<size_t>(i) * at.nphysics, sizeof(mjtNum) * at.nphysics);
      std::memcpy(sd, standing_sensordata.data() + static_cast<size_t>(i) * at.nsensordata,
                  sizeof(mjtNum) * at.nsensordata);
      for (int k = 0; k < at.nv; ++k) row[at.warmstart_at + k] = 0.0;
    }
    float* out = host_in.data() + static_cast<size_t>(i) * width();
    for (int k = 0; k < at.nphysics; ++k) out[k] = static_cast<float>(row[k]);
    for (int k = 0; k < at.nsensordata; ++k) out[at.nphysics + k] = static_cast<float>(sd[k]);
    out[width() - 1] = fail ? 1.0f : 0.0f;
    return mj_step_ns;
  }

  // Take the next item if there is one and step it on lane t; returns whether there was one.
  bool TakeOne(int t) {
    int64_t k = next.load(std::memory_order_relaxed);
    while (k < published.load(std::memory_order_acquire)) {
      if (next.compare_exchange_weak(k, k + 1, std::memory_order_acq_rel)) {
        const int i = static_cast<int>(k % nsim);
        StepOne(t, i);
        remaining[part_of[i]].fetch_sub(1, std::memory_order_acq_rel);
        done.fetch_add(1, std::memory_order_acq_rel);
        return true;
      }
    }
    return false;
  }

  // Worker t: take items; after about 50 µs without any, park until a part is published.
  void Worker(int t) {
    while (!stop.load(std::memory_order_acquire)) {
      if (TakeOne(t)) continue;
      auto ready = [this] {
        return stop.load(std::memory_order_acquire) || next.load() < published.load();
      };
      const int64_t wait_start_ns = AccountNow();
      if (!SpinUntil(ready)) {
        std::unique_lock<std::mutex> lock(mu);
        parked.fetch_add(1);
        wake.wait(lock, ready);
        parked.fetch_sub(1);
      }
      if constexpr (kAccounts) {
        accounts[t].Add(LaneAccount::kWaitNs, NowNs() - wait_start_ns);
        accounts[t].first = true;
      }
    }
  }

  // Publish the step of instances [first, last) with their torques (last - first) x nact float32: the workers
  // start at once. The part's previous step must be finished.
  void Publish(int first, int last, const float* torque) {
    const int nact = static_cast<int>(actuator.size());
    for (int i = first; i < last; ++i) {
      mjtNum* row = rows.data() + static_cast<size_t>(i) * nstate;
      for (int j = 0; j < nact; ++j) row[at.ctrl_at + actuator[j]] = torque[(i - first) * nact + j];
      std::memcpy(before.data() + static_cast<size_t>(i) * at.nphysics, row, sizeof(mjtNum) * at.nphysics);
      status[i] = 0;
      part_of[i] = first;
    }
    remaining[first].store(last - first, std::memory_order_relaxed);
    // Sequentially consistent with the parking worker's count and check: one of the two sees the other.
    published.fetch_add(last - first);
    if (parked.load() > 0) {
      std::lock_guard<std::mutex> lock(mu);
      wake.notify_all();
    }
  }

  // Take items on the caller's lane until every published one is stepped, then start the queue again at the
  // batch's first instance: after an error nothing is left running while the caller reads or writes the rows, and
  // the next program's parts are published in order again.
  void Drain() {
    while (done.load(std::memory_order_acquire) < published.load()) {
      if (!TakeOne(static_cast<int>(lanes.size()) - 1)) CpuPause();
    }
    const int64_t whole = (published.load() + nsim - 1) / nsim * nsim;
    next.store(whole);
    published.store(whole);
    done.store(whole);
  }

  // Take items on the caller's lane until the part [first, last) is stepped (the items of a part published after
  // it as well, while its last ones run on workers); returns the number of its instances in which MuJoCo raised
  // an error (the first one's message in error).
  int Finish(int first, int last, char* error, int error_sz) {
    const int lane = static_cast<int>(lanes.size()) - 1;
    LaneAccount& account = accounts[lane];
    const int64_t start_ns = AccountNow();
    const int64_t stepped_before_ns = kAccounts ? account.field[LaneAccount::kStepNs].load() : 0;
    if constexpr (kAccounts) account.first = true;
    for (int idle = 0; remaining[first].load(std::memory_order_acquire) > 0;) {
      if (TakeOne(lane)) {
        idle = 0;
      } else if (++idle < 2000) {
        CpuPause();
      } else {
        std::this_thread::yield();  // a worker holds its last instances: leave the core to it if it needs this one
      }
    }
    if constexpr (kAccounts) {
      const int64_t stepped_ns = account.field[LaneAccount::kStepNs].load(std::memory_order_relaxed);
      account.Add(LaneAccount::kWaitNs, NowNs() - start_ns - (stepped_ns - stepped_before_ns));
      account.Add(LaneAccount::kFinishes, 1);
    }
    int nerror = 0;
    for (int i = first; i < last; ++i) {
      if (status[i] && nerror++ == 0) std::snprintf(error, error_sz, "simulation %d: %s", i, errors[i].c_str());
    }
    return nerror;
  }

  ~Stepper() {
    if (!lanes.empty()) Drain();
    {
      std::lock_guard<std::mutex> lock(mu);
      stop.store(true, std::memory_order_release);
    }
    wake.notify_all();
    for (auto& w : workers) w.join();
    for (auto& lane : lanes) mjb_deleteBatch(lane.batch);
  }
};

Stepper* FromHandle(ffi::Buffer<ffi::U32> handle) {
  const uint32_t* h = handle.typed_data();
  return reinterpret_cast<Stepper*>(static_cast<uintptr_t>(h[0]) | (static_cast<uintptr_t>(h[1]) << 32));
}

void CopyRows(const Stepper* s, int first, int last, float* out) {
  std::memcpy(out, s->host_in.data() + static_cast<size_t>(first) * s->width(),
              sizeof(float) * static_cast<size_t>(last - first) * s->width());
}

// Why the part [lo, hi) cannot be published now ("" if it can): parts are published in their order in the batch.
std::string CannotPublish(const Stepper* s, int32_t lo, int32_t hi, size_t ntorque) {
  if (lo < 0 || hi > s->nsim || lo >= hi) return "instances outside the batch";
  if (s->published.load(std::memory_order_relaxed) % s->nsim != lo) return "a part published out of order";
  if (ntorque != static_cast<size_t>(hi - lo) * s->actuator.size()) return "torques not of the part's size";
  return "";
}

// Why the part [lo, hi) cannot be finished into a buffer of `nhost_in` floats ("" if it can).
std::string CannotFinish(const Stepper* s, int32_t lo, int32_t hi, size_t nhost_in) {
  if (lo < 0 || hi > s->nsim || lo >= hi) return "instances outside the batch";
  if (nhost_in != static_cast<size_t>(hi - lo) * s->width()) return "input rows not of the part's size";
  return "";
}

ffi::Error Failed(Stepper* s, const char* target, const std::string& why) {
  s->Drain();
  return ffi::Error::InvalidArgument(std::string(target) + ": " + why);
}

ffi::Error MuJoCoError(Stepper* s, const char* error) {
  s->Drain();
  return ffi::Error::Internal(std::string("MuJoCo: ") + error);
}

// The whole batch's step: torque (nsim x nact) -> host_in (nsim x width).
ffi::Error BatchStep(ffi::Buffer<ffi::U32> handle, ffi::Buffer<ffi::F32> torque,
                     ffi::ResultBuffer<ffi::F32> host_in) {
  Stepper* s = FromHandle(handle);
  std::string why = CannotPublish(s, 0, s->nsim, torque.element_count());
  if (why.empty()) {
    s->Publish(0, s->nsim, torque.typed_data());
    why = CannotFinish(s, 0, s->nsim, host_in->element_count());
  }
  if (!why.empty()) return Failed(s, "cpgjax_batch_step", why);
  char error[1000] = "";
  if (s->Finish(0, s->nsim, error, sizeof(error)) > 0) return MuJoCoError(s, error);
  CopyRows(s, 0, s->nsim, host_in->typed_data());
  return ffi::Error::Success();
}

// The batch in two halves of `half` instances: publish the step of half `which` (0: instances [0, half), 1: the
// rest) with torque (half x nact), then finish the other half's step, if one is published: its rows
// [physics state | sensor data | failed] after its last step (half x width).
ffi::Error StepAlternate(ffi::Buffer<ffi::U32> handle, ffi::Buffer<ffi::F32> torque, ffi::Buffer<ffi::S32> which,
                         ffi::ResultBuffer<ffi::F32> host_in, int32_t half) {
  Stepper* s = FromHandle(handle);
  const int32_t part = which.typed_data()[0];
  std::string why;
  if (2 * half != s->nsim || (part != 0 && part != 1)) {
    why = "not one of two halves of the batch";
  } else {
    why = CannotFinish(s, (1 - part) * half, (2 - part) * half, host_in->element_count());
    if (why.empty()) why = CannotPublish(s, part * half, (part + 1) * half, torque.element_count());
  }
  if (!why.empty()) return Failed(s, "cpgjax_step_alternate", why);
  s->Publish(part * half, (part + 1) * half, torque.typed_data());
  char error[1000] = "";
  if (s->Finish((1 - part) * half, (2 - part) * half, error, sizeof(error)) > 0) return MuJoCoError(s, error);
  CopyRows(s, (1 - part) * half, (2 - part) * half, host_in->typed_data());
  return ffi::Error::Success();
}

// Finish the step of the part [lo, hi): host_in ((hi - lo) x width). `after` is not read: what computes it runs
// before this call.
ffi::Error StepFinish(ffi::Buffer<ffi::U32> handle, ffi::Buffer<ffi::F32> after, ffi::ResultBuffer<ffi::F32> host_in,
                      int32_t lo, int32_t hi) {
  Stepper* s = FromHandle(handle);
  const std::string why = CannotFinish(s, lo, hi, host_in->element_count());
  if (!why.empty()) return Failed(s, "cpgjax_step_finish", why);
  char error[1000] = "";
  if (s->Finish(lo, hi, error, sizeof(error)) > 0) return MuJoCoError(s, error);
  CopyRows(s, lo, hi, host_in->typed_data());
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(cpgjax_batch_step, BatchStep,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(cpgjax_step_alternate, StepAlternate,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int32_t>("half"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(cpgjax_step_finish, StepFinish,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::Buffer<ffi::F32>>()
                                  .Ret<ffi::Buffer<ffi::F32>>()
                                  .Attr<int32_t>("lo")
                                  .Attr<int32_t>("hi"));

extern "C" {

void* cpgjax_stepper_new(const mjModel* const* models, int nsim, int nthread, const Offsets* offsets,
                         const int* actuator, int nact, const double* standing_physics,
                         const double* standing_sensordata, char* error, int error_sz) {
  auto* s = new Stepper;
  s->nsim = nsim;
  nthread = nthread < 1 ? 1 : (nthread > nsim ? nsim : nthread);
  for (int t = 0; t < nthread; ++t) {
    mjBatchConfig config;
    mjb_defaultConfig(&config);
    config.nthread = 1;  // the lane's steps run on the thread that calls them
    config.persistent = 0;
    mjBatch* batch = mjb_makeBatch(models[0], nsim, &config, error, error_sz);
    if (!batch) {
      delete s;
      return nullptr;
    }
    s->lanes.push_back(Lane{batch, mjb_state(batch), mjb_warning(batch), nullptr});
    mjb_setModels(batch, models);
    int nsensordata = 0;
    s->lanes.back().sensordata = static_cast<const mjtNum*>(mjb_output(batch, "sensordata", &nsensordata, nullptr));
    if (!s->lanes.back().sensordata || nsensordata != offsets->nsensordata) {
      std::snprintf(error, error_sz, "mjb_output(sensordata) gave %d numbers per simulation, expected %d",
                    nsensordata, offsets->nsensordata);
      delete s;
      return nullptr;
    }
  }
  s->nstate = mjb_nstate(s->lanes[0].batch);
  s->at = *offsets;
  s->actuator.assign(actuator, actuator + nact);
  s->timestep_s = models[0]->opt.timestep;
  s->rows.assign(s->lanes[0].state, s->lanes[0].state + static_cast<size_t>(nsim) * s->nstate);
  s->warning.assign(static_cast<size_t>(nsim) * mjNWARNING, mjWarningStat{});
  s->standing_physics.assign(standing_physics, standing_physics + static_cast<size_t>(nsim) * s->at.nphysics);
  s->standing_sensordata.assign(standing_sensordata,
                                standing_sensordata + static_cast<size_t>(nsim) * s->at.nsensordata);
  s->sensordata = s->standing_sensordata;
  s->before.resize(static_cast<size_t>(nsim) * s->at.nphysics);
  s->host_in.resize(static_cast<size_t>(nsim) * s->width());
  s->failed.assign(nsim, 0);
  s->status.assign(nsim, 0);
  s->errors.resize(nsim);
  s->part_of.assign(nsim, -1);
  s->remaining.reset(new std::atomic<int>[nsim]);
  s->accounts.reset(new LaneAccount[nthread]);
  for (int i = 0; i < nsim; ++i) s->remaining[i].store(0);
  for (int t = 0; t < nthread - 1; ++t) s->workers.emplace_back([s, t] { s->Worker(t); });
  return s;
}

int cpgjax_stepper_nstate(void* s) { return static_cast<Stepper*>(s)->nstate; }
int cpgjax_stepper_nthread(void* s) { return static_cast<int>(static_cast<Stepper*>(s)->lanes.size()); }
double* cpgjax_stepper_rows(void* s) { return static_cast<Stepper*>(s)->rows.data(); }
double* cpgjax_stepper_sensordata(void* s) { return static_cast<Stepper*>(s)->sensordata.data(); }

// The whole batch's step from the host: torque (nsim x nact) float32; failed (nsim) bytes. Returns the number of
// failed instances, or -1 where MuJoCo raised an error (its message in error).
int cpgjax_stepper_step(void* p, const float* torque, uint8_t* failed, char* error, int error_sz) {
  auto* s = static_cast<Stepper*>(p);
  s->Drain();  // what a failed program left published
  s->Publish(0, s->nsim, torque);
  if (s->Finish(0, s->nsim, error, error_sz) > 0) {
    s->Drain();
    return -1;
  }
  int nfailed = 0;
  for (int i = 0; i < s->nsim; ++i) nfailed += failed[i] = s->failed[i];
  return nfailed;
}

// Each lane's account (see the top of this file) into out (nlanes x LaneAccount::kFields: steps, ns in steps, ns in
// their mj_step, ns waiting, first steps after other work, ns in them, finishes; the caller's lane last), then zeroed
// if reset. Returns the number of lanes, or 0 where the library counts nothing (built without accounts). Read while
// no step runs.
int cpgjax_stepper_accounts(void* p, int64_t* out, int reset) {
  if (!kAccounts) return 0;
  auto* s = static_cast<Stepper*>(p);
  const int nlanes = static_cast<int>(s->lanes.size());
  for (int t = 0; t < nlanes; ++t) {
    for (int f = 0; f < LaneAccount::kFields; ++f) {
      out[t * LaneAccount::kFields + f] = s->accounts[t].field[f].load();
      if (reset) s->accounts[t].field[f].store(0);
    }
  }
  return nlanes;
}

void cpgjax_stepper_delete(void* s) { delete static_cast<Stepper*>(s); }

}  // extern "C"
