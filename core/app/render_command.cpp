#include <iostream>

#include "commands.hpp"

namespace mapmerge::app {

// Placeholder until the render subcommand lands.
void add_render_command(CLI::App& app, int& exit_code) {
  auto* cmd = app.add_subcommand("render", "(not implemented yet)");
  cmd->callback([&exit_code] {
    std::cerr << "mapmerge render: not implemented yet\n";
    exit_code = 2;
  });
}

}  // namespace mapmerge::app
