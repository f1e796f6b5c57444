// Writes small ONNX models byte by byte (protobuf wire format), so the C++ tests and the fuzzer
// need neither Python nor libprotobuf, and can build the broken files they want.
#pragma once
#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "envi/model.hpp"

namespace pb {

using Bytes = std::string;

inline void varint(Bytes& out, uint64_t v) {
  while (v >= 0x80) { out += char(v | 0x80); v >>= 7; }
  out += char(v);
}
inline void key(Bytes& out, uint32_t field, uint32_t wire) { varint(out, (uint64_t(field) << 3) | wire); }
inline void field_bytes(Bytes& out, uint32_t field, const Bytes& v) { key(out, field, 2); varint(out, v.size()); out += v; }
inline void field_int(Bytes& out, uint32_t field, uint64_t v) { key(out, field, 0); varint(out, v); }

inline Bytes tensor(const std::string& name, const std::vector<int64_t>& dims, const std::vector<float>& data) {
  Bytes t;
  for (int64_t d : dims) field_int(t, 1, uint64_t(d));
  field_int(t, 2, 1);  // FLOAT
  field_bytes(t, 8, name);
  field_bytes(t, 9, Bytes(reinterpret_cast<const char*>(data.data()), data.size() * 4));
  return t;
}

// An int64 tensor (the residual head's indices and axes).
inline Bytes tensor_i64(const std::string& name, const std::vector<int64_t>& dims, const std::vector<int64_t>& data) {
  Bytes t;
  for (int64_t d : dims) field_int(t, 1, uint64_t(d));
  field_int(t, 2, 7);  // INT64
  field_bytes(t, 8, name);
  field_bytes(t, 9, Bytes(reinterpret_cast<const char*>(data.data()), data.size() * 8));
  return t;
}

inline Bytes attr_int(const std::string& name, int64_t v) {
  Bytes a;
  field_bytes(a, 1, name);
  field_int(a, 3, uint64_t(v));
  field_int(a, 20, 2);  // INT
  return a;
}

inline Bytes node(const std::string& op, const std::vector<std::string>& in, const std::string& out,
                  const std::vector<Bytes>& attrs = {}, const std::string& domain = "", const std::string& name = "") {
  Bytes n;
  for (const auto& i : in) field_bytes(n, 1, i);
  field_bytes(n, 2, out);
  field_bytes(n, 3, name.empty() ? out + "_node" : name);
  field_bytes(n, 4, op);
  for (const auto& a : attrs) field_bytes(n, 5, a);
  if (!domain.empty()) field_bytes(n, 7, domain);
  return n;
}

inline Bytes value_info(const std::string& name) {
  Bytes v;
  field_bytes(v, 1, name);
  return v;
}

struct Spec {
  int history = 3, hidden = 8;
  int n_state = 1, n_action = 1;  // more than one: channels color<i> / angle<i>, limits 0..100 each
  bool gaussian = false;
  std::string post = R"({"clamp": true, "limits": [[0.0, 100.0]], "round_to": null})";
  uint32_t seed = 1;
  bool hash = true;  // write envi.content_sha256, as envi-export does
  bool clamp = true;  // more than one state: clamp to 0..100 (one state: `post` says)
  // A residual mean head, written as envi-export writes it (envi_py/export.py, _residual_base):
  // mean = 2 tanh(head) + base. With `limit_state` >= 0 (Gaussian only) that state saturates at its
  // normaliser's high end (80, normalised +1): an event head, envi.limit_events and a limit level.
  bool residual = false;
  int limit_state = -1;
  std::string residual_meta;  // envi.residual as written; empty: what `residual` implies
  std::string head_meta;      // envi.head as written; empty: what `gaussian` implies
  std::string bad_initializer;  // this initializer's first value is `bad_value` (a damaged weight)
  float bad_value = NAN;
};

// The residual head's nodes and constants for a window of `history` rows of `channels`.
inline void residual_head(Bytes& graph, const Spec& s, const std::string& head) {
  const int ns = s.n_state, c = s.n_state + s.n_action, l = s.history;
  auto add = [&](const std::string& op, const std::vector<std::string>& in, const std::string& out,
                 const std::vector<Bytes>& attrs = {}) { field_bytes(graph, 1, node(op, in, out, attrs, "", out)); };
  field_bytes(graph, 5, tensor_i64("residual.axis", {1}, {1}));
  if (s.limit_state < 0) {
    add("Slice", {"x", "residual.starts", "residual.ends", "residual.axis"}, "residual.base");
    field_bytes(graph, 5, tensor_i64("residual.starts", {1}, {int64_t((l - 1) * c)}));
    field_bytes(graph, 5, tensor_i64("residual.ends", {1}, {int64_t((l - 1) * c + ns)}));
  } else {
    std::vector<int64_t> index;
    for (int t = 0; t < l; ++t)
      for (int i = 0; i < ns; ++i) index.push_back(t * c + i);
    std::vector<float> levels(size_t(ns), INFINITY);
    levels[size_t(s.limit_state)] = 1.f;
    field_bytes(graph, 5, tensor_i64("residual.rows.index", {l, ns}, index));
    field_bytes(graph, 5, tensor("residual.levels", {ns}, levels));
    field_bytes(graph, 5, tensor("residual.tolerance", {}, {1e-5f}));
    add("Gather", {"x", "residual.rows.index"}, "residual.rows", {attr_int("axis", 1)});
    add("Sub", {"residual.rows", "residual.levels"}, "residual.offset");
    add("Abs", {"residual.offset"}, "residual.distance");
    add("Greater", {"residual.distance", "residual.tolerance"}, "residual.in_range");
    add("Cast", {"residual.in_range"}, "residual.in_range_float", {attr_int("to", 1)});
    add("ArgMax", {"residual.in_range_float"}, "residual.last_in_range", {attr_int("axis", 1), attr_int("select_last_index", 1)});
    add("GatherElements", {"residual.rows", "residual.last_in_range"}, "residual.picked", {attr_int("axis", 1)});
    add("Squeeze", {"residual.picked", "residual.axis"}, "residual.base");
  }
  field_bytes(graph, 5, tensor("residual.scale", {}, {2.f}));
  add("Mul", {head, "residual.scale"}, "residual.change");
  field_bytes(graph, 1, node("Add", {"residual.change", "residual.base"}, "mean", {}, "", "residual.add"));
}

// A model (history*channels) -> hidden tanh -> n_state tanh [+ log-std head], the lane-keeping
// schema and metadata (or as many colour states and angle actions as asked).
inline Bytes model(const Spec& s, std::vector<Bytes> extra_nodes = {}) {
  std::mt19937 rng(s.seed);
  std::normal_distribution<float> g(0.f, 0.4f);
  auto rnd = [&](size_t n) { std::vector<float> v(n); for (auto& x : v) x = g(rng); return v; };
  const int ns = s.n_state, na = s.n_action, in = s.history * (ns + na);
  Bytes graph;
  field_bytes(graph, 1, node("Gemm", {"x", "w0", "b0"}, "h0", {attr_int("transB", 1)}));
  field_bytes(graph, 1, node("Tanh", {"h0"}, "a0"));
  field_bytes(graph, 1, node("Gemm", {"a0", "w1", "b1"}, "m0", {attr_int("transB", 1)}));
  field_bytes(graph, 1, node("Tanh", {"m0"}, s.residual ? "t0" : "mean"));
  if (s.residual) residual_head(graph, s, "t0");
  if (s.gaussian) {
    field_bytes(graph, 1, node("MatMul", {"a0", "w2"}, "s0"));
    field_bytes(graph, 1, node("Add", {"s0", "b2"}, "s1"));
    field_bytes(graph, 1, node("Clip", {"s1", "lo", "hi"}, "log_std"));
  }
  if (s.limit_state >= 0) field_bytes(graph, 1, node("Gemm", {"a0", "w3", "b3"}, "event_logit", {attr_int("transB", 1)}));
  for (const auto& n : extra_nodes) field_bytes(graph, 1, n);
  field_bytes(graph, 2, "g");
  auto tensor = [&](const std::string& name, std::vector<int64_t> dims, std::vector<float> v) {
    if (name == s.bad_initializer && !v.empty()) v[0] = s.bad_value;
    return pb::tensor(name, std::move(dims), std::move(v));
  };
  field_bytes(graph, 5, tensor("w0", {s.hidden, in}, rnd(size_t(s.hidden * in))));
  field_bytes(graph, 5, tensor("b0", {s.hidden}, rnd(size_t(s.hidden))));
  field_bytes(graph, 5, tensor("w1", {ns, s.hidden}, rnd(size_t(ns * s.hidden))));
  field_bytes(graph, 5, tensor("b1", {ns}, rnd(size_t(ns))));
  if (s.gaussian) {
    field_bytes(graph, 5, tensor("w2", {s.hidden, ns}, rnd(size_t(s.hidden * ns))));
    field_bytes(graph, 5, tensor("b2", {ns}, std::vector<float>(size_t(ns), -1.5f)));
    field_bytes(graph, 5, tensor("lo", {}, {-7.f}));
    field_bytes(graph, 5, tensor("hi", {}, {1.f}));
  }
  if (s.limit_state >= 0) {
    field_bytes(graph, 5, tensor("w3", {1, s.hidden}, rnd(size_t(s.hidden))));
    field_bytes(graph, 5, tensor("b3", {1}, {-3.f}));  // events rare: most steps take the value head
  }
  field_bytes(graph, 11, value_info("x"));
  field_bytes(graph, 12, value_info("mean"));
  if (s.gaussian) field_bytes(graph, 12, value_info("log_std"));
  if (s.limit_state >= 0) field_bytes(graph, 12, value_info("event_logit"));

  Bytes m;
  field_int(m, 1, 8);  // ir_version
  field_bytes(m, 2, "envi-test");
  field_bytes(m, 7, graph);
  Bytes opset;
  field_bytes(opset, 1, "");
  field_int(opset, 2, 17);
  field_bytes(m, 8, opset);
  auto meta = [&](const std::string& k, const std::string& v) {
    Bytes e;
    field_bytes(e, 1, k);
    field_bytes(e, 2, v);
    field_bytes(m, 14, e);
  };
  meta("envi.format", "\"envi-onnx\"");
  if (ns == 1 && na == 1) {
    meta("envi.schema", R"({"states": [{"name": "color", "unit": "%", "range": [0.0, 100.0]}], )"
                        R"("actions": [{"name": "angle", "unit": "deg", "range": [-90.0, 90.0]}]})");
    meta("envi.normaliser", R"({"low": [5.0, -30.0], "high": [80.0, 30.0]})");
  } else {
    std::string states, actions, low, high;
    for (int i = 0; i < ns; ++i) {
      states += std::string(i ? ", " : "") + R"({"name": "color)" + std::to_string(i) + R"(", "unit": "%", "range": [0.0, 100.0]})";
      low += std::string(i ? ", " : "") + "5.0";
      high += std::string(i ? ", " : "") + "80.0";
    }
    for (int i = 0; i < na; ++i) {
      actions += std::string(i ? ", " : "") + R"({"name": "angle)" + std::to_string(i) + R"(", "unit": "deg", "range": [-90.0, 90.0]})";
      low += ", -30.0";
      high += ", 30.0";
    }
    meta("envi.schema", R"({"states": [)" + states + R"(], "actions": [)" + actions + "]}");
    meta("envi.normaliser", R"({"low": [)" + low + R"(], "high": [)" + high + "]}");
  }
  meta("envi.history", std::to_string(s.history));
  meta("envi.period_ms", "40.0");
  meta("envi.head", !s.head_meta.empty() ? s.head_meta : s.gaussian ? "\"gaussian\"" : "\"deterministic\"");
  meta("envi.algorithm", "\"bc\"");
  std::string post = s.post;
  if (ns > 1) {
    std::string limits;
    for (int i = 0; i < ns; ++i) limits += std::string(i ? ", " : "") + "[0.0, 100.0]";
    post = R"({"clamp": )" + std::string(s.clamp ? "true" : "false") + R"(, "limits": [)" + limits + R"(], "round_to": null})";
  }
  meta("envi.post", post);  // required: no prefix of the file is a complete model
  if (s.limit_state >= 0) meta("envi.limit_events", "[[" + std::to_string(s.limit_state) + ", 80.0]]");
  std::string residual = s.residual_meta;
  if (residual.empty() && s.residual) {
    std::string limits = s.limit_state >= 0 ? "[" + std::to_string(s.limit_state) + ", 1.0]" : "";
    residual = R"({"scale": 2.0, "tolerance": 1e-05, "limit_levels": [)" + limits + "]}";
  }
  if (!residual.empty()) meta("envi.residual", residual);
  // As envi-export does: the content hash over everything above, the last entry.
  if (s.hash) meta("envi.content_sha256", "\"" + envi::content_sha256(reinterpret_cast<const uint8_t*>(m.data()), m.size()) + "\"");
  return m;
}

}  // namespace pb
