// A ROS 2-style participant on Fast DDS (the default ROS 2 middleware), independent of Prime's Cyclone DDS:
//   peer DOMAIN STATES SECONDS STIFFNESS DAMPING TARGET0 ... TARGET13
// reads STATES joint states from rt/prime/joint_states (printing one "JS" line each: arrival in
// CLOCK_MONOTONIC ns, stamp, names, positions), then streams MitCommands with the given targets for SECONDS
// on rt/remote_policy_controller/command (joint names as received), asks for REMOTE on rt/prime/mode_request,
// and keeps printing the joint states it reads. ROS 2's default QoS: reliable, volatile, keep-last 10.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <string>
#include <thread>
#include <vector>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include "gen/prime_typesPubSubTypes.h"

using namespace eprosima::fastdds::dds;

template <class Qos> static void ros_default(Qos& q) {
  q.reliability().kind = RELIABLE_RELIABILITY_QOS;  // a Fast DDS reader defaults to best effort
  q.durability().kind = VOLATILE_DURABILITY_QOS;
  q.history().kind = KEEP_LAST_HISTORY_QOS;
  q.history().depth = 10;
}

static long long monotonic_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

int main(int argc, char** argv) {
  if (argc != 20) {
    std::fprintf(stderr, "usage: %s DOMAIN STATES SECONDS STIFFNESS DAMPING TARGET0..TARGET13\n", argv[0]);
    return 2;
  }
  const int domain = std::atoi(argv[1]);
  const int states = std::atoi(argv[2]);
  const double seconds = std::atof(argv[3]);
  const double stiffness = std::atof(argv[4]);
  const double damping = std::atof(argv[5]);
  std::vector<double> target;
  for (int i = 6; i < 20; ++i) target.push_back(std::atof(argv[i]));

  auto* factory = DomainParticipantFactory::get_instance();
  DomainParticipant* dp = factory->create_participant(domain, PARTICIPANT_QOS_DEFAULT);
  if (dp == nullptr) { std::fprintf(stderr, "cannot create a participant in domain %d\n", domain); return 3; }
  TypeSupport js_type(new sensor_msgs::msg::dds_::JointState_PubSubType());
  TypeSupport mit_type(new prime_msgs::msg::dds_::MitCommand_PubSubType());
  TypeSupport string_type(new std_msgs::msg::dds_::String_PubSubType());
  js_type.register_type(dp);
  mit_type.register_type(dp);
  string_type.register_type(dp);
  Topic* js_topic = dp->create_topic("rt/prime/joint_states", js_type.get_type_name(), TOPIC_QOS_DEFAULT);
  Topic* mit_topic = dp->create_topic("rt/remote_policy_controller/command", mit_type.get_type_name(),
                                      TOPIC_QOS_DEFAULT);
  Topic* mode_topic = dp->create_topic("rt/prime/mode_request", string_type.get_type_name(), TOPIC_QOS_DEFAULT);
  DataReaderQos rq = DATAREADER_QOS_DEFAULT;
  ros_default(rq);
  DataWriterQos wq = DATAWRITER_QOS_DEFAULT;
  ros_default(wq);
  DataReader* reader = dp->create_subscriber(SUBSCRIBER_QOS_DEFAULT)->create_datareader(js_topic, rq);
  Publisher* publisher = dp->create_publisher(PUBLISHER_QOS_DEFAULT);
  DataWriter* commands = publisher->create_datawriter(mit_topic, wq);
  DataWriter* modes = publisher->create_datawriter(mode_topic, wq);

  int got = 0;
  std::vector<std::string> names;
  auto read = [&]() {
    sensor_msgs::msg::dds_::JointState_ m;
    SampleInfo info;
    while (reader->take_next_sample(&m, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      ++got;
      names = m.name();
      std::printf("JS %lld %d.%09u ", monotonic_ns(), m.header().stamp().sec(), m.header().stamp().nanosec());
      for (size_t i = 0; i < m.name().size(); ++i) std::printf("%s%s", i ? "," : "", m.name()[i].c_str());
      std::printf(" ");
      for (size_t i = 0; i < m.position().size(); ++i) std::printf("%s%.6f", i ? "," : "", m.position()[i]);
      std::printf("\n");
    }
    std::fflush(stdout);
  };

  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (got < states && std::chrono::steady_clock::now() < give_up) {
    if (reader->wait_for_unread_message(eprosima::fastrtps::Duration_t(0, 100000000))) read();
  }
  if (got < states) { std::fprintf(stderr, "only %d joint states\n", got); return 1; }

  PublicationMatchedStatus matched{};
  while (std::chrono::steady_clock::now() < give_up) {
    commands->get_publication_matched_status(matched);
    if (matched.current_count > 0) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (matched.current_count == 0) { std::fprintf(stderr, "nobody takes the commands\n"); return 1; }

  prime_msgs::msg::dds_::MitCommand_ command;
  command.name(names);
  command.position(target);
  command.velocity(std::vector<double>(names.size(), 0.0));
  command.effort(std::vector<double>(names.size(), 0.0));
  command.stiffness(std::vector<double>(names.size(), stiffness));
  command.damping(std::vector<double>(names.size(), damping));
  std_msgs::msg::dds_::String_ remote;
  remote.data("REMOTE");
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  int sent = 0;
  while (std::chrono::steady_clock::now() < end) {
    const long long now = monotonic_ns();
    command.header().stamp().sec(static_cast<int>(now / 1000000000LL));
    command.header().stamp().nanosec(static_cast<unsigned>(now % 1000000000LL));
    commands->write(&command);
    if (++sent == 3) modes->write(&remote);  // commands are flowing: REMOTE starts on a fresh one
    read();
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::printf("SENT %d\n", sent);
  commands->wait_for_acknowledgments(eprosima::fastrtps::Duration_t(2, 0));
  dp->delete_contained_entities();
  factory->delete_participant(dp);
  return 0;
}
