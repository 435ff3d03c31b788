// libFuzzer target over the map-decoding entry points (issue 7): decode_map() for every wire
// encoding and decode_tree_body() for the ROS 2 message path. See fuzz_decode.hpp for the input
// format and the invariants checked.
#include "fuzz_decode.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  mapmerge::fuzz::decode_one(data, size);
  return 0;
}
