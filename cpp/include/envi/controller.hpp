// Controllers under verification, from the same declarative spec as envi_py/controllers.py:
//   {"name": "lane-keeping", "params": {"x": 30}}, {"name": "bang-bang", "params": {"input": 1}},
//   {"name": "pid", "params": {"kp": 2, "ki": 5, "input": 0}},
//   {"name": "combine", "params": {"loops": [spec, spec, ...]}}  (one loop per action channel).
// A controller is a list of single-output loops; its memory (a PID's integral and previous error)
// lives in a caller-owned array, so the step loop never allocates and each thread keeps its own.
#pragma once
#include <stdexcept>
#include <string>
#include <vector>

namespace envi {

struct Json;

// A controller that does not fit the model: reads a state channel it lacks, or drives another
// number of action channels than it has. Python raises controllers.WidthError for the same cases.
struct WidthError : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};

// One output channel computed from one state channel (Python's controllers.Loop).
struct Loop {
  enum class Kind { BangBang, Pid } kind = Kind::BangBang;
  std::string name;  // as given: "bang-bang", "lane-keeping" or "pid"
  int input = 0;     // state channel read
  // bang-bang: sign(s - threshold) * x
  double x = 30.0, threshold = 40.0;
  // pid: clip(offset + kp e + ki I + kd de/dt, out_min, out_max), e = s - setpoint
  double kp = 1.0, ki = 0.0, kd = 0.0, setpoint = 40.0, dt = 0.04, out_min = -90.0, out_max = 90.0, offset = 0.0;

  // Memory per run: a PID keeps [integral, previous error, has previous error]; bang-bang none.
  static constexpr int kPidMemory = 3;
  int memory() const { return kind == Kind::Pid ? kPidMemory : 0; }
  // One answer per run: run b reads states[b * stride + input], answers out[b * out_stride] and
  // keeps its memory at mem + b * mem_stride.
  void act(const double* states, int stride, double* out, int out_stride, int count, double* mem, int mem_stride) const;
};

class Controller {
 public:
  // Parses a spec; a PID without `dt` integrates over `period_ms` (0 = unknown: 40 ms, as Python).
  // Throws std::invalid_argument naming the controller and the problem.
  static Controller parse(const std::string& json, double period_ms = 0.0);
  static Controller from_json(const Json& spec, double period_ms = 0.0);

  const std::string& name() const { return name_; }
  // The spec as Python's json.dumps(ControllerSpec.to_json()) writes it.
  const std::string& to_json() const { return json_; }
  const std::vector<Loop>& loops() const { return loops_; }
  int outputs() const { return int(loops_.size()); }

  // Throws WidthError unless the controller reads only states < n_state and drives n_action actions.
  void check(int n_state, int n_action) const;

  // Memory layout: run b's memory is memory[b * memory_per_run() ...], loop i's part starting at
  // memory_offset(i) within it.
  int memory_per_run() const { return memory_per_run_; }
  int memory_offset(int loop) const { return offsets_[size_t(loop)]; }
  // Forget everything (Python's reset(n)) for `count` runs.
  void reset(double* memory, int count) const;
  // One step for `count` runs: run b's states start at states[b * stride] (stride >= the states
  // read, so whole logged rows can be passed as they are) -> actions (count x outputs()). The
  // warm-up on sigma_0 is this call on each of the window's rows in order, answers discarded.
  void act(const double* states, int stride, double* actions, int count, double* memory) const;

 private:
  std::string name_, json_;
  std::vector<Loop> loops_;
  std::vector<int> offsets_;
  int memory_per_run_ = 0;
};

}  // namespace envi
