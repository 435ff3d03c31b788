#include "mapmerge/wire/profile.hpp"

#include <fstream>
#include <stdexcept>

namespace mapmerge::wire {

ProfileSpec ProfileSpec::parse(const std::string& text) {
  ProfileSpec spec;
  if (text == "local") {
    spec.kind = Kind::Local;
  } else if (text == "default") {
    spec.kind = Kind::Default;
  } else if (text.size() > 4 && text.compare(text.size() - 4, 4, ".xml") == 0) {
    if (!std::ifstream(text)) throw std::invalid_argument("DDS profile file '" + text + "' cannot be read");
    spec.kind = Kind::File;
    spec.file = text;
  } else {
    throw std::invalid_argument("unknown DDS profile '" + text + "' (expected local, default or FILE.xml)");
  }
  return spec;
}

std::string ProfileSpec::describe() const {
  std::string s = kind == Kind::Local ? "local" : kind == Kind::Default ? "default" : file;
  if (!discovery_server.empty()) s += " (discovery server " + discovery_server + ")";
  return s;
}

}  // namespace mapmerge::wire
