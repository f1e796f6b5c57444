// The controller spec parser's errors, the per-run memory layout, warm-up and widths; the
// arithmetic itself is checked against envi_py.controllers by tests/test_controller_parity.py.
#include <cmath>
#include <vector>

#include "check.hpp"
#include "envi/controller.hpp"

using namespace envi;

static void parser_errors() {
  // Each bad spec: one message naming the controller (or the spec) and the problem.
  CHECK_THROWS(std::invalid_argument, Controller::parse("{"), "controller spec");
  CHECK_THROWS(std::invalid_argument, Controller::parse("[1, 2]"), "must be an object with a 'name'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"params": {}})"), "must be an object with a 'name'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": 3})"), "must be an object with a 'name'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "steer"})"), "unknown controller 'steer'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pkg.mod:f"})"), "not available in the native runtime");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": [1]})"), "controller 'pid': 'params' must be an object");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"kq": 1, "kz": 2}})"),
               "controller 'pid': unknown parameter(s) kq, kz; known: kp, ki, kd, setpoint, dt, out_min, out_max, offset, input");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "bang-bang", "params": {"kp": 1}})"),
               "controller 'bang-bang': unknown parameter(s) kp; known: x, threshold, input");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"kp": "fast"}})"),
               "controller 'pid': parameter 'kp' must be a number, not 'fast'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"kp": true}})"), "'kp' must be a number, not true");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"ki": null}})"), "'ki' must be a number, not null");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"kd": [1]}})"), "'kd' must be a number, not [1]");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"input": 1.5}})"), "'input' must be a state channel index");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"input": "left"}})"), "'input' must be a state channel index");
  CHECK_THROWS(WidthError, Controller::parse(R"({"name": "pid", "params": {"input": -1}})"), "reads state channel -1");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"out_min": 5, "out_max": 1}})"), "pid: out_min 5.0 > out_max 1.0");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid", "params": {"dt": 0}})"), "pid: dt must be positive, got 0.0");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "pid"})", -40.0), "dt must be positive");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "combine"})"), "controller 'combine': params must be {'loops'");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "combine", "params": {"loops": []}})"), "one loop per action");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "combine", "params": {"loops": [], "x": 1}})"), "one loop per action");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "combine", "params": {"loops": [{"name": "combine"}]}})"),
               "combine: loop 'combine' is not one of bang-bang, lane-keeping, pid");
  CHECK_THROWS(std::invalid_argument, Controller::parse(R"({"name": "combine", "params": {"loops": [{"name": "pid", "params": {"kq": 1}}]}})"),
               "controller 'pid': unknown parameter(s) kq");
  // Accepted forms: numbers as strings (Python's float()), integral floats as channels, dt null.
  Controller ok = Controller::parse(R"({"name": "pid", "params": {"kp": "2.5", "input": 1.0, "dt": null}})", 25.0);
  CHECK(ok.loops()[0].kp == 2.5 && ok.loops()[0].input == 1 && ok.loops()[0].dt == 0.025);
  CHECK(Controller::parse(R"({"name": "pid"})").loops()[0].dt == 0.04);  // unknown period: 40 ms
  CHECK(Controller::parse(R"({"name": "pid", "params": {"dt": 0.5}})", 25.0).loops()[0].dt == 0.5);
  CHECK(Controller::parse(R"({"name": "lane-keeping", "params": null})").to_json() == R"({"name": "lane-keeping", "params": {}})");
  CHECK(Controller::parse(R"({"name": "pid", "params": {"kp": 2, "ki": 0.5}})").to_json() ==
        R"({"name": "pid", "params": {"kp": 2, "ki": 0.5}})");
}

static void widths() {
  Controller pid = Controller::parse(R"({"name": "pid", "params": {"input": 1}})");
  pid.check(2, 1);
  CHECK_THROWS(WidthError, pid.check(1, 1), "controller 'pid': reads state channel 1, the model has 1 state(s)");
  CHECK_THROWS(WidthError, pid.check(2, 2), "controller 'pid' drives 1 action channel(s), the model has 2");
  Controller two = Controller::parse(R"({"name": "combine", "params": {"loops": [{"name": "pid"}, {"name": "bang-bang", "params": {"input": 2}}]}})");
  two.check(3, 2);
  CHECK_THROWS(WidthError, two.check(2, 2), "controller 'bang-bang' (loop 2 of combine): reads state channel 2");
  CHECK_THROWS(WidthError, two.check(3, 3), "controller 'combine' drives 2 action channel(s), the model has 3");
}

