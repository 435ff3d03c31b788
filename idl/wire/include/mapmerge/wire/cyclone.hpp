#pragma once
/// Cyclone DDS (C API) participants configured from mapmerge's profiles.

#include <stdexcept>
#include <string>

#include <dds/dds.h>

#include "mapmerge/wire/profile.hpp"
#include "mapmerge/wire/security.hpp"

namespace mapmerge::wire {

/// Thrown when a Cyclone DDS entity cannot be created.
class CycloneError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// One Cyclone DDS participant in a domain configured from a mapmerge profile. Deleting it
/// deletes every entity it created. Several may share a domain within one process.
/// With `security` enabled the participant uses DDS Security (Cyclone's builtin plugins, set
/// through participant QoS properties); a secure participant's writers and readers are refused
/// (CycloneError) on topics its permissions do not grant.
class CycloneParticipant {
 public:
  CycloneParticipant(int domain, const ProfileSpec& profile, const SecurityOptions& security = {});
  ~CycloneParticipant();
  CycloneParticipant(const CycloneParticipant&) = delete;
  CycloneParticipant& operator=(const CycloneParticipant&) = delete;

  dds_entity_t participant() const { return participant_; }
  dds_entity_t topic(const dds_topic_descriptor_t* descriptor, const std::string& name);
  dds_entity_t create_writer(dds_entity_t topic, TopicKind kind);
  dds_entity_t create_reader(dds_entity_t topic, TopicKind kind);

 private:
  int domain_;
  dds_entity_t participant_ = 0;
};

/// The QoS of a topic kind, as in idl/profiles/fastdds_qos.xml. Caller frees with dds_delete_qos.
dds_qos_t* make_cyclone_qos(TopicKind kind);

}  // namespace mapmerge::wire
