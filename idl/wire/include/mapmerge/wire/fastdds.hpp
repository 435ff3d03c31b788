#pragma once
/// Fast DDS participants configured from mapmerge's profiles.

#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>

#include "mapmerge/wire/profile.hpp"
#include "mapmerge/wire/security.hpp"

namespace mapmerge::wire {

/// Thrown when a DDS entity cannot be created (the message says which and why).
class DdsError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct ParticipantOptions {
  int domain = 0;        ///< DDS domain id (0..101 on hosts with the default port range)
  ProfileSpec profile;   ///< network configuration
  std::string name;      ///< participant name shown in discovery tools
  SecurityOptions security;  ///< DDS Security identity (scripts/make-keystore); default: off
  /// With a discovery server: join as SUPER_CLIENT, which receives the discovery data of every
  /// topic (a plain CLIENT hears only of topics it reads or writes). For services that
  /// subscribe to topics as they appear (mapmerge-server).
  bool discover_all_topics = false;
};

/// One Fast DDS participant with one publisher and one subscriber. Everything it created is
/// deleted in its destructor. Topics are created once per name and reused.
class FastddsParticipant {
 public:
  explicit FastddsParticipant(const ParticipantOptions& options,
                              eprosima::fastdds::dds::DomainParticipantListener* listener = nullptr,
                              const eprosima::fastdds::dds::StatusMask& mask =
                                  eprosima::fastdds::dds::StatusMask::none());
  ~FastddsParticipant();
  FastddsParticipant(const FastddsParticipant&) = delete;
  FastddsParticipant& operator=(const FastddsParticipant&) = delete;

  eprosima::fastdds::dds::DomainParticipant* participant() const { return participant_; }

  /// The topic `name` of type PubSubType (registered on first use).
  template <class PubSubType>
  eprosima::fastdds::dds::Topic* topic(const std::string& name) {
    eprosima::fastdds::dds::TypeSupport type(new PubSubType());
    return topic(name, type);
  }
  eprosima::fastdds::dds::Topic* topic(const std::string& name, eprosima::fastdds::dds::TypeSupport type);

  eprosima::fastdds::dds::DataWriter* create_writer(
      eprosima::fastdds::dds::Topic* topic, TopicKind kind,
      eprosima::fastdds::dds::DataWriterListener* listener = nullptr);
  eprosima::fastdds::dds::DataReader* create_reader(
      eprosima::fastdds::dds::Topic* topic, TopicKind kind,
      eprosima::fastdds::dds::DataReaderListener* listener = nullptr);
  /// Deletes a writer or reader made by this participant (topics stay).
  void remove(eprosima::fastdds::dds::DataWriter* writer);
  void remove(eprosima::fastdds::dds::DataReader* reader);

 private:
  eprosima::fastdds::dds::DomainParticipant* participant_ = nullptr;
  eprosima::fastdds::dds::Publisher* publisher_ = nullptr;
  eprosima::fastdds::dds::Subscriber* subscriber_ = nullptr;
  std::mutex mutex_;
  std::map<std::string, eprosima::fastdds::dds::Topic*> topics_;
};

}  // namespace mapmerge::wire
