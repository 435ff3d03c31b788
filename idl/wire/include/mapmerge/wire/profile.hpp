#pragma once
/// Which DDS network configuration a participant uses.

#include <string>

namespace mapmerge::wire {

/// Topic QoS classes (idl/profiles/fastdds_qos.xml; mirrored for Cyclone in cyclone.cpp).
enum class TopicKind {
  State,  ///< maps, global map, poses: reliable, transient-local, keep-last 1 per key
  Event,  ///< status, merge reports, requests, tf: reliable, volatile, keep-last 16
};

struct ProfileSpec {
  enum class Kind {
    Local,    ///< all traffic on 127.0.0.1 (tests, demo, benchmarks)
    Default,  ///< the vendor's normal interfaces and discovery (a real fleet)
    File,     ///< a user's XML: Fast DDS profiles (participant "mapmerge") or a Cyclone config
  };
  Kind kind = Kind::Local;
  std::string file;              ///< the XML file when kind == File
  std::string discovery_server;  ///< "HOST:PORT" of a Fast DDS discovery server; empty: none

  /// "local", "default" or a path to an XML file. Throws std::invalid_argument otherwise.
  static ProfileSpec parse(const std::string& text);
  std::string describe() const;
};

namespace embedded {
extern const char* const kFastddsQos;
extern const char* const kFastddsLocal;
extern const char* const kFastddsDefault;
extern const char* const kCycloneLocal;
extern const char* const kCycloneDefault;
}  // namespace embedded

}  // namespace mapmerge::wire
