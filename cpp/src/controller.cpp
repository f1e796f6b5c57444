#include "envi/controller.hpp"

#include <algorithm>
#include <stdexcept>

#include "envi/json.hpp"

namespace envi {

ControllerSpec ControllerSpec::parse(const std::string& json) {
  try {
    return from_json(Json::parse(json));
  } catch (const std::invalid_argument&) {
    throw;
  } catch (const std::exception& e) {
    throw std::invalid_argument(std::string("controller spec: ") + e.what());
  }
}

ControllerSpec ControllerSpec::from_json(const Json& spec) {
  ControllerSpec c;
  const std::string& name = spec.at("name").as_string();
  struct P { const char* key; double* dst; };
  std::initializer_list<P> lk = {{"x", &c.x}, {"threshold", &c.threshold}};
  std::initializer_list<P> pid = {{"kp", &c.kp}, {"ki", &c.ki}, {"kd", &c.kd}, {"setpoint", &c.setpoint},
                                  {"dt", &c.dt}, {"out_min", &c.out_min}, {"out_max", &c.out_max}};
  const std::initializer_list<P>* known = nullptr;
  if (name == "lane-keeping") { c.kind = Kind::LaneKeeping; known = &lk; }
  else if (name == "pid") { c.kind = Kind::Pid; known = &pid; }
  else throw std::invalid_argument("controller '" + name + "' is not available in the native runtime (it runs lane-keeping and pid)");
  if (const Json* params = spec.find("params")) {
    if (params->type != Json::Type::Object && !params->is_null()) throw std::invalid_argument("controller params must be an object");
    for (const auto& kv : params->object) {
      auto it = std::find_if(known->begin(), known->end(), [&](const P& p) { return kv.first == p.key; });
      if (it == known->end()) throw std::invalid_argument("controller '" + name + "': unknown parameter '" + kv.first + "'");
      *it->dst = kv.second.as_number();
    }
  }
  if (c.kind == Kind::Pid) {
    if (c.out_min > c.out_max) throw std::invalid_argument("pid: out_min > out_max");
    if (!(c.dt > 0)) throw std::invalid_argument("pid: dt must be positive");
  }
  return c;
}

std::string ControllerSpec::to_json() const {
  if (kind == Kind::LaneKeeping)
    return "{\"name\": \"lane-keeping\", \"params\": {\"x\": " + py_float(x) + ", \"threshold\": " + py_float(threshold) + "}}";
  return "{\"name\": \"pid\", \"params\": {\"kp\": " + py_float(kp) + ", \"ki\": " + py_float(ki) + ", \"kd\": " + py_float(kd) +
         ", \"setpoint\": " + py_float(setpoint) + ", \"dt\": " + py_float(dt) + ", \"out_min\": " + py_float(out_min) +
         ", \"out_max\": " + py_float(out_max) + "}}";
}

void ControllerSpec::act(const double* states, int ns, double* actions, int na, int count, double* memory, bool first) const {
  for (int b = 0; b < count; ++b) {
    double s = states[size_t(b) * size_t(ns)];
    double u;
    if (kind == Kind::LaneKeeping) {
      double d = s - threshold;  // np.sign: 0 on the threshold, NaN stays NaN
      u = (d > 0 ? 1.0 : d < 0 ? -1.0 : d) * x;
    } else {
      double* m = memory + size_t(b) * kStateSize;  // [integral, previous error]
      double err = s - setpoint;
      double deriv = first ? 0.0 : (err - m[1]) / dt;
      m[1] = err;
      double integral = m[0] + err * dt;
      double raw = kp * err + ki * integral + kd * deriv;
      u = std::min(std::max(raw, out_min), out_max);  // np.clip
      if (u == raw) m[0] = integral;  // anti-windup: freeze the integral while saturated
    }
    for (int j = 0; j < na; ++j) actions[size_t(b) * size_t(na) + size_t(j)] = u;
  }
}

}  // namespace envi
