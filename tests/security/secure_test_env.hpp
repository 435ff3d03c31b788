#pragma once
/// Keystores and bounded waits for the DDS Security tests.
///
/// Every test process makes its keystores with scripts/make-keystore in a fresh temporary
/// directory (nothing shared between tests, nothing committed):
///   trusted   the fleet's keystore: server "mapmerge_server", robots r1 and r2
///   other_ca  another CA's keystore with its own robot "r1" (a stranger with a look-alike name)
/// plus two hand-made enclaves:
///   forged/enclaves/r1   trusted r1's cert and key + permissions granting the server's topics,
///                        signed by other_ca's CA (with its governance and permissions CA): a
///                        stolen robot key with self-made permissions. It passes its own local
///                        checks; peers must refuse it.
///   stolen/enclaves/r1   trusted r1's cert and key + r2's (validly signed) permissions

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <initializer_list>
#include <stdexcept>
#include <string>
#include <thread>

#include <stdlib.h>

#include "mapmerge/wire/security.hpp"

namespace mapmerge::test {

namespace fs = std::filesystem;

class SecureKeystores {
 public:
  SecureKeystores() {
    char tmpl[] = "/tmp/mapmerge-security-test-XXXXXX";
    if (::mkdtemp(tmpl) == nullptr) throw std::runtime_error("mkdtemp failed");
    root_ = tmpl;
    make(trusted(), "--robots r1,r2");
    make(other_ca(), "--robots r1");
    splice(forged(), "r1", trusted(), other_ca(), {"permissions_ca.cert.pem", "governance.p7s"});
    forge_permissions(forged() + "/enclaves/r1/permissions.p7s", "CN=r1", other_ca());
    splice(stolen(), "r1", trusted(), trusted(), {});
    fs::copy_file(fs::path(trusted()) / "enclaves/r2/permissions.p7s", fs::path(stolen()) / "enclaves/r1/permissions.p7s",
                  fs::copy_options::overwrite_existing);
  }
  ~SecureKeystores() {
    std::error_code ignored;
    fs::remove_all(root_, ignored);
  }
  SecureKeystores(const SecureKeystores&) = delete;
  SecureKeystores& operator=(const SecureKeystores&) = delete;

  std::string trusted() const { return root_ + "/trusted"; }
  std::string other_ca() const { return root_ + "/other_ca"; }
  std::string forged() const { return root_ + "/forged"; }
  std::string stolen() const { return root_ + "/stolen"; }
  /// A keystore for a Cyclone DDS server (make-keystore --server-vendor cyclone), made on first use.
  std::string cyclone_server() {
    const std::string dir = root_ + "/cyclone_server";
    if (!fs::exists(dir)) make(dir, "--robots r1,r2 --server-vendor cyclone");
    return dir;
  }
  /// A fresh directory under this test's temporary root.
  std::string scratch(const std::string& name) const { return root_ + "/" + name; }

  static void make(const std::string& dir, const std::string& args) {
    // MAPMERGE_MAKE_KEYSTORE in the environment: another script (e.g. a deliberately broken copy,
    // to see these tests fail).
    const char* script = std::getenv("MAPMERGE_MAKE_KEYSTORE");
    const std::string cmd = std::string(script != nullptr ? script : MAPMERGE_MAKE_KEYSTORE) + " " + dir + " " + args +
                            " >/dev/null";
    if (std::system(cmd.c_str()) != 0) throw std::runtime_error("failed: " + cmd);
  }

  static wire::SecurityOptions identity(const std::string& keystore, const std::string& enclave) {
    return wire::SecurityOptions{keystore, enclave};
  }

  /// Permissions for `subject` to publish the server's topics, signed by `keystore`'s CA.
  void forge_permissions(const std::string& p7s, const std::string& subject, const std::string& keystore) const {
    const std::string xml = root_ + "/forged-permissions.xml";
    std::ofstream(xml) << "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<dds><permissions><grant name=\"forged\">"
                       << "<subject_name>" << subject << "</subject_name>"
                       << "<validity><not_before>2000-01-01T00:00:00</not_before>"
                       << "<not_after>2100-01-01T00:00:00</not_after></validity>"
                       << "<allow_rule><domains><id_range><min>0</min><max>232</max></id_range></domains>"
                       << "<publish><topics><topic>rt/mapmerge/*</topic><topic>rt/*/mapmerge/map</topic></topics></publish>"
                       << "<subscribe><topics><topic>*</topic></topics></subscribe>"
                       << "</allow_rule><default>DENY</default></grant></permissions></dds>\n";
    const std::string cmd = "openssl smime -sign -text -md sha256 -in " + xml + " -out " + p7s + " -signer " +
                            keystore + "/public/ca.cert.pem -inkey " + keystore + "/private/ca.key.pem";
    if (std::system(cmd.c_str()) != 0) throw std::runtime_error("failed: " + cmd);
  }

  /// Keystore `dir` gets enclave `name` made of `base`'s files, with `replaced` taken from `donor`.
  static void splice(const std::string& dir, const std::string& name, const std::string& base,
                     const std::string& donor, std::initializer_list<const char*> replaced) {
    const fs::path out = fs::path(dir) / "enclaves" / name;
    fs::create_directories(out);
    for (const char* f : {"cert.pem", "key.pem", "identity_ca.cert.pem", "permissions_ca.cert.pem", "governance.p7s",
                          "permissions.p7s"}) {
      fs::copy_file(fs::path(base) / "enclaves" / name / f, out / f, fs::copy_options::overwrite_existing);
    }
    for (const char* f : replaced) {
      fs::copy_file(fs::path(donor) / "enclaves" / name / f, out / f, fs::copy_options::overwrite_existing);
    }
  }

 private:
  std::string root_;
};

/// Polls `done` every 20 ms until it holds or `timeout` passes; returns whether it held.
inline bool eventually(const std::function<bool()>& done, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (done()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return done();
}

}  // namespace mapmerge::test