static void memory_layout_and_warmup() {
  // combine(pid on 0, bang-bang on 1, pid on 1): memory per run [pid 0: 3][bang-bang: 0][pid 1: 3]
  Controller c = Controller::parse(R"({"name": "combine", "params": {"loops": [
      {"name": "pid", "params": {"kp": 1, "ki": 2, "kd": 0.5, "setpoint": 0, "dt": 1, "out_min": -100, "out_max": 100}},
      {"name": "bang-bang", "params": {"x": 3, "threshold": 0, "input": 1}},
      {"name": "pid", "params": {"kp": 0, "ki": 1, "setpoint": 0, "dt": 1, "offset": 10, "input": 1}}]}})");
  CHECK(c.outputs() == 3 && c.memory_per_run() == 6);
  CHECK(c.memory_offset(0) == 0 && c.memory_offset(1) == 3 && c.memory_offset(2) == 3);
  const int runs = 2;
  std::vector<double> mem(size_t(runs * c.memory_per_run()), 99.0), act(size_t(runs * 3));
  c.reset(mem.data(), runs);
  for (double v : mem) CHECK(v == 0.0);
  // rows of 3 values (two states and one logged action), as the engine passes whole rows
  const double rows[2][runs * 3] = {{1, -2, 0, 4, 5, 0}, {3, 1, 0, 2, -1, 0}};
  for (const auto* r : rows) c.act(r, 3, act.data(), runs, mem.data());  // warm-up: answers discarded
  // run 0, pid 0: e = 1 then 3 -> integral 4, previous 3, has previous; pid 1: e = -2 then 1 -> integral -1
  const double want0[6] = {4, 3, 1, -1, 1, 1};
  const double want1[6] = {6, 2, 1, 4, -1, 1};
  for (int k = 0; k < 6; ++k) {
    CHECK(mem[size_t(k)] == want0[k]);
    CHECK(mem[size_t(6 + k)] == want1[k]);
  }
  // first step after the warm-up: the derivative uses the window's last error
  const double states[runs * 2] = {5, 2, 0, 0};
  c.act(states, 2, act.data(), runs, mem.data());
  // run 0: pid 0 = 5 + 2 * (4 + 5) + 0.5 * (5 - 3) = 24; bang-bang +3; pid 1 = 10 + (-1 + 2) = 11
  CHECK(act[0] == 24 && act[1] == 3 && act[2] == 11);
  // run 1: pid 0 = 0 + 2 * 6 + 0.5 * (0 - 2) = 11; bang-bang sign(0) = 0; pid 1 = 10 + 4 = 14
  CHECK(act[3] == 11 && act[4] == 0 && act[5] == 14);
  // a reset forgets the previous error: the next derivative is 0 again
  c.reset(mem.data(), runs);
  c.act(states, 2, act.data(), runs, mem.data());
  CHECK(act[0] == 5 + 2 * 5 && act[3] == 0);
}

static void saturation_freezes_the_integral() {
  Controller pid = Controller::parse(R"({"name": "pid", "params": {"kp": 1, "ki": 10, "dt": 0.5, "setpoint": 0, "out_max": 4}})");
  double s = 2, u, m[3];
  pid.reset(m, 1);
  pid.act(&s, 1, &u, 1, m);  // raw = 2 + 10 * 1 = 12 -> 4, the integral stays 0
  CHECK(u == 4 && m[0] == 0);
  s = -1;
  pid.act(&s, 1, &u, 1, m);  // raw = -1 + 10 * (0 - 0.5) = -6, in range: the integral moves
  CHECK(u == -6 && m[0] == -0.5);
  s = std::nan("");
  pid.act(&s, 1, &u, 1, m);  // NaN in, NaN out (np.clip), the integral kept
  CHECK(std::isnan(u) && m[0] == -0.5);
}

int main() {
  parser_errors();
  widths();
  memory_layout_and_warmup();
  saturation_freezes_the_integral();
  std::printf("test_controller: %d failure(s)\n", failures());
  return failures() ? 1 : 0;
}
