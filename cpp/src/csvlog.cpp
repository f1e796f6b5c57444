#include "envi/csvlog.hpp"
#include "envi/controller.hpp"

#include <sys/stat.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace envi {
namespace {

constexpr size_t kMaxSidecarBytes = size_t(1) << 20;  // envi_py.logs.MAX_SIDECAR_BYTES
constexpr int kMaxSidecarDepth = 32;                  // envi_py.logs.MAX_JSON_DEPTH
const char* const kSources[] = {"fot", "sim", "twin", "hil"};
const char* const kRegistry[] = {"bang-bang", "lane-keeping", "pid", "combine"};  // envi_py.controllers.REGISTRY
const char* const kSidecarKeys[] = {"schema_version", "states", "actions", "logged", "controller", "period_ms", "run_id", "source", "provenance", "breaks"};

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

std::string trim(const std::string& s) {
  size_t a = s.find_first_not_of(" \t\r\n\f\v"), b = s.find_last_not_of(" \t\r\n\f\v");
  return a == std::string::npos ? "" : s.substr(a, b - a + 1);
}

// A CSV line's cells, trimmed; a cell wholly in double quotes loses them ("" inside is one quote),
// as Python's csv module reads a quoted number.
std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> out;
  size_t start = 0;
  for (;;) {
    size_t comma = line.find(',', start);
    std::string cell = trim(line.substr(start, comma == std::string::npos ? std::string::npos : comma - start));
    if (cell.size() >= 2 && cell.front() == '"' && cell.back() == '"') {
      std::string inner;
      for (size_t i = 1; i + 1 < cell.size(); ++i) {
        inner += cell[i];
        if (cell[i] == '"' && cell[i + 1] == '"') ++i;
      }
      cell = trim(inner);
    }
    out.push_back(cell);
    if (comma == std::string::npos) return out;
    start = comma + 1;
  }
}

std::string stem(const std::string& name) {
  size_t dot = name.rfind('.');
  return dot == std::string::npos ? name : name.substr(0, dot);
}

std::string base(const std::string& path) {
  size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? path : path.substr(slash + 1);
}

std::string dir_of(const std::string& path) {
  size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? "." : path.substr(0, slash);
}

// Python's %g (and f"{x:g}") of a number in a message.
std::string g(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

// A value in a message as Python's repr of a short string shows it.
std::string quoted(const std::string& s) { return "'" + s.substr(0, 60) + "'"; }

// The bytes of a regular file of at most `max_bytes`: a FIFO or device would hang or never end,
// so it is refused before it is opened, as envi_py.logs._regular_file does.
std::string read_regular(const std::string& path, size_t max_bytes, const char* what) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) fail(path, std::string("cannot read (") + std::strerror(errno) + ")");
  if (!S_ISREG(st.st_mode)) fail(path, "not a regular file (a pipe, device or folder cannot be a log)");
  if (size_t(st.st_size) > max_bytes) fail(path, std::string(what) + " larger than " + std::to_string(max_bytes >> 20) + " MiB");
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot read (") + std::strerror(errno) + ")");
  std::stringstream ss;
  ss << in.rdbuf();
  if (in.bad()) fail(path, "cannot read");
  std::string text = ss.str();
  if (text.compare(0, 3, "\xEF\xBB\xBF") == 0) text.erase(0, 3);  // a BOM, as utf-8-sig reads it
  return text;
}

// Offset of the first byte that is not valid UTF-8, or npos.
size_t invalid_utf8(const std::string& s) {
  size_t i = 0;
  while (i < s.size()) {
    unsigned char c = static_cast<unsigned char>(s[i]);
    if (c < 0x80) {
      ++i;
      continue;
    }
    int extra = (c >= 0xC2 && c <= 0xDF) ? 1 : (c >> 4) == 0xE ? 2 : (c >= 0xF0 && c <= 0xF4) ? 3 : -1;
    if (extra < 0 || i + size_t(extra) >= s.size()) return i;
    unsigned cp = c & (0x3F >> extra);
    for (int k = 1; k <= extra; ++k) {
      unsigned char d = static_cast<unsigned char>(s[i + size_t(k)]);
      if ((d >> 6) != 0x2) return i;
      cp = (cp << 6) | (d & 0x3F);
    }
    if ((extra == 2 && (cp < 0x800 || (cp >= 0xD800 && cp < 0xE000))) || (extra == 3 && (cp < 0x10000 || cp > 0x10FFFF)))
      return i;
    i += size_t(extra) + 1;
  }
  return std::string::npos;
}

