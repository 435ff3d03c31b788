#pragma once
/// Subcommands of the offline `mapmerge` tool. Each registers itself on the CLI11 app and
/// sets `exit_code` when it runs (0 ok, 1 bad input, 2 bad usage, 3 no accepted alignment).

#include <CLI/CLI.hpp>

namespace mapmerge::app {

void add_merge_command(CLI::App& app, int& exit_code);
void add_render_command(CLI::App& app, int& exit_code);
void add_scenario_command(CLI::App& app, int& exit_code);
void add_report_command(CLI::App& app, int& exit_code);

}  // namespace mapmerge::app
