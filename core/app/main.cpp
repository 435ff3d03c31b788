#include <exception>
#include <iostream>

#include "commands.hpp"

int main(int argc, char** argv) {
  CLI::App app{"mapmerge: merge and inspect OctoMaps offline"};
  app.require_subcommand(1);
  int exit_code = 0;
  mapmerge::app::add_merge_command(app, exit_code);
  mapmerge::app::add_render_command(app, exit_code);
  mapmerge::app::add_scenario_command(app, exit_code);
  mapmerge::app::add_report_command(app, exit_code);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int rc = app.exit(e);
    return rc == 0 ? 0 : 2;
  } catch (const std::exception& e) {
    std::cerr << "mapmerge: " << e.what() << "\n";
    return 1;
  }
  return exit_code;
}