// envi_py.logs._NUMBER: [+-]digits[.digits][e[+-]digits] in ASCII, nothing else (no nan, inf, hex).
bool plain_number(const std::string& t) {
  size_t i = 0, n = t.size();
  if (i < n && (t[i] == '+' || t[i] == '-')) ++i;
  size_t int_digits = 0, frac_digits = 0;
  while (i < n && std::isdigit(static_cast<unsigned char>(t[i]))) ++i, ++int_digits;
  if (i < n && t[i] == '.') {
    ++i;
    while (i < n && std::isdigit(static_cast<unsigned char>(t[i]))) ++i, ++frac_digits;
  }
  if (int_digits + frac_digits == 0) return false;
  if (i < n && (t[i] == 'e' || t[i] == 'E')) {
    ++i;
    if (i < n && (t[i] == '+' || t[i] == '-')) ++i;
    size_t exp_digits = 0;
    while (i < n && std::isdigit(static_cast<unsigned char>(t[i]))) ++i, ++exp_digits;
    if (!exp_digits) return false;
  }
  return i == n;
}

double parse_cell(const std::string& text, const std::string& path, long row, const std::string& col) {
  const std::string where = "row " + std::to_string(row) + ": column '" + col + "' ";
  if (!plain_number(text)) {
    std::string low;
    for (char ch : text) low += char(std::tolower(static_cast<unsigned char>(ch)));
    low.erase(0, low.find_first_not_of("+-") == std::string::npos ? low.size() : low.find_first_not_of("+-"));
    if (low == "nan" || low == "inf" || low == "infinity")
      fail(path, where + "is " + quoted(text) + " (NaN/inf are not valid readings)");
    fail(path, where + "has non-numeric value " + quoted(text));
  }
  double v = std::strtod(text.c_str(), nullptr);
  if (!std::isfinite(v)) fail(path, where + "is " + quoted(text) + " (out of the float range)");
  return v;
}

int depth(const Json& v) {
  int deepest = 0;
  for (const Json& x : v.array) deepest = std::max(deepest, depth(x));
  for (const auto& kv : v.object) deepest = std::max(deepest, depth(kv.second));
  return (v.type == Json::Type::Array || v.type == Json::Type::Object) ? deepest + 1 : 0;
}

bool has_nan(const Json& v) {
  if (v.type == Json::Type::Number && std::isnan(v.number)) return true;
  for (const Json& x : v.array)
    if (has_nan(x)) return true;
  for (const auto& kv : v.object)
    if (has_nan(kv.second)) return true;
  return false;
}

const char* type_name(const Json& v) {  // Python's type names, as the Python reader's messages say
  switch (v.type) {
    case Json::Type::Null: return "NoneType";
    case Json::Type::Bool: return "bool";
    case Json::Type::Number: return v.integer ? "int" : "float";
    case Json::Type::String: return "str";
    case Json::Type::Array: return "list";
    case Json::Type::Object: return "dict";
  }
  return "?";
}

bool is_number(const Json* v) { return v && v->type == Json::Type::Number; }  // JSON true is no number

// envi_py.system.COLUMN_NAME: a name a CSV header holds as is.
bool is_column_name(const std::string& s) {
  if (s.empty() || s.find_first_of(",\"\r\n", 0) != std::string::npos || s.find('\0') != std::string::npos) return false;
  return trim(s) == s;
}

// One channel of a sidecar's schema, as envi_py.system.Channel.from_json checks it.
LogChannel channel(const Json& c) {
  const Json* name = c.find("name");
  if (c.type != Json::Type::Object || !name || name->type != Json::Type::String || name->string.empty())
    throw std::runtime_error("a channel must be an object with a 'name', not " + dump(c).substr(0, 60));
  const std::string& n = name->string;
  if (!is_column_name(n))
    throw std::runtime_error("channel name " + quoted(n) + " cannot be a CSV column (no separators, quotes, line breaks or surrounding spaces)");
  LogChannel out{n, -INFINITY, INFINITY, false};
  if (const Json* range = c.find("range")) {
    if (range->type != Json::Type::Array || range->array.size() != 2)
      throw std::runtime_error("channel " + quoted(n) + ": 'range' must be [low, high]");
    if (!is_number(&range->array[0]) || !is_number(&range->array[1]))
      throw std::runtime_error("channel " + quoted(n) + ": 'range' must hold two numbers");
    out.low = range->array[0].number;
    out.high = range->array[1].number;
    if (!(out.low < out.high)) throw std::runtime_error("channel " + quoted(n) + ": range [" + g(out.low) + ", " + g(out.high) + "] is empty");
  }
  const Json* res = c.find("resolution");
  if (res && !res->is_null() && !(is_number(res) && res->number > 0 && std::isfinite(res->number)))
    throw std::runtime_error("channel " + quoted(n) + ": resolution must be a positive number");
  const Json* unit = c.find("unit");
  if (unit && unit->type != Json::Type::String) throw std::runtime_error("channel " + quoted(n) + ": 'unit' must be a string");
  if (const Json* sat = c.find("saturates")) {
    if (sat->type != Json::Type::Bool) throw std::runtime_error("channel " + quoted(n) + ": 'saturates' must be true or false");
    out.saturates = sat->boolean;
  }
  return out;
}

