#include "envi/json.hpp"

#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>

namespace envi {
namespace {

constexpr int kMaxDepth = 64;

struct Parser {
  const std::string& s;
  size_t i = 0;

  [[noreturn]] void fail(const char* what) const {
    throw std::runtime_error(std::string("JSON: ") + what + " at offset " + std::to_string(i));
  }
  void ws() {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\n' || s[i] == '\r' || s[i] == '\t')) ++i;
  }
  bool lit(const char* word) {
    size_t n = std::strlen(word);
    if (s.compare(i, n, word) == 0) { i += n; return true; }
    return false;
  }
  Json value(int depth) {
    if (depth > kMaxDepth) fail("nesting too deep");
    ws();
    if (i >= s.size()) fail("unexpected end");
    Json v;
    char c = s[i];
    if (c == '{') {
      v.type = Json::Type::Object;
      ++i; ws();
      if (i < s.size() && s[i] == '}') { ++i; return v; }
      for (;;) {
        ws();
        if (i >= s.size() || s[i] != '"') fail("expected a key");
        std::string key = str();
        ws();
        if (i >= s.size() || s[i] != ':') fail("expected ':'");
        ++i;
        v.object.emplace_back(std::move(key), value(depth + 1));
        ws();
        if (i < s.size() && s[i] == ',') { ++i; continue; }
        if (i < s.size() && s[i] == '}') { ++i; return v; }
        fail("expected ',' or '}'");
      }
    }
    if (c == '[') {
      v.type = Json::Type::Array;
      ++i; ws();
      if (i < s.size() && s[i] == ']') { ++i; return v; }
      for (;;) {
        v.array.push_back(value(depth + 1));
        ws();
        if (i < s.size() && s[i] == ',') { ++i; continue; }
        if (i < s.size() && s[i] == ']') { ++i; return v; }
        fail("expected ',' or ']'");
      }
    }
    if (c == '"') { v.type = Json::Type::String; v.string = str(); return v; }
    if (lit("null")) return v;
    if (lit("true")) { v.type = Json::Type::Bool; v.boolean = true; return v; }
    if (lit("false")) { v.type = Json::Type::Bool; return v; }
    v.type = Json::Type::Number;
    // Python's json writes these for non-finite floats (a channel range may be unbounded).
    if (lit("NaN")) { v.number = std::numeric_limits<double>::quiet_NaN(); return v; }
    if (lit("Infinity")) { v.number = std::numeric_limits<double>::infinity(); return v; }
    if (lit("-Infinity")) { v.number = -std::numeric_limits<double>::infinity(); return v; }
    const char* b = s.data() + i;
    const size_t n = number_length();  // JSON's grammar, stricter than from_chars ("01", "1.", ".5")
    if (n == 0) fail("invalid value");
    auto [end, ec] = std::from_chars(b, b + n, v.number);
    if (ec == std::errc::result_out_of_range)  // as Python's float(): 1e999 is inf, 1e-999 is 0
      v.number = std::strtod(std::string(b, n).c_str(), nullptr);
    else if (ec != std::errc() || end != b + n)
      fail("invalid value");
    v.integer = std::string(b, n).find_first_of(".eE") == std::string::npos;
    i += n;
    return v;
  }
  // Length of the number at i by JSON's grammar: -?(0|[1-9][0-9]*)(.[0-9]+)?([eE][+-]?[0-9]+)?;
  // 0 when there is none. Python's json refuses the rest, and so must every reader of a sidecar.
  size_t number_length() const {
    size_t k = i;
    auto digits = [&]() {
      size_t from = k;
      while (k < s.size() && s[k] >= '0' && s[k] <= '9') ++k;
      return k - from;
    };
    if (k < s.size() && s[k] == '-') ++k;
    if (k < s.size() && s[k] == '0') ++k;
    else if (digits() == 0) return 0;
    if (k < s.size() && s[k] == '.') {
      ++k;
      if (digits() == 0) return 0;
    }
    if (k < s.size() && (s[k] == 'e' || s[k] == 'E')) {
      ++k;
      if (k < s.size() && (s[k] == '+' || s[k] == '-')) ++k;
      if (digits() == 0) return 0;
    }
    return k - i;
  }
  static void utf8(std::string& out, unsigned cp) {
    if (cp < 0x80) out += char(cp);
    else if (cp < 0x800) { out += char(0xC0 | (cp >> 6)); out += char(0x80 | (cp & 0x3F)); }
    else if (cp < 0x10000) {
      out += char(0xE0 | (cp >> 12)); out += char(0x80 | ((cp >> 6) & 0x3F)); out += char(0x80 | (cp & 0x3F));
    } else {
      out += char(0xF0 | (cp >> 18)); out += char(0x80 | ((cp >> 12) & 0x3F));
      out += char(0x80 | ((cp >> 6) & 0x3F)); out += char(0x80 | (cp & 0x3F));
    }
  }
  unsigned hex4() {
    if (i + 4 > s.size()) fail("short \\u escape");
    unsigned cp = 0;
    for (int k = 0; k < 4; ++k) {
      char h = s[i++];
      cp <<= 4;
      if (h >= '0' && h <= '9') cp |= unsigned(h - '0');
      else if (h >= 'a' && h <= 'f') cp |= unsigned(h - 'a' + 10);
      else if (h >= 'A' && h <= 'F') cp |= unsigned(h - 'A' + 10);
      else fail("bad \\u escape");
    }
    return cp;
  }
  std::string str() {
    ++i;  // opening quote
    std::string out;
    while (i < s.size()) {
      char c = s[i++];
      if (c == '"') return out;
      if (static_cast<unsigned char>(c) < 0x20) fail("control character in a string");  // as Python's strict json
      if (c != '\\') { out += c; continue; }
      if (i >= s.size()) break;
      char e = s[i++];
      switch (e) {
        case '"': out += '"'; break;
        case '\\': out += '\\'; break;
        case '/': out += '/'; break;
        case 'b': out += '\b'; break;
        case 'f': out += '\f'; break;
        case 'n': out += '\n'; break;
        case 'r': out += '\r'; break;
        case 't': out += '\t'; break;
        case 'u': {
          unsigned cp = hex4();
          if (cp >= 0xD800 && cp < 0xDC00 && i + 6 <= s.size() && s[i] == '\\' && s[i + 1] == 'u') {
            i += 2;
            unsigned lo = hex4();
            if (lo >= 0xDC00 && lo < 0xE000) cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
          }
          utf8(out, cp);
          break;
        }
        default: fail("bad escape");
      }
    }
    fail("unterminated string");
  }
};

}  // namespace

Json Json::parse(const std::string& text) {
  Parser p{text};
  Json v = p.value(0);
  p.ws();
  if (p.i != text.size()) p.fail("trailing characters");
  return v;
}

const Json* Json::find(const std::string& key) const {
  if (type != Type::Object) return nullptr;
  for (const auto& kv : object)
    if (kv.first == key) return &kv.second;
  return nullptr;
}

const Json& Json::at(const std::string& key) const {
  const Json* v = find(key);
  if (!v) throw std::runtime_error("JSON: missing key '" + key + "'");
  return *v;
}

double Json::as_number() const {
  if (type == Type::Number) return number;
  if (type == Type::Bool) return boolean ? 1.0 : 0.0;  // Python's float(True)
  if (type == Type::String) {
    char* end = nullptr;
    double v = std::strtod(string.c_str(), &end);
    if (!string.empty() && end == string.c_str() + string.size()) return v;
  }
  throw std::runtime_error("JSON: expected a number");
}

const std::string& Json::as_string() const {
  if (type != Type::String) throw std::runtime_error("JSON: expected a string");
  return string;
}

const std::vector<Json>& Json::as_array() const {
  if (type != Type::Array) throw std::runtime_error("JSON: expected an array");
  return array;
}

std::vector<double> Json::as_numbers() const {
  std::vector<double> out;
  for (const auto& v : as_array()) out.push_back(v.as_number());
  return out;
}

std::string py_float(double v) {
  if (std::isnan(v)) return "nan";
  if (std::isinf(v)) return v > 0 ? "inf" : "-inf";
  char buf[64];
  auto res = std::to_chars(buf, buf + sizeof buf, v, std::chars_format::scientific);
  std::string sci(buf, res.ptr);  // e.g. -1.2345e+02: shortest round-trip digits
  bool neg = sci[0] == '-';
  size_t epos = sci.find('e');
  std::string mant = sci.substr(neg ? 1 : 0, epos - (neg ? 1 : 0));
  int exp = std::atoi(sci.c_str() + epos + 1);
  std::string digits;
  for (char c : mant)
    if (c != '.') digits += c;
  std::string out = neg ? "-" : "";
  int n = int(digits.size());
  if (exp < -4 || exp >= 16) {
    out += digits.substr(0, 1);
    if (n > 1) out += "." + digits.substr(1);
    char e[16];
    std::snprintf(e, sizeof e, "e%c%02d", exp < 0 ? '-' : '+', exp < 0 ? -exp : exp);
    return out + e;
  }
  if (exp < 0) return out + "0." + std::string(size_t(-exp - 1), '0') + digits;
  if (n <= exp + 1) return out + digits + std::string(size_t(exp + 1 - n), '0') + ".0";
  return out + digits.substr(0, size_t(exp + 1)) + "." + digits.substr(size_t(exp + 1));
}

std::string json_number(double v) { return std::isfinite(v) ? py_float(v) : "null"; }

bool all_finite(const Json& v) {
  if (v.type == Json::Type::Number && !std::isfinite(v.number)) return false;
  for (const Json& x : v.array)
    if (!all_finite(x)) return false;
  for (const auto& kv : v.object)
    if (!all_finite(kv.second)) return false;
  return true;
}

Json Json::object_of(std::vector<std::pair<std::string, Json>> members) {
  Json j;
  j.type = Type::Object;
  j.object = std::move(members);
  return j;
}

namespace {
// Python's json.dumps writes Infinity for an open channel range, and the readers on both sides
// accept it there; NaN is never a value (both readers refuse it), so it is never written either.
std::string dump_number(const Json& v) {
  if (std::isnan(v.number)) throw std::invalid_argument("JSON: NaN is not a value and is not written");
  if (std::isinf(v.number)) return v.number > 0 ? "Infinity" : "-Infinity";
  if (v.integer && std::fabs(v.number) < 9.2e18) return std::to_string(static_cast<long long>(v.number));
  return py_float(v.number);
}
}  // namespace

std::string dump(const Json& v) {
  switch (v.type) {
    case Json::Type::Null: return "null";
    case Json::Type::Bool: return v.boolean ? "true" : "false";
    case Json::Type::Number: return dump_number(v);
    case Json::Type::String: return json_quote(v.string);
    case Json::Type::Array: {
      std::string out = "[";
      for (size_t k = 0; k < v.array.size(); ++k) out += (k ? ", " : "") + dump(v.array[k]);
      return out + "]";
    }
    case Json::Type::Object: {
      std::string out = "{";
      for (size_t k = 0; k < v.object.size(); ++k)
        out += (k ? ", " : "") + json_quote(v.object[k].first) + ": " + dump(v.object[k].second);
      return out + "}";
    }
  }
  return "null";
}

std::string dump_indent1(const Json& v, int depth) {
  std::string pad(size_t(depth + 1), ' '), close(size_t(depth), ' ');
  switch (v.type) {
    case Json::Type::Null: return "null";
    case Json::Type::Bool: return v.boolean ? "true" : "false";
    case Json::Type::Number: return dump_number(v);
    case Json::Type::String: return json_quote(v.string);
    case Json::Type::Array: {
      if (v.array.empty()) return "[]";
      std::string out = "[";
      for (size_t k = 0; k < v.array.size(); ++k) out += (k ? ",\n" : "\n") + pad + dump_indent1(v.array[k], depth + 1);
      return out + "\n" + close + "]";
    }
    case Json::Type::Object: {
      if (v.object.empty()) return "{}";
      std::string out = "{";
      for (size_t k = 0; k < v.object.size(); ++k)
        out += (k ? ",\n" : "\n") + pad + json_quote(v.object[k].first) + ": " + dump_indent1(v.object[k].second, depth + 1);
      return out + "\n" + close + "}";
    }
  }
  return "null";
}

std::string json_quote(const std::string& s) {
  std::string out = "\"";
  for (size_t i = 0; i < s.size(); ++i) {
    unsigned char c = static_cast<unsigned char>(s[i]);
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      case '\b': out += "\\b"; break;
      case '\f': out += "\\f"; break;
      default:
        if (c < 0x20 || c >= 0x80) {
          // decode UTF-8 to a code point for \uXXXX as ensure_ascii does; invalid bytes as-is code points
          unsigned cp = c;
          int extra = c >= 0xF0 ? 3 : c >= 0xE0 ? 2 : c >= 0xC0 ? 1 : 0;
          if (extra && i + size_t(extra) < s.size() + 0) {
            cp = c & (0x3F >> extra);
            for (int k = 1; k <= extra; ++k) cp = (cp << 6) | (static_cast<unsigned char>(s[i + size_t(k)]) & 0x3F);
            i += size_t(extra);
          }
          char b[16];
          if (cp >= 0x10000) {
            cp -= 0x10000;
            std::snprintf(b, sizeof b, "\\u%04x\\u%04x", 0xD800 + (cp >> 10), 0xDC00 + (cp & 0x3FF));
          } else {
            std::snprintf(b, sizeof b, "\\u%04x", cp);
          }
          out += b;
        } else {
          out += char(c);
        }
    }
  }
  return out + "\"";
}

}  // namespace envi
