// A small JSON reader and writer: enough for the ONNX metadata, controller specs and log sidecars.
// The runtime parses untrusted files, so the reader bounds-checks every access and limits nesting.
#pragma once
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace envi {

struct Json {
  enum class Type { Null, Bool, Number, String, Array, Object };
  Type type = Type::Null;
  bool boolean = false;
  double number = 0.0;
  bool integer = false;  // written without '.' or exponent, as Python's int
  std::string string;
  std::vector<Json> array;
  std::vector<std::pair<std::string, Json>> object;  // insertion order, as Python's json keeps it

  static Json parse(const std::string& text);  // throws std::runtime_error with the offset
  static Json object_of(std::vector<std::pair<std::string, Json>> members);

  bool is_null() const { return type == Type::Null; }
  const Json* find(const std::string& key) const;
  const Json& at(const std::string& key) const;  // throws when missing
  double as_number() const;                      // numbers, and strings holding a number
  const std::string& as_string() const;
  const std::vector<Json>& as_array() const;
  std::vector<double> as_numbers() const;
};

// json.dumps(value, indent=1) of Python, byte for byte (ints stay ints, floats as repr, an infinity
// as Infinity); a NaN anywhere throws std::invalid_argument: no reader of the project accepts one.
std::string dump_indent1(const Json& v, int depth = 0);

// json.dumps(value) of Python: one line, ", " and ": " separators.
std::string dump(const Json& v);

// Python's repr(float): shortest round-trip digits, exponent form outside 1e-4 <= |v| < 1e16.
std::string py_float(double v);
// A number for strict JSON output (envi_sim's metrics): repr(float) when finite, else null, as
// envi_py.report.files.strict writes a non-finite figure.
std::string json_number(double v);
// JSON string literal with Python json.dumps escaping (ensure_ascii=True).
std::string json_quote(const std::string& s);
// True when no number anywhere in v is NaN or infinite: a controller spec or its params holding
// one would run a controller on non-finite gains (envi_py refuses them too).
bool all_finite(const Json& v);

}  // namespace envi