std::vector<LogChannel> channel_list(const Json& schema, const char* key) {
  const Json* items = schema.find(key);
  bool logged = std::strcmp(key, "logged") == 0;
  if (logged && !items) return {};
  if (!items || items->type != Json::Type::Array || (!logged && items->array.empty()))
    throw std::runtime_error(std::string("schema '") + key + "' must be a non-empty list of channels");
  std::vector<LogChannel> out;
  for (const Json& c : items->array) out.push_back(channel(c));
  return out;
}

// The model's states and actions with their ranges, and whether each saturates (its envi.schema).
std::vector<LogChannel> model_channels(const Model& m) {
  std::vector<LogChannel> out;
  for (const auto& c : m.states) out.push_back({c.name, c.low, c.high, false});
  for (const auto& c : m.actions) out.push_back({c.name, c.low, c.high, false});
  const Json schema = Json::parse(m.metadata_value("envi.schema"));
  size_t k = 0;
  for (const char* key : {"states", "actions"})
    if (const Json* list = schema.find(key))
      for (const Json& c : list->array) {
        const Json* sat = c.find("saturates");
        if (k < out.size() && sat && sat->type == Json::Type::Bool) out[k].saturates = sat->boolean;
        ++k;
      }
  return out;
}

std::string names(const std::vector<LogChannel>& list) {
  std::string out;
  for (const auto& c : list) out += (out.empty() ? "" : ",") + c.name;
  return out;
}

std::string join(const std::vector<std::string>& items, const char* sep) {
  std::string out;
  for (const auto& s : items) out += (out.empty() ? "" : sep) + s;
  return out;
}

// Via a temporary file and a rename, so a crash never leaves half a file (no litter on failure).
void write_atomic(const std::string& path, const std::string& text) {
  std::string tmp = dir_of(path) + "/." + base(path) + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary);
    out << text;
    if (!out.flush()) {
      std::remove(tmp.c_str());
      throw std::runtime_error(path + ": cannot write");
    }
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    std::remove(tmp.c_str());
    throw std::runtime_error(path + ": cannot rename into place");
  }
}

}  // namespace

bool is_run_id(const std::string& id) {
  auto ok = [](char ch) { return std::isalnum(static_cast<unsigned char>(ch)) || ch == '_' || ch == '-' || ch == '.'; };
  return !id.empty() && id.size() <= 120 && id[0] != '.' && std::all_of(id.begin(), id.end(), ok);
}

