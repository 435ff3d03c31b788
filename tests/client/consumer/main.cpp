// Builds against the installed headers only: mapmerge/client/client.hpp and OctoMap.
#include <cstdlib>
#include <iostream>

#include <mapmerge/client/client.hpp>
#include <octomap/OcTree.h>

int main(int argc, char** argv) {
  if (argc != 2) return 2;
  mapmerge::client::Options options;
  options.robot_id = "consumer";
  options.domain = std::atoi(argv[1]);
  mapmerge::Client client(options);  // local profile: 127.0.0.1 only
  octomap::OcTree tree(0.1);
  tree.updateNode(octomap::point3d(1.0f, 2.0f, 0.5f), true);
  const auto result = client.publish(tree);
  if (!result.queued || result.sequence_number != 1) {
    std::cerr << "publish failed: " << result.error << "\n";
    return 1;
  }
  std::cout << "published " << result.bytes << " bytes as " << result.encoding << " in session "
            << client.session_id() << "\n";
  return 0;
}
