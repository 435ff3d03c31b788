#include "mapmerge/wire/cyclone.hpp"

#include <dlfcn.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>

namespace mapmerge::wire {
namespace {

/// Cyclone configures a domain once per process: keep the domain handle while any
/// CycloneParticipant of ours uses it.
struct DomainRegistry {
  std::mutex mutex;
  std::map<int, std::pair<dds_entity_t, int>> domains;  // id -> (handle, users)
};

DomainRegistry& registry() {
  static DomainRegistry r;
  return r;
}

std::string read_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw CycloneError("cannot read Cyclone DDS config '" + path + "'");
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string config_xml(const ProfileSpec& profile) {
  switch (profile.kind) {
    case ProfileSpec::Kind::Local: return embedded::kCycloneLocal;
    case ProfileSpec::Kind::Default: return embedded::kCycloneDefault;
    case ProfileSpec::Kind::File: return read_file(profile.file);
  }
  return embedded::kCycloneLocal;
}

void acquire_domain(int domain, const ProfileSpec& profile) {
  auto& r = registry();
  std::lock_guard<std::mutex> lock(r.mutex);
  auto it = r.domains.find(domain);
  if (it != r.domains.end()) {
    ++it->second.second;
    return;
  }
  const std::string xml = config_xml(profile);
  const dds_entity_t handle = dds_create_domain(static_cast<dds_domainid_t>(domain), xml.c_str());
  if (handle < 0) {
    throw CycloneError("cannot create Cyclone DDS domain " + std::to_string(domain) + ": " +
                       dds_strretcode(handle));
  }
  r.domains.emplace(domain, std::make_pair(handle, 1));
}

void release_domain(int domain) {
  auto& r = registry();
  std::lock_guard<std::mutex> lock(r.mutex);
  auto it = r.domains.find(domain);
  if (it == r.domains.end()) return;
  if (--it->second.second == 0) {
    dds_delete(it->second.first);
    r.domains.erase(it);
  }
}

/// Where Cyclone's security plugins live: Debian installs them in libddsc0debian/ beside
/// libddsc, outside the loader's search path, so give dlopen a full path when they are there.
std::string security_plugin(const char* name) {
  Dl_info info{};
  if (dladdr(reinterpret_cast<void*>(&dds_create_participant), &info) != 0 && info.dli_fname != nullptr) {
    const auto dir = std::filesystem::path(info.dli_fname).parent_path();
    for (const char* sub : {"libddsc0debian", ""}) {
      const auto path = dir / sub / (std::string("lib") + name + ".so");
      if (std::filesystem::exists(path)) return path.string();
    }
  }
  return name;  // Cyclone adds lib/.so and asks the loader
}

/// Participant QoS carrying the DDS Security properties of `security` (caller frees).
dds_qos_t* security_qos(const SecurityOptions& security) {
  SecurityFiles files;
  try {
    files = security.files();
  } catch (const std::invalid_argument& e) {
    throw CycloneError(e.what());
  }
  dds_qos_t* qos = dds_create_qos();
  const std::pair<const char*, std::string> props[] = {
      {"dds.sec.auth.library.path", security_plugin("dds_security_auth")},
      {"dds.sec.auth.library.init", "init_authentication"},
      {"dds.sec.auth.library.finalize", "finalize_authentication"},
      {"dds.sec.auth.identity_ca", "file:" + files.identity_ca},
      {"dds.sec.auth.identity_certificate", "file:" + files.certificate},
      {"dds.sec.auth.private_key", "file:" + files.private_key},
      {"dds.sec.access.library.path", security_plugin("dds_security_ac")},
      {"dds.sec.access.library.init", "init_access_control"},
      {"dds.sec.access.library.finalize", "finalize_access_control"},
      {"dds.sec.access.permissions_ca", "file:" + files.permissions_ca},
      {"dds.sec.access.governance", "file:" + files.governance},
      {"dds.sec.access.permissions", "file:" + files.permissions},
      {"dds.sec.crypto.library.path", security_plugin("dds_security_crypto")},
      {"dds.sec.crypto.library.init", "init_crypto"},
      {"dds.sec.crypto.library.finalize", "finalize_crypto"},
  };
  for (const auto& [name, value] : props) dds_qset_prop(qos, name, value.c_str());
  if (!files.crl.empty()) dds_qset_prop(qos, "org.eclipse.cyclonedds.sec.auth.crl", ("file:" + files.crl).c_str());
  return qos;
}

}  // namespace

dds_qos_t* make_cyclone_qos(TopicKind kind) {
  dds_qos_t* qos = dds_create_qos();
  if (kind == TopicKind::State) {
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
    dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
    dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 1);
  } else {
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_MSECS(200));
    dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
    dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 16);
  }
  return qos;
}

CycloneParticipant::CycloneParticipant(int domain, const ProfileSpec& profile, const SecurityOptions& security)
    : domain_(domain) {
  dds_qos_t* qos = security.enabled() ? security_qos(security) : nullptr;
  acquire_domain(domain, profile);
  participant_ = dds_create_participant(static_cast<dds_domainid_t>(domain), qos, nullptr);
  if (qos != nullptr) dds_delete_qos(qos);
  if (participant_ < 0) {
    const std::string why = dds_strretcode(participant_);
    release_domain(domain);
    throw CycloneError("cannot create Cyclone DDS participant on domain " + std::to_string(domain) + ": " + why +
                       " (security " + security.describe() + ")");
  }
}

CycloneParticipant::~CycloneParticipant() {
  dds_delete(participant_);
  release_domain(domain_);
}

dds_entity_t CycloneParticipant::topic(const dds_topic_descriptor_t* descriptor, const std::string& name) {
  const dds_entity_t t = dds_create_topic(participant_, descriptor, name.c_str(), nullptr, nullptr);
  if (t < 0) throw CycloneError("cannot create Cyclone topic " + name + ": " + dds_strretcode(t));
  return t;
}

dds_entity_t CycloneParticipant::create_writer(dds_entity_t topic, TopicKind kind) {
  dds_qos_t* qos = make_cyclone_qos(kind);
  const dds_entity_t w = dds_create_writer(participant_, topic, qos, nullptr);
  dds_delete_qos(qos);
  if (w < 0) throw CycloneError(std::string("cannot create Cyclone writer: ") + dds_strretcode(w));
  return w;
}

dds_entity_t CycloneParticipant::create_reader(dds_entity_t topic, TopicKind kind) {
  dds_qos_t* qos = make_cyclone_qos(kind);
  const dds_entity_t r = dds_create_reader(participant_, topic, qos, nullptr);
  dds_delete_qos(qos);
  if (r < 0) throw CycloneError(std::string("cannot create Cyclone reader: ") + dds_strretcode(r));
  return r;
}

}  // namespace mapmerge::wire