Sidecar read_sidecar(const std::string& path) {
  std::string text = read_regular(path, kMaxSidecarBytes, "sidecar");
  if (size_t bad = invalid_utf8(text); bad != std::string::npos)
    fail(path, "sidecar is not valid JSON (not UTF-8 at byte " + std::to_string(bad) + ")");
  Json d;
  try {
    d = Json::parse(text);
  } catch (const std::exception& e) {
    fail(path, std::string("sidecar is not valid JSON (") + e.what() + ")");
  }
  if (has_nan(d)) fail(path, "sidecar is not valid JSON (NaN is not a value)");
  if (depth(d) > kMaxSidecarDepth) fail(path, "sidecar nested deeper than " + std::to_string(kMaxSidecarDepth) + " levels");
  if (d.type != Json::Type::Object) fail(path, std::string("a sidecar must be a JSON object, not ") + type_name(d));
  {  // every key a sidecar may hold (Python's logs.SIDECAR_KEYS): a misspelt one is not dropped silently
    std::vector<std::string> unknown;
    for (const auto& [key, value] : d.object)
      if (std::find(std::begin(kSidecarKeys), std::end(kSidecarKeys), key) == std::end(kSidecarKeys)) unknown.push_back(key);
    if (!unknown.empty()) {
      std::sort(unknown.begin(), unknown.end());
      std::string names;
      for (size_t i = 0; i < std::min<size_t>(3, unknown.size()); ++i)
        names += (i ? ", '" : "'") + unknown[i].substr(0, 38) + "'";
      std::vector<std::string> known(std::begin(kSidecarKeys), std::end(kSidecarKeys));
      std::sort(known.begin(), known.end());
      std::string all;
      for (const auto& k : known) all += (all.empty() ? "" : ", ") + k;
      fail(path, "sidecar key(s) " + names + " unknown; known: " + all);
    }
  }
  const Json* version = d.find("schema_version");
  if (!version || version->type != Json::Type::Number || !version->integer || version->number != 1)
    fail(path, "sidecar schema_version " + (version ? dump(*version).substr(0, 40) : std::string("None")) + " is not supported (expected 1)");
  if (const Json* source = d.find("source")) {
    bool known = source->type == Json::Type::String &&
                 std::any_of(std::begin(kSources), std::end(kSources), [&](const char* s) { return source->string == s; });
    if (!known) fail(path, "sidecar source " + dump(*source).substr(0, 40) + " is not one of fot, sim, twin, hil");
  }
  Sidecar out;
  try {
    out.states = channel_list(d, "states");
    out.actions = channel_list(d, "actions");
    out.logged = channel_list(d, "logged");
    std::vector<std::string> cols{"time"};
    for (const auto* list : {&out.states, &out.actions, &out.logged})
      for (const auto& c : *list) cols.push_back(c.name);
    for (size_t i = 0; i < cols.size(); ++i)
      if (std::count(cols.begin(), cols.end(), cols[i]) > 1) throw std::runtime_error("schema names column(s) " + cols[i] + " twice");
    const Json* ctrl = d.find("controller");
    if (ctrl && !ctrl->is_null()) {
      const Json* name = ctrl->find("name");
      if (ctrl->type != Json::Type::Object || !name || name->type != Json::Type::String)
        throw std::runtime_error("controller spec must be an object with a 'name', not " + dump(*ctrl).substr(0, 80));
      const Json* params = ctrl->find("params");
      if (params && !params->is_null() && params->type != Json::Type::Object)
        throw std::runtime_error("controller " + quoted(name->string) + ": 'params' must be an object");
      if (params && !all_finite(*params)) throw std::runtime_error("controller params hold a non-finite number");
      // a registered controller is built once here, as Python's reader does: a bad gain or a loop
      // reading a state the log lacks stops the read (a user's controller, by import path, is not built)
      if (std::find(std::begin(kRegistry), std::end(kRegistry), name->string) != std::end(kRegistry)) {
        try {
          Controller::from_json(*ctrl).check(int(out.states.size()), int(out.actions.size()));
        } catch (const std::invalid_argument& e) {
          throw std::runtime_error(e.what());
        }
      }
    }
  } catch (const std::runtime_error& e) {
    fail(path, std::string("sidecar ") + e.what());
  }
  const Json* period = d.find("period_ms");
  if (period && !period->is_null() && !(is_number(period) && std::isfinite(period->number) && period->number > 0))
    fail(path, "sidecar period_ms " + dump(*period).substr(0, 40) + " is not a positive number");
  const Json* id = d.find("run_id");
  if (id && !id->is_null()) {
    std::string text = id->type == Json::Type::String ? id->string : dump(*id);
    bool scalar = id->type == Json::Type::String || id->type == Json::Type::Number;
    if (!scalar || !is_run_id(text))
      fail(path, "run_id " + quoted(text) + " is not a plain name (letters, digits, '.', '_', '-')");
    out.run_id = text;
  }
  const Json* prov = d.find("provenance");
  if (prov && !prov->is_null() && prov->type != Json::Type::Object) fail(path, "sidecar provenance must be an object");
  // As LogMeta.from_json: rows that follow rows lost in transit, increasing whole numbers >= 1.
  if (const Json* breaks = d.find("breaks"); breaks && !breaks->is_null()) {
    bool ok = breaks->type == Json::Type::Array;
    double previous = 0;
    for (size_t i = 0; ok && i < breaks->array.size(); ++i) {
      const Json& b = breaks->array[i];
      ok = b.type == Json::Type::Number && b.integer && std::isfinite(b.number) && b.number > previous;
      previous = b.number;
    }
    if (!ok) fail(path, "sidecar breaks " + dump(*breaks).substr(0, 60) + " is not an increasing list of row numbers >= 1");
    out.last_break = breaks->array.empty() ? 0 : long(std::min(previous, 9e18));
  }
  return out;
}

