// The C++ twins of envi_py/controllers.py, checked against them by tests/test_controller_parity.py.
// The arithmetic is written in the order numpy evaluates it and this file is compiled without
// floating-point contraction (see CMakeLists.txt), so both give the same doubles.
#include "envi/controller.hpp"

#include <algorithm>
#include <cmath>
#include <iterator>

#include "envi/json.hpp"

namespace envi {
namespace {

const char* const kLoopNames = "bang-bang, lane-keeping, pid";

// A loop's parameters in Python's order; `input` (no field) is the state channel read.
struct Param {
  const char* key;
  double Loop::*field;
};
const Param kBangBang[] = {{"x", &Loop::x}, {"threshold", &Loop::threshold}, {"input", nullptr}};
const Param kPid[] = {{"kp", &Loop::kp}, {"ki", &Loop::ki}, {"kd", &Loop::kd}, {"setpoint", &Loop::setpoint},
                      {"dt", &Loop::dt}, {"out_min", &Loop::out_min}, {"out_max", &Loop::out_max},
                      {"offset", &Loop::offset}, {"input", nullptr}};

[[noreturn]] void fail(const std::string& name, const std::string& what) {
  throw std::invalid_argument("controller '" + name + "': " + what);
}

// Short text of a JSON value for messages, as Python's {value!r:.40} shows it.
std::string shown(const Json& v) {
  std::string s = v.type == Json::Type::String ? "'" + v.string + "'" : dump(v);
  return s.size() > 40 ? s.substr(0, 40) : s;
}

// Numbers, and strings holding a number (Python's float(value)); never booleans or null.
double number(const std::string& name, const std::string& key, const Json& v) {
  if (v.type == Json::Type::Number) return v.number;
  if (v.type == Json::Type::String) {
    try {
      return v.as_number();
    } catch (const std::exception&) {
    }
  }
  fail(name, "parameter '" + key + "' must be a number, not " + shown(v));
}

int channel(const std::string& name, const Json& v) {
  double d = std::nan("");
  if (v.type == Json::Type::Number || v.type == Json::Type::String) {
    try {
      d = v.as_number();
    } catch (const std::exception&) {
    }
  }
  if (!(d == std::floor(d)) || std::abs(d) > 1e9)
    fail(name, "'input' must be a state channel index, not " + shown(v));
  if (d < 0) throw WidthError("controller '" + name + "': reads state channel " + std::to_string(long(d)) + "; channels count from 0");
  return int(d);
}

Loop parse_loop(const Json& spec, double period_ms, bool nested) {
  if (spec.type != Json::Type::Object || !spec.find("name") || spec.at("name").type != Json::Type::String)
    throw std::invalid_argument("controller spec must be an object with a 'name', not " + shown(spec));
  Loop lp;
  lp.name = spec.at("name").string;
  const Param *known = nullptr, *known_end = nullptr;
  if (lp.name == "bang-bang" || lp.name == "lane-keeping") {
    lp.kind = Loop::Kind::BangBang;
    known = std::begin(kBangBang);
    known_end = std::end(kBangBang);
  } else if (lp.name == "pid") {
    lp.kind = Loop::Kind::Pid;
    known = std::begin(kPid);
    known_end = std::end(kPid);
  } else if (nested) {
    throw std::invalid_argument("combine: loop '" + lp.name + "' is not one of " + kLoopNames);
  } else if (lp.name.find(':') != std::string::npos) {
    throw std::invalid_argument("controller '" + lp.name +
                                "' is not available in the native runtime (a user's controller runs in the PyTorch engine)");
  } else {
    throw std::invalid_argument("unknown controller '" + lp.name + "'; registered: " + kLoopNames +
                                ", combine, or give 'package.module:function'");
  }
  bool dt_given = false;
  if (const Json* params = spec.find("params"); params && !params->is_null()) {
    if (params->type != Json::Type::Object) fail(lp.name, "'params' must be an object");
    std::string unknown;
    for (const auto& kv : params->object)
      if (std::none_of(known, known_end, [&](const Param& p) { return kv.first == p.key; }))
        unknown += (unknown.empty() ? "" : ", ") + kv.first;
    if (!unknown.empty()) {
      std::string names;
      for (const Param* p = known; p != known_end; ++p) names += (names.empty() ? "" : ", ") + std::string(p->key);
      fail(lp.name, "unknown parameter(s) " + unknown + "; known: " + names);
    }
    for (const auto& kv : params->object) {
      if (kv.first == "input") {
        lp.input = channel(lp.name, kv.second);
      } else if (kv.first == "dt" && kv.second.is_null()) {
        continue;  // None: the model's period, as Python
      } else {
        const Param* it = std::find_if(known, known_end, [&](const Param& p) { return kv.first == p.key; });
        lp.*(it->field) = number(lp.name, kv.first, kv.second);
        dt_given = dt_given || kv.first == "dt";
      }
    }
  }
  if (lp.kind == Loop::Kind::Pid) {
    if (!dt_given) lp.dt = (period_ms != 0.0 ? period_ms : 40.0) / 1000.0;  // (period_ms or 40.0) / 1000
    if (!(lp.out_min <= lp.out_max))
      throw std::invalid_argument("pid: out_min " + py_float(lp.out_min) + " > out_max " + py_float(lp.out_max));
    if (!(lp.dt > 0)) throw std::invalid_argument("pid: dt must be positive, got " + py_float(lp.dt));
  }
  return lp;
}

}  // namespace

void Loop::act(const double* states, int stride, double* out, int out_stride, int count, double* mem,
               int mem_stride) const {
  if (kind == Kind::BangBang) {
    for (int b = 0; b < count; ++b) {
      double d = states[size_t(b) * size_t(stride) + size_t(input)] - threshold;  // np.sign: 0 on it, NaN stays
      out[size_t(b) * size_t(out_stride)] = (d > 0 ? 1.0 : d < 0 ? -1.0 : d) * x;
    }
    return;
  }
  for (int b = 0; b < count; ++b) {
    double* m = mem + size_t(b) * size_t(mem_stride);  // [integral, previous error, has previous]
    double err = states[size_t(b) * size_t(stride) + size_t(input)] - setpoint;
    double deriv = m[2] != 0.0 ? (err - m[1]) / dt : 0.0;
    m[1] = err;
    m[2] = 1.0;
    double integral = m[0] + err * dt;
    double raw = offset + kp * err + ki * integral + kd * deriv;
    double u = std::min(std::max(raw, out_min), out_max);  // np.clip
    if (u == raw) m[0] = integral;                          // anti-windup: frozen while saturated
    out[size_t(b) * size_t(out_stride)] = u;
  }
}

Controller Controller::parse(const std::string& json, double period_ms) {
  Json j;
  try {
    j = Json::parse(json);
  } catch (const std::exception& e) {
    throw std::invalid_argument(std::string("controller spec: ") + e.what());
  }
  return from_json(j, period_ms);
}

Controller Controller::from_json(const Json& spec, double period_ms) {
  Controller c;
  const Json* name = spec.type == Json::Type::Object ? spec.find("name") : nullptr;
  if (name && name->type == Json::Type::String && name->string == "combine") {
    c.name_ = "combine";
    const Json* params = spec.find("params");
    const Json* loops = params && params->type == Json::Type::Object ? params->find("loops") : nullptr;
    if (!loops || params->object.size() != 1 || loops->type != Json::Type::Array || loops->array.empty())
      fail("combine", "params must be {'loops': [spec, ...]}, one loop per action");
    for (const Json& lp : loops->array) c.loops_.push_back(parse_loop(lp, period_ms, true));
  } else {
    c.loops_.push_back(parse_loop(spec, period_ms, false));
    c.name_ = c.loops_.back().name;
  }
  const Json* params = spec.find("params");
  Json out = Json::object_of({{"name", spec.at("name")}, {"params", params && !params->is_null() ? *params : Json::object_of({})}});
  c.json_ = dump(out);
  for (const Loop& lp : c.loops_) {
    c.offsets_.push_back(c.memory_per_run_);
    c.memory_per_run_ += lp.memory();
  }
  return c;
}

void Controller::check(int n_state, int n_action) const {
  for (size_t i = 0; i < loops_.size(); ++i)
    if (loops_[i].input >= n_state)
      throw WidthError("controller '" + loops_[i].name + "'" +
                       (name_ == "combine" ? " (loop " + std::to_string(i + 1) + " of combine)" : std::string()) +
                       ": reads state channel " + std::to_string(loops_[i].input) + ", the model has " +
                       std::to_string(n_state) + " state(s)");
  if (outputs() != n_action)
    throw WidthError("controller '" + name_ + "' drives " + std::to_string(outputs()) +
                     " action channel(s), the model has " + std::to_string(n_action) +
                     "; use 'combine' with one loop per action");
}

void Controller::reset(double* memory, int count) const {
  std::fill(memory, memory + size_t(count) * size_t(memory_per_run_), 0.0);
}

void Controller::act(const double* states, int stride, double* actions, int count, double* memory) const {
  const int na = outputs();
  for (int i = 0; i < na; ++i)
    loops_[size_t(i)].act(states, stride, actions + i, na, count, memory + offsets_[size_t(i)], memory_per_run_);
}

}  // namespace envi
