#include "mapmerge/wire/security.hpp"

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <stdexcept>

namespace mapmerge::wire {
namespace fs = std::filesystem;

namespace {

std::string existing_file(const fs::path& dir, const char* name) {
  const fs::path path = dir / name;
  if (!std::ifstream(path)) {
    throw std::invalid_argument("DDS Security: cannot read " + path.string() +
                                " (make it with scripts/make-keystore)");
  }
  return path.string();
}

}  // namespace

SecurityFiles SecurityOptions::files() const {
  if (!enabled()) throw std::invalid_argument("DDS Security: no keystore given");
  if (enclave.empty() || enclave.find('/') != std::string::npos || enclave == "." || enclave == "..") {
    throw std::invalid_argument("DDS Security: bad enclave name '" + enclave + "'");
  }
  const fs::path dir = fs::absolute(fs::path(keystore) / "enclaves" / enclave);
  if (!fs::is_directory(dir)) {
    throw std::invalid_argument("DDS Security: no enclave '" + enclave + "' in keystore " + keystore +
                                " (scripts/make-keystore " + keystore + " --robots " + enclave + ")");
  }
  SecurityFiles f;
  f.identity_ca = existing_file(dir, "identity_ca.cert.pem");
  f.certificate = existing_file(dir, "cert.pem");
  f.private_key = existing_file(dir, "key.pem");
  f.permissions_ca = existing_file(dir, "permissions_ca.cert.pem");
  f.governance = existing_file(dir, "governance.p7s");
  f.permissions = existing_file(dir, "permissions.p7s");
  if (std::ifstream(dir / "crl.pem")) f.crl = (dir / "crl.pem").string();  // older keystores have none
  return f;
}

std::string SecurityOptions::describe() const {
  if (!enabled()) return "off";
  return "keystore " + keystore + ", enclave " + enclave;
}

SecurityOptions SecurityOptions::from_environment(const std::string& enclave) {
  SecurityOptions s;
  const char* enable = std::getenv("ROS_SECURITY_ENABLE");
  const char* keystore = std::getenv("ROS_SECURITY_KEYSTORE");
  if (enable == nullptr || std::string(enable) != "true" || keystore == nullptr || *keystore == '\0') return s;
  s.keystore = keystore;
  const char* env_enclave = std::getenv("ROS_SECURITY_ENCLAVE");
  s.enclave = env_enclave != nullptr && *env_enclave != '\0' ? env_enclave : enclave;
  while (!s.enclave.empty() && s.enclave.front() == '/') s.enclave.erase(0, 1);
  return s;
}

}  // namespace mapmerge::wire
