// Writes small ONNX models byte by byte (protobuf wire format), so the C++ tests and the fuzzer
// need neither Python nor libprotobuf, and can build the broken files they want.
#pragma once
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

inline Bytes attr_int(const std::string& name, int64_t v) {
  Bytes a;
  field_bytes(a, 1, name);
  field_int(a, 3, uint64_t(v));
  field_int(a, 20, 2);  // INT
  return a;
}

inline Bytes node(const std::string& op, const std::vector<std::string>& in, const std::string& out,
                  const std::vector<Bytes>& attrs = {}, const std::string& domain = "") {
  Bytes n;
  for (const auto& i : in) field_bytes(n, 1, i);
  field_bytes(n, 2, out);
  field_bytes(n, 3, out + "_node");
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
};

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
  field_bytes(graph, 1, node("Tanh", {"m0"}, "mean"));
  if (s.gaussian) {
    field_bytes(graph, 1, node("MatMul", {"a0", "w2"}, "s0"));
    field_bytes(graph, 1, node("Add", {"s0", "b2"}, "s1"));
    field_bytes(graph, 1, node("Clip", {"s1", "lo", "hi"}, "log_std"));
  }
  for (const auto& n : extra_nodes) field_bytes(graph, 1, n);
  field_bytes(graph, 2, "g");
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
  field_bytes(graph, 11, value_info("x"));
  field_bytes(graph, 12, value_info("mean"));
  if (s.gaussian) field_bytes(graph, 12, value_info("log_std"));

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
  meta("envi.head", s.gaussian ? "\"gaussian\"" : "\"deterministic\"");
  meta("envi.algorithm", "\"bc\"");
  std::string post = s.post;
  if (ns > 1) {
    std::string limits;
    for (int i = 0; i < ns; ++i) limits += std::string(i ? ", " : "") + "[0.0, 100.0]";
    post = R"({"clamp": true, "limits": [)" + limits + R"(], "round_to": null})";
  }
  meta("envi.post", post);  // required: no prefix of the file is a complete model
  // As envi-export does: the content hash over everything above, the last entry.
  if (s.hash) meta("envi.content_sha256", "\"" + envi::content_sha256(reinterpret_cast<const uint8_t*>(m.data()), m.size()) + "\"");
  return m;
}

}  // namespace pb
