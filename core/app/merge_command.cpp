#include <iostream>

#include "commands.hpp"

namespace mapmerge::app {

// Placeholder until the merge subcommand lands.
void add_merge_command(CLI::App& app, int& exit_code) {
  auto* cmd = app.add_subcommand("merge", "(not implemented yet)");
  cmd->callback([&exit_code] {
    std::cerr << "mapmerge merge: not implemented yet\n";
    exit_code = 2;
  });
}

}  // namespace mapmerge::app
