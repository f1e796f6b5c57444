// SHA-256 (FIPS 180-4), for the content hash of exported models (envi.content_sha256).
// Hand-written rather than linked from OpenSSL: the pip build and the fuzz harness compile
// cpp/src/*.cpp with no library beyond Eigen, and one hash of a file at load needs no more.
#pragma once
#include <array>
#include <cstddef>
#include <cstdint>
#include <string>

namespace envi {

class Sha256 {
 public:
  Sha256();
  void update(const void* data, size_t size);
  void update(const std::string& s) { update(s.data(), s.size()); }
  std::array<uint8_t, 32> digest();  // finishes the hash; the object is spent afterwards
  std::string hex();                 // digest() as 64 lowercase hex digits

 private:
  void block(const uint8_t* p);
  uint32_t h_[8];
  uint8_t buf_[64];
  size_t used_ = 0;
  uint64_t bytes_ = 0;
};

// The hex digest of `size` bytes at `data`.
std::string sha256_hex(const void* data, size_t size);

}  // namespace envi
