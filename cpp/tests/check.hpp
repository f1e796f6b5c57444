// Minimal test helpers: CHECK records a failure and goes on; main returns the failure count.
#pragma once
#include <cstdio>
#include <string>

inline int& failures() {
  static int n = 0;
  return n;
}
#define CHECK(cond)                                                     \
  do {                                                                  \
    if (!(cond)) {                                                      \
      std::fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond); \
      ++failures();                                                     \
    }                                                                   \
  } while (0)
// The call must throw E whose message contains `part`.
#define CHECK_THROWS(E, call, part)                                                        \
  do {                                                                                     \
    bool thrown = false;                                                                   \
    try {                                                                                  \
      call;                                                                                \
    } catch (const E& e) {                                                                 \
      thrown = std::string(e.what()).find(part) != std::string::npos;                      \
      if (!thrown) std::fprintf(stderr, "%s:%d: message was: %s\n", __FILE__, __LINE__, e.what()); \
    }                                                                                      \
    if (!thrown) {                                                                         \
      std::fprintf(stderr, "%s:%d: expected %s mentioning '%s'\n", __FILE__, __LINE__, #E, part); \
      ++failures();                                                                        \
    }                                                                                      \
  } while (0)
