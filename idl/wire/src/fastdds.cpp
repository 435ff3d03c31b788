#include "mapmerge/wire/fastdds.hpp"

#include <cstring>
#include <mutex>

#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/qos/DomainParticipantQos.hpp>
#include <fastdds/rtps/common/Locator.h>
#include <fastrtps/attributes/LibrarySettingsAttributes.h>
#include <fastrtps/utils/IPLocator.h>
#include <fastrtps/xmlparser/XMLProfileManager.h>

namespace mapmerge::wire {
namespace dds = eprosima::fastdds::dds;
using eprosima::fastrtps::types::ReturnCode_t;

namespace {

constexpr const char* kStateWriterProfile = "mapmerge_state_writer";
constexpr const char* kStateReaderProfile = "mapmerge_state_reader";
constexpr const char* kEventWriterProfile = "mapmerge_event_writer";
constexpr const char* kEventReaderProfile = "mapmerge_event_reader";
/// The participant profile a user's XML file (--profile FILE.xml) may define.
constexpr const char* kUserParticipantProfile = "mapmerge";
/// Fast DDS's well-known GUID prefix of discovery server 0 (`fastdds discovery -i 0`).
constexpr const char* kDiscoveryServerPrefix = "44.53.00.5f.45.50.52.4f.53.49.4d.41";

void load_xml(const char* xml, const std::string& what) {
  auto* factory = dds::DomainParticipantFactory::get_instance();
  if (factory->load_XML_profiles_string(xml, std::strlen(xml)) != ReturnCode_t::RETCODE_OK) {
    throw DdsError("Fast DDS rejected the " + what + " profile XML");
  }
}

/// Loads the embedded profiles once per process, before any default QoS is read
/// (Fast DDS silently ignores profiles loaded after get_default_participant_qos()). A process
/// may hold two copies of this library (a program linking it and libmapmerge_client.so): the
/// factory is one per process, so a copy finding the profiles there leaves them be (loading them
/// again makes Fast DDS log an error for every profile).
void load_embedded_profiles() {
  static std::once_flag once;
  std::call_once(once, [] {
    eprosima::fastrtps::ParticipantAttributes loaded;
    if (eprosima::fastrtps::xmlparser::XMLProfileManager::fillParticipantAttributes(
            "mapmerge_default", loaded, /*log_error=*/false) == eprosima::fastrtps::xmlparser::XMLP_ret::XML_OK) {
      return;
    }
    load_xml(embedded::kFastddsQos, "mapmerge QoS");
    load_xml(embedded::kFastddsLocal, "local");
    load_xml(embedded::kFastddsDefault, "default");
    // Discovery between participants of one process goes through the transport, user data
    // still directly (a profile file the user loads may say otherwise). With discovery delivered
    // in-process (Fast DDS's default) Fast DDS 2.9 can deadlock in a process holding several
    // participants: deleting a writer hands its disposal to another participant's discovery
    // listener, which waits for that participant's PDP lock, while its holder waits for the
    // event thread, which waits for the deleting writer's lock (every thread's stack from a test
    // that hung so, after its server was killed: robots' and an observer's participants in one
    // process, session 25).
    eprosima::fastrtps::LibrarySettingsAttributes library;
    library.intraprocess_delivery = eprosima::fastrtps::INTRAPROCESS_USER_DATA_ONLY;
    eprosima::fastrtps::xmlparser::XMLProfileManager::library_settings(library);
  });
}

dds::DomainParticipantQos participant_qos(const ProfileSpec& spec) {
  auto* factory = dds::DomainParticipantFactory::get_instance();
  dds::DomainParticipantQos qos;
  const char* profile = spec.kind == ProfileSpec::Kind::Local ? "mapmerge_local" : "mapmerge_default";
  if (spec.kind == ProfileSpec::Kind::File) {
    if (factory->load_XML_profiles_file(spec.file) != ReturnCode_t::RETCODE_OK) {
      throw DdsError("Fast DDS could not load profile file '" + spec.file + "'");
    }
    profile = kUserParticipantProfile;
    if (factory->get_participant_qos_from_profile(profile, qos) != ReturnCode_t::RETCODE_OK) {
      qos = factory->get_default_participant_qos();  // the file's default profile, if any
    }
    return qos;
  }
  if (factory->get_participant_qos_from_profile(profile, qos) != ReturnCode_t::RETCODE_OK) {
    throw DdsError(std::string("Fast DDS profile '") + profile + "' is missing");
  }
  return qos;
}

void use_discovery_server(dds::DomainParticipantQos& qos, const std::string& address, bool super_client) {
  const auto colon = address.rfind(':');
  if (colon == std::string::npos) throw DdsError("discovery server must be HOST:PORT, got '" + address + "'");
  const std::string host = address.substr(0, colon);
  const int port = std::atoi(address.c_str() + colon + 1);
  if (port <= 0 || port > 65535) throw DdsError("bad discovery server port in '" + address + "'");
  eprosima::fastrtps::rtps::RemoteServerAttributes server;
  server.ReadguidPrefix(kDiscoveryServerPrefix);
  eprosima::fastrtps::rtps::Locator_t locator;
  eprosima::fastrtps::rtps::IPLocator::setIPv4(locator, host);
  locator.port = static_cast<uint32_t>(port);
  server.metatrafficUnicastLocatorList.push_back(locator);
  auto& discovery = qos.wire_protocol().builtin.discovery_config;
  discovery.discoveryProtocol = super_client ? eprosima::fastrtps::rtps::DiscoveryProtocol_t::SUPER_CLIENT
                                             : eprosima::fastrtps::rtps::DiscoveryProtocol_t::CLIENT;
  discovery.m_DiscoveryServers.push_back(server);
  // The server is the only peer: no initial peers list of our own is needed.
  qos.wire_protocol().builtin.initialPeersList.clear();
}

/// DDS Security with the builtin plugins: PKI-DH authentication, signed governance and
/// permissions, AES-GCM-GMAC. Throws if the enclave's files are missing (never falls back to
/// an insecure participant).
void use_security(dds::DomainParticipantQos& qos, const SecurityOptions& security) {
  const SecurityFiles files = security.files();
  auto& props = qos.properties().properties();
  auto set = [&props](const std::string& name, const std::string& value) {
    for (auto& p : props) {
      if (p.name() == name) {
        p.value(value);
        return;
      }
    }
    props.emplace_back(name, value);
  };
  set("dds.sec.auth.plugin", "builtin.PKI-DH");
  set("dds.sec.auth.builtin.PKI-DH.identity_ca", "file://" + files.identity_ca);
  set("dds.sec.auth.builtin.PKI-DH.identity_certificate", "file://" + files.certificate);
  set("dds.sec.auth.builtin.PKI-DH.private_key", "file://" + files.private_key);
  if (!files.crl.empty()) set("dds.sec.auth.builtin.PKI-DH.identity_crl", "file://" + files.crl);
  set("dds.sec.access.plugin", "builtin.Access-Permissions");
  set("dds.sec.access.builtin.Access-Permissions.permissions_ca", "file://" + files.permissions_ca);
  set("dds.sec.access.builtin.Access-Permissions.governance", "file://" + files.governance);
  set("dds.sec.access.builtin.Access-Permissions.permissions", "file://" + files.permissions);
  set("dds.sec.crypto.plugin", "builtin.AES-GCM-GMAC");
}

}  // namespace

FastddsParticipant::FastddsParticipant(const ParticipantOptions& options,
                                       dds::DomainParticipantListener* listener,
                                       const dds::StatusMask& mask) {
  load_embedded_profiles();
  dds::DomainParticipantQos qos = participant_qos(options.profile);
  if (!options.name.empty()) qos.name(options.name);
  if (!options.profile.discovery_server.empty()) {
    use_discovery_server(qos, options.profile.discovery_server, options.discover_all_topics);
  }
  if (options.security.enabled()) {
    try {
      use_security(qos, options.security);
    } catch (const std::invalid_argument& e) {
      throw DdsError(e.what());
    }
  }
  auto* factory = dds::DomainParticipantFactory::get_instance();
  participant_ = factory->create_participant(options.domain, qos, listener, mask);
  if (participant_ == nullptr) {
    throw DdsError("cannot create Fast DDS participant on domain " + std::to_string(options.domain) +
                   " with profile " + options.profile.describe() +
                   ", security " + options.security.describe() +
                   (options.security.enabled() ? " (rejected identity, permissions or governance?)" : ""));
  }
  publisher_ = participant_->create_publisher(dds::PUBLISHER_QOS_DEFAULT);
  subscriber_ = participant_->create_subscriber(dds::SUBSCRIBER_QOS_DEFAULT);
  if (publisher_ == nullptr || subscriber_ == nullptr) {
    participant_->delete_contained_entities();
    factory->delete_participant(participant_);
    throw DdsError("cannot create Fast DDS publisher/subscriber");
  }
}

FastddsParticipant::~FastddsParticipant() {
  if (participant_ == nullptr) return;
  participant_->delete_contained_entities();
  dds::DomainParticipantFactory::get_instance()->delete_participant(participant_);
}

dds::Topic* FastddsParticipant::topic(const std::string& name, dds::TypeSupport type) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = topics_.find(name);
  if (it != topics_.end()) return it->second;
  if (participant_->find_type(type.get_type_name()).empty() &&
      type.register_type(participant_) != ReturnCode_t::RETCODE_OK) {
    throw DdsError("cannot register type " + type.get_type_name());
  }
  dds::Topic* t = participant_->create_topic(name, type.get_type_name(), dds::TOPIC_QOS_DEFAULT);
  if (t == nullptr) throw DdsError("cannot create topic " + name);
  topics_.emplace(name, t);
  return t;
}

dds::DataWriter* FastddsParticipant::create_writer(dds::Topic* topic, TopicKind kind,
                                                   dds::DataWriterListener* listener) {
  const char* profile = kind == TopicKind::State ? kStateWriterProfile : kEventWriterProfile;
  dds::DataWriter* writer = publisher_->create_datawriter_with_profile(topic, profile, listener);
  if (writer == nullptr) throw DdsError("cannot create writer on " + topic->get_name());
  return writer;
}

dds::DataReader* FastddsParticipant::create_reader(dds::Topic* topic, TopicKind kind,
                                                   dds::DataReaderListener* listener) {
  const char* profile = kind == TopicKind::State ? kStateReaderProfile : kEventReaderProfile;
  dds::DataReader* reader = subscriber_->create_datareader_with_profile(topic, profile, listener);
  if (reader == nullptr) throw DdsError("cannot create reader on " + topic->get_name());
  return reader;
}

void FastddsParticipant::remove(dds::DataWriter* writer) {
  if (writer != nullptr) publisher_->delete_datawriter(writer);
}

void FastddsParticipant::remove(dds::DataReader* reader) {
  if (reader != nullptr) subscriber_->delete_datareader(reader);
}

}  // namespace mapmerge::wire
