// SLAM options by name: a config file of "key = value" lines and single "key=value" settings
// (flatslam run --config FILE --set KEY=VALUE), so a run can be tuned without rebuilding.
// Keys are the option fields with their struct as prefix: "orb.features", "stereo.sad_half_window",
// "bundle_adjustment.first_pass_iterations", "min_local_map_inliers"; every key comes from the
// option lists (core/option_fields.h, SlamOptions::VisitAll).
// Concurrency: free functions on the caller's options.
#pragma once

#include <filesystem>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "config/options.h"

namespace flatslam {

struct OrbSettings;  // io/orb_settings.h

// Sets one option. Throws flatslam::Error naming the key when it is unknown or the value does not
// parse as the option's type (integer, real or true/false). `where` prefixes the message (a file
// and line, or "--set").
void SetSlamOption(SlamOptions* options, std::string_view key, std::string_view value,
                   std::string_view where = "--set");

// Applies "KEY=VALUE" (one setting, as given to --set).
void ApplySlamSetting(SlamOptions* options, std::string_view setting);

// Reads a config file: one "key = value" per line; blank lines and '#' comments are skipped.
// Errors name the file and line. The options are checked (SlamOptions::Check) at the end.
void LoadSlamConfig(const std::filesystem::path& path, SlamOptions* options);

// Applies the option sources of a run in their order (later wins): an ORB-SLAM2/3 settings
// file's ORB and depth options for `sensor` (may be null), `features` when non-zero (--features),
// a config file (may be empty), then each "KEY=VALUE,..." of `set` (--set), whose ranges are
// checked once all of them are in. Errors name the source: the settings or config file and line,
// or --set.
void ApplySlamOptionSources(SlamOptions* options, const OrbSettings* settings, Sensor sensor, int features,
                            const std::string& config, const std::vector<std::string>& set);

// Every key with its current value in `options`, as "key = value" lines (the config file format),
// each after its description as '#' comment lines and, for a key listed in `derived`
// (ResolvedOptions), a "# derived: RULE" line; a blank line between keys.
[[nodiscard]] std::vector<std::string> DescribeSlamOptions(const SlamOptions& options,
                                                           std::span<const DerivedOption> derived = {});

}  // namespace flatslam
