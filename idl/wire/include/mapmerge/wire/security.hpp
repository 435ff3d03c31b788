#pragma once
/// DDS Security identity of a participant: which enclave of a keystore (scripts/make-keystore,
/// SROS2 layout) it uses. Empty keystore = security off (the default).

#include <string>

namespace mapmerge::wire {

/// The files of one enclave, as absolute paths (keystore/enclaves/<enclave>/...).
struct SecurityFiles {
  std::string identity_ca;     ///< identity_ca.cert.pem: CA that signs every participant's certificate
  std::string certificate;     ///< cert.pem: this participant's identity (subject CN=<enclave>)
  std::string private_key;     ///< key.pem: its private key (unencrypted PEM, ECDSA P-256)
  std::string permissions_ca;  ///< permissions_ca.cert.pem: CA that signs governance and permissions
  std::string governance;      ///< governance.p7s: signed domain rules
  std::string permissions;     ///< permissions.p7s: signed grants of this participant
  std::string crl;             ///< crl.pem: revoked certificates (make-keystore --revoke); empty: none
};

struct SecurityOptions {
  std::string keystore;  ///< keystore root directory; empty: DDS Security off
  std::string enclave;   ///< enclave name under keystore/enclaves/ (robot id or server name)

  bool enabled() const { return !keystore.empty(); }
  /// The enclave's files. Throws std::invalid_argument naming what is missing or unreadable,
  /// so a misconfigured secure participant fails loudly instead of running insecure.
  SecurityFiles files() const;
  /// "off" or "keystore DIR, enclave NAME".
  std::string describe() const;

  /// From ROS 2's variables, so SROS2 users' settings carry over: ROS_SECURITY_KEYSTORE and
  /// ROS_SECURITY_ENCLAVE (leading '/' dropped), when ROS_SECURITY_ENABLE=true. `enclave` is
  /// used when ROS_SECURITY_ENCLAVE is unset. Returns "off" otherwise.
  static SecurityOptions from_environment(const std::string& enclave = "");
};

}  // namespace mapmerge::wire