InitialWindow read_initial_window(const std::string& path, const Model& model) {
  InitialWindow win;
  win.name = base(path);
  win.run_id = stem(win.name);
  // The sidecar, when there is one, declares the log's columns and ranges (as in read_log, it wins).
  const std::string side = path.substr(0, path.size() - win.name.size()) + stem(win.name) + ".meta.json";
  struct stat st {};
  const bool has_side = ::lstat(side.c_str(), &st) == 0;
  std::vector<LogChannel> channels = model_channels(model), declared = channels;
  // The system description the model was trained on (envi.system; null in older exports): as
  // envi_py.logs reads a log, its logged columns belong to the log and its ignored ones may be there.
  const Json system = Json::parse(model.metadata_value("envi.system"));
  std::vector<std::string> ignored;
  if (const Json* ig = system.find("ignore"); ig && ig->type == Json::Type::Array)
    for (const Json& name : ig->array)
      if (name.type == Json::Type::String) ignored.push_back(name.string);
  long last_break = 0;
  if (has_side) {
    Sidecar meta = read_sidecar(side);
    if (names(meta.states) != names({channels.begin(), channels.begin() + model.n_state()}) ||
        names(meta.actions) != names({channels.begin() + model.n_state(), channels.end()}))
      fail(path, "holds states " + names(meta.states) + " and actions " + names(meta.actions) + ", the model reads states " +
                     names({channels.begin(), channels.begin() + model.n_state()}) + " and actions " +
                     names({channels.begin() + model.n_state(), channels.end()}) + " (a model of another system?)");
    declared = meta.states;
    declared.insert(declared.end(), meta.actions.begin(), meta.actions.end());
    declared.insert(declared.end(), meta.logged.begin(), meta.logged.end());
    if (!meta.run_id.empty()) win.run_id = meta.run_id;
    last_break = meta.last_break;
  } else if (const Json* schema = system.find("schema"); schema && schema->type == Json::Type::Object) {
    for (const LogChannel& c : channel_list(*schema, "logged")) declared.push_back(c);
  }
  if (!is_run_id(win.run_id)) fail(path, "run_id " + quoted(win.run_id) + " is not a plain name (letters, digits, '.', '_', '-')");

  std::string text = read_regular(path, std::string::npos, "log");
  if (size_t bad = invalid_utf8(text); bad != std::string::npos)
    fail(path, "not a UTF-8 text CSV file (invalid byte at byte " + std::to_string(bad) + ")");
  if (text.find('\0') != std::string::npos) fail(path, "not a text CSV file (it holds NUL bytes)");
  if (size_t first = text.find_first_not_of(" \t\r\n\xEF\xBB\xBF"); first != std::string::npos && text[first] == '{')
    fail(path, "a JSON file (a manifest?), not a CSV log: give envi_sim the logs themselves (envi simulate reads manifests)");
  std::string lines;  // line ends made \n, as _read_text does
  lines.reserve(text.size());
  for (size_t i = 0; i < text.size(); ++i) {
    if (text[i] != '\r') lines += text[i];
    else if (i + 1 >= text.size() || text[i + 1] != '\n') lines += '\n';
  }
  std::istringstream in(lines);
  std::string line;
  std::getline(in, line);
  if (trim(line).empty()) fail(path, "empty file (no header row)");
  const std::vector<std::string> header = split(line);
  for (size_t i = 0; i < header.size(); ++i) {
    if (header[i].empty()) fail(path, "row 1: column " + std::to_string(i + 1) + " of the header has no name");
    if (std::count(header.begin(), header.end(), header[i]) > 1) fail(path, "row 1: column(s) " + header[i] + " appear twice in the header");
  }
  std::vector<std::string> expected{"time"}, missing, extra;
  for (const auto& c : declared) expected.push_back(c.name);
  for (const auto& w : expected)
    if (std::find(header.begin(), header.end(), w) == header.end()) missing.push_back(w);
  // As envi_py.logs: any other column is refused (a model exported without a system description
  // has no logged or ignored ones).
  for (const auto& h : header)
    if (std::find(expected.begin(), expected.end(), h) == expected.end() &&
        std::find(ignored.begin(), ignored.end(), h) == ignored.end())
      extra.push_back(h);
  if (!missing.empty() || !extra.empty()) {
    std::vector<std::string> parts;
    if (!missing.empty()) parts.push_back("missing column(s) " + join(missing, ", "));
    if (!extra.empty())
      parts.push_back("unexpected column(s) " + join(extra, ", ") + " (declare them in the system description with role 'logged' or 'ignore')");
    fail(path, "row 1: " + join(parts, "; ") + " (expected " + join(expected, ",") + ")");
  }
  std::vector<size_t> order;
  for (const auto& w : expected) order.push_back(size_t(std::find(header.begin(), header.end(), w) - header.begin()));

  // Every row, as read_log reads them: cells first, then time, then the declared ranges.
  const size_t width = expected.size();
  std::vector<double> data;
  std::vector<long> row_of;
  for (long row = 2; std::getline(in, line); ++row) {
    if (line.empty()) continue;  // a blank line is not a reading
    auto cells = split(line);
    if (std::all_of(cells.begin(), cells.end(), [](const std::string& c) { return c.empty(); }))
      fail(path, "row " + std::to_string(row) + ": an empty row (only separators)");
    if (cells.size() != header.size())
      fail(path, "row " + std::to_string(row) + ": " + std::to_string(cells.size()) + " cells, header has " + std::to_string(header.size()));
    for (size_t k = 0; k < width; ++k) data.push_back(parse_cell(cells[order[k]], path, row, expected[k]));
    row_of.push_back(row);
  }
  const long n = long(row_of.size());
  if (last_break > 0 && last_break >= n)
    fail(path, "its sidecar marks a break at row " + std::to_string(last_break) + ", but the log has " + std::to_string(n) + " rows");
  if (n == 0) fail(path, "no data rows (only a header)");
  if (n < model.history)
    fail(path, std::to_string(n) + " data rows, shorter than the " + std::to_string(model.history) + " the history window needs");
  for (long r = 1; r < n; ++r)
    if (!(data[size_t(r) * width] > data[size_t(r - 1) * width]))
      fail(path, "row " + std::to_string(row_of[size_t(r)]) + ": time " + g(data[size_t(r) * width]) +
                     " does not increase (previous " + g(data[size_t(r - 1) * width]) + ")");
  for (size_t k = 1; k < width; ++k) {
    const LogChannel& ch = declared[k - 1];
    for (long r = 0; r < n; ++r) {
      double& v = data[size_t(r) * width + k];
      if (v >= ch.low && v <= ch.high) continue;
      if (!ch.saturates)
        fail(path, "row " + std::to_string(row_of[size_t(r)]) + ": column '" + ch.name + "' is " + g(v) +
                       ", outside its valid range [" + g(ch.low) + ", " + g(ch.high) + "]");
      v = std::min(std::max(v, ch.low), ch.high);  // a saturating sensor reads its limit
    }
  }
  win.rows = n;
  for (long r = 0; r < model.history; ++r) {
    win.time.push_back(data[size_t(r) * width]);
    for (const auto& c : channels)
      win.values.push_back(data[size_t(r) * width + size_t(std::find(expected.begin(), expected.end(), c.name) - expected.begin())]);
  }
  return win;
}

