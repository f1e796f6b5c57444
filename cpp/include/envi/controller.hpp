// Controllers under verification, from the same declarative spec as envi_py/controllers.py:
// {"name": "lane-keeping", "params": {"x": 30, "threshold": 40}} or {"name": "pid", ...}.
// State (a PID's integral and previous error) lives in caller-owned arrays so the step loop never
// allocates and each thread keeps its own.
#pragma once
#include <string>

namespace envi {

struct Json;

struct ControllerSpec {
  enum class Kind { LaneKeeping, Pid } kind = Kind::LaneKeeping;
  // lane-keeping
  double x = 30.0, threshold = 40.0;
  // pid
  double kp = 1.0, ki = 0.0, kd = 0.0, setpoint = 40.0, dt = 0.04, out_min = -90.0, out_max = 90.0;

  static ControllerSpec parse(const std::string& json);  // throws std::invalid_argument
  static ControllerSpec from_json(const Json& spec);
  std::string to_json() const;  // as Python's ControllerSpec.to_json() dumps it
  std::string name() const { return kind == Kind::Pid ? "pid" : "lane-keeping"; }

  // Per-simulation memory; sized by the caller (PID: integral and previous error per run).
  static constexpr int kStateSize = 2;
  // One step for `count` runs: states (count x ns, row-major) -> actions (count x na), every action
  // channel gets the controller's output as Python's (N, 1) result broadcasts. `first` is true on
  // the first call after a reset (a PID has no previous error yet).
  void act(const double* states, int ns, double* actions, int na, int count, double* memory, bool first) const;
};

}  // namespace envi
