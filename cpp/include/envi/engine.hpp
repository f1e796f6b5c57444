// The closed loop, batched: runs are split into blocks of columns, each block steps the model
// (one GEMM per layer), decodes and post-processes the next state, asks the controller and slides
// its window. Semantics are those of envi_py.simulate.rollout.
#pragma once
#include <cstdint>

#include "envi/controller.hpp"
#include "envi/model.hpp"

namespace envi {

// Receives every row of every run, block by block. Calls for one block come from one thread;
// different blocks may be in flight on different threads at once.
class Sink {
 public:
  virtual ~Sink() = default;
  // A block of `count` runs starting at global run `first_run` begins on thread `thread`.
  virtual void begin(int thread, long first_run, int count) = 0;
  // Row `t` (0 .. history+steps-1) of each run of the block: count x channels, row-major.
  virtual void rows(int thread, long t, const double* values) = 0;
  virtual void end(int thread) = 0;
};

struct Job {
  const double* init = nullptr;  // (windows, history, channels) physical, C order
  long windows = 0;
  long runs = 1;        // runs per window: global run g starts from window g / runs
  long first_run = 0;   // global run range [first_run, first_run + n_runs)
  long n_runs = 0;      // 0: all windows * runs
  long steps = 0;
  uint64_t seed = 0;
  int threads = 0;      // 0: one per core
  int block = 256;      // runs per block (columns of the GEMMs)
};

// Runs the job; throws std::invalid_argument on bad arguments (WidthError when the controller does
// not fit the model). Each run's controller is reset, then warmed up on its initial window's rows
// (as envi_py.simulate.rollout does), then the closed loop starts. Allocates only before the loop.
void simulate(const Model& model, const Controller& controller, const Job& job, Sink& sink);

// How `simulate` splits a job: worker threads and runs per block (sinks size their state by it).
struct Plan {
  int threads;
  int block;
};
Plan plan(const Job& job);

}  // namespace envi