std::string format_value(double v) {
  if (std::floor(v) == v && std::fabs(v) < 1e15) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(v));
    return buf;
  }
  return py_float(v);
}

double median_period(const std::vector<double>& time) {
  std::vector<double> d;
  for (size_t i = 1; i < time.size(); ++i) d.push_back(time[i] - time[i - 1]);
  if (d.empty()) return 0.0;
  std::sort(d.begin(), d.end());
  size_t n = d.size();
  return n % 2 ? d[n / 2] : (d[n / 2 - 1] + d[n / 2]) / 2;
}

void write_log(const std::string& dir, const std::string& run_id, const Model& model, const Json& meta,
               const std::vector<double>& time, const double* rows, long length) {
  const int c = model.channels();
  std::string text = "time";
  for (const auto& ch : model.states) text += "," + ch.name;
  for (const auto& ch : model.actions) text += "," + ch.name;
  text += "\n";
  for (long t = 0; t < length; ++t) {
    text += format_value(time[size_t(t)]);
    for (int k = 0; k < c; ++k) text += "," + format_value(rows[t * c + k]);
    text += "\n";
  }
  std::string csv = dir + "/" + run_id + ".csv";
  write_atomic(dir + "/" + run_id + ".meta.json", dump_indent1(meta) + "\n");  // sidecar first, as write_log
  write_atomic(csv, text);
}

}  // namespace envi
