// mapmerge::Client and friends: thin forwarding to the vendor-free ClientCore.

#include "mapmerge/client/client.hpp"

#include <cmath>

#include "client_core.hpp"

namespace mapmerge {
namespace client {

const char* to_string(Vendor vendor) { return vendor == Vendor::kCyclone ? "cyclone" : "fastdds"; }

std::optional<Vendor> parse_vendor(std::string_view name) {
  if (name == "fastdds") return Vendor::kFastdds;
  if (name == "cyclone") return Vendor::kCyclone;
  return std::nullopt;
}

const char* to_string(PoseStatus status) {
  switch (status) {
    case PoseStatus::kAligned: return "aligned";
    case PoseStatus::kRejected: return "rejected";
    case PoseStatus::kUnknown: break;
  }
  return "unknown";
}

std::array<double, 16> Pose::matrix() const {
  double x = rotation[0], y = rotation[1], z = rotation[2], w = rotation[3];
  const double n = std::sqrt(x * x + y * y + z * z + w * w);
  if (n > 0.0 && std::isfinite(n)) {
    x /= n, y /= n, z /= n, w /= n;
  } else {
    x = y = z = 0.0, w = 1.0;
  }
  return {1 - 2 * (y * y + z * z), 2 * (x * y - z * w),     2 * (x * z + y * w),     translation[0],
          2 * (x * y + z * w),     1 - 2 * (x * x + z * z), 2 * (y * z - x * w),     translation[1],
          2 * (x * z - y * w),     2 * (y * z + x * w),     1 - 2 * (x * x + y * y), translation[2],
          0.0,                     0.0,                     0.0,                     1.0};
}

}  // namespace client

Client::Client(client::Options options) : Client(std::move(options), client::Vendor::kFastdds) {}

Client::Client(client::Options options, client::Vendor vendor)
    : core_(std::make_unique<client::detail::ClientCore>(std::move(options), vendor)) {}

Client::~Client() = default;

client::PublishResult Client::publish(const octomap::OcTree& tree) { return core_->publish(tree); }
bool Client::flush(std::chrono::milliseconds timeout) { return core_->flush(timeout); }
bool Client::server_connected() const { return core_->server_connected(); }
bool Client::wait_for_server(std::chrono::milliseconds timeout) { return core_->wait_for_server(timeout); }
void Client::request_global_map() { core_->request_global_map(); }

std::optional<client::Pose> Client::own_pose() const {
  if (core_->robot_id().empty()) return std::nullopt;
  return core_->pose(core_->robot_id());
}
std::optional<client::Pose> Client::pose(const std::string& robot_id) const { return core_->pose(robot_id); }
std::vector<client::Pose> Client::poses() const { return core_->poses(); }
std::shared_ptr<const client::GlobalMap> Client::global_map() const { return core_->global_map(); }

void Client::on_own_pose(client::PoseCallback callback) { core_->set_own_pose_callback(std::move(callback)); }
void Client::on_pose(client::PoseCallback callback) { core_->set_pose_callback(std::move(callback)); }
void Client::on_global_map(client::GlobalMapCallback callback) { core_->set_global_map_callback(std::move(callback)); }
void Client::on_server_connection(client::ConnectionCallback callback) {
  core_->set_connection_callback(std::move(callback));
}
void Client::on_warning(client::WarningCallback callback) { core_->set_warning_callback(std::move(callback)); }

const std::string& Client::robot_id() const { return core_->robot_id(); }
const std::string& Client::session_id() const { return core_->session_id(); }
client::Vendor Client::vendor() const { return core_->vendor(); }
client::Statistics Client::statistics() const { return core_->statistics(); }

CycloneClient::CycloneClient(client::Options options) : Client(std::move(options), client::Vendor::kCyclone) {}

std::unique_ptr<Client> make_client(client::Options options, client::Vendor vendor) {
  if (vendor == client::Vendor::kCyclone) return std::make_unique<CycloneClient>(std::move(options));
  return std::make_unique<Client>(std::move(options));
}

}  // namespace mapmerge
