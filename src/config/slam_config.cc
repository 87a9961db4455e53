#include "config/slam_config.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <functional>
#include <limits>
#include <sstream>
#include <variant>

#include "core/error.h"
#include "io/orb_settings.h"

namespace flatslam {
namespace {

// A pointer to one option field inside a SlamOptions.
// size_t and uint64_t are one type here; a platform where they differ fails to compile below.
using Field = std::variant<int*, uint64_t*, float*, double*, bool*, BundleAdjustmentOptions::Solver*>;
using BaSolver = BundleAdjustmentOptions::Solver;
static_assert(std::is_same_v<size_t, uint64_t>);

struct Entry {
  const char* key;
  std::function<Field(SlamOptions&)> field;
};

// Every tunable field. Callbacks, the vocabulary pointer and enums are not settable by name.
const std::vector<Entry>& Entries() {
  static const std::vector<Entry> entries = {
      {"orb.features", [](SlamOptions& o) -> Field { return &o.orb.features; }},
      {"orb.scale_factor", [](SlamOptions& o) -> Field { return &o.orb.scale_factor; }},
      {"orb.levels", [](SlamOptions& o) -> Field { return &o.orb.levels; }},
      {"orb.fast_threshold", [](SlamOptions& o) -> Field { return &o.orb.fast_threshold; }},
      {"orb.min_fast_threshold", [](SlamOptions& o) -> Field { return &o.orb.min_fast_threshold; }},
      {"orb.cell_size", [](SlamOptions& o) -> Field { return &o.orb.cell_size; }},
      {"orb.edge_margin", [](SlamOptions& o) -> Field { return &o.orb.edge_margin; }},
      {"orb.budget_by_area", [](SlamOptions& o) -> Field { return &o.orb.budget_by_area; }},
      {"orb.blur_sigma", [](SlamOptions& o) -> Field { return &o.orb.blur_sigma; }},
      {"orb.blur_kernel", [](SlamOptions& o) -> Field { return &o.orb.blur_kernel; }},
      {"stereo.min_depth_m", [](SlamOptions& o) -> Field { return &o.stereo.min_depth_m; }},
      {"stereo.descriptor_threshold", [](SlamOptions& o) -> Field { return &o.stereo.descriptor_threshold; }},
      {"stereo.row_radius", [](SlamOptions& o) -> Field { return &o.stereo.row_radius; }},
      {"stereo.octave_radius", [](SlamOptions& o) -> Field { return &o.stereo.octave_radius; }},
      {"stereo.sad_half_window", [](SlamOptions& o) -> Field { return &o.stereo.sad_half_window; }},
      {"stereo.sad_search_radius", [](SlamOptions& o) -> Field { return &o.stereo.sad_search_radius; }},
      {"stereo.outlier_factor", [](SlamOptions& o) -> Field { return &o.stereo.outlier_factor; }},
      {"matcher.max_distance", [](SlamOptions& o) -> Field { return &o.matcher.max_distance; }},
      {"matcher.max_distance_strict", [](SlamOptions& o) -> Field { return &o.matcher.max_distance_strict; }},
      {"matcher.nn_ratio", [](SlamOptions& o) -> Field { return &o.matcher.nn_ratio; }},
      {"matcher.check_orientation", [](SlamOptions& o) -> Field { return &o.matcher.check_orientation; }},
      {"matcher.fusion_radius", [](SlamOptions& o) -> Field { return &o.matcher.fusion_radius; }},
      {"pose.rounds", [](SlamOptions& o) -> Field { return &o.pose.rounds; }},
      {"pose.iterations_per_round", [](SlamOptions& o) -> Field { return &o.pose.iterations_per_round; }},
      {"pose.chi2_mono", [](SlamOptions& o) -> Field { return &o.pose.chi2_mono; }},
      {"pose.chi2_stereo", [](SlamOptions& o) -> Field { return &o.pose.chi2_stereo; }},
      {"pose.huber_mono", [](SlamOptions& o) -> Field { return &o.pose.huber_mono; }},
      {"pose.huber_stereo", [](SlamOptions& o) -> Field { return &o.pose.huber_stereo; }},
      {"pose.robust_last_round", [](SlamOptions& o) -> Field { return &o.pose.robust_last_round; }},
      {"bundle_adjustment.solver", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.solver; }},
      {"bundle_adjustment.first_pass_iterations",
       [](SlamOptions& o) -> Field { return &o.bundle_adjustment.first_pass_iterations; }},
      {"bundle_adjustment.second_pass_iterations",
       [](SlamOptions& o) -> Field { return &o.bundle_adjustment.second_pass_iterations; }},
      {"bundle_adjustment.chi2_mono", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.chi2_mono; }},
      {"bundle_adjustment.chi2_stereo", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.chi2_stereo; }},
      {"bundle_adjustment.huber_mono", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.huber_mono; }},
      {"bundle_adjustment.huber_stereo", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.huber_stereo; }},
      {"bundle_adjustment.robust_second_pass",
       [](SlamOptions& o) -> Field { return &o.bundle_adjustment.robust_second_pass; }},
      {"bundle_adjustment.dense_schur_max_poses",
       [](SlamOptions& o) -> Field { return &o.bundle_adjustment.dense_schur_max_poses; }},
      {"bundle_adjustment.schur_lm_max_poses",
       [](SlamOptions& o) -> Field { return &o.bundle_adjustment.schur_lm_max_poses; }},
      {"bundle_adjustment.num_threads", [](SlamOptions& o) -> Field { return &o.bundle_adjustment.num_threads; }},
      {"rgbd_virtual_baseline_m", [](SlamOptions& o) -> Field { return &o.rgbd_virtual_baseline_m; }},
      {"close_depth_baselines", [](SlamOptions& o) -> Field { return &o.close_depth_baselines; }},
      {"far_stereo_baselines", [](SlamOptions& o) -> Field { return &o.far_stereo_baselines; }},
      {"min_init_points", [](SlamOptions& o) -> Field { return &o.min_init_points; }},
      {"min_init_matches", [](SlamOptions& o) -> Field { return &o.min_init_matches; }},
      {"mono_search_radius", [](SlamOptions& o) -> Field { return &o.mono_search_radius; }},
      {"seed", [](SlamOptions& o) -> Field { return &o.seed; }},
      {"min_motion_inliers", [](SlamOptions& o) -> Field { return &o.min_motion_inliers; }},
      {"min_local_map_inliers", [](SlamOptions& o) -> Field { return &o.min_local_map_inliers; }},
      {"min_motion_matches", [](SlamOptions& o) -> Field { return &o.min_motion_matches; }},
      {"min_reference_matches", [](SlamOptions& o) -> Field { return &o.min_reference_matches; }},
      {"reference_bow_ratio", [](SlamOptions& o) -> Field { return &o.reference_bow_ratio; }},
      {"keyframe_track_ratio", [](SlamOptions& o) -> Field { return &o.keyframe_track_ratio; }},
      {"keyframe_track_ratio_mono", [](SlamOptions& o) -> Field { return &o.keyframe_track_ratio_mono; }},
      {"keyframe_close_tracked", [](SlamOptions& o) -> Field { return &o.keyframe_close_tracked; }},
      {"keyframe_close_untracked", [](SlamOptions& o) -> Field { return &o.keyframe_close_untracked; }},
      {"keyframe_min_inliers", [](SlamOptions& o) -> Field { return &o.keyframe_min_inliers; }},
      {"motion_search_radius", [](SlamOptions& o) -> Field { return &o.motion_search_radius; }},
      {"max_frames_between_keyframes", [](SlamOptions& o) -> Field { return &o.max_frames_between_keyframes; }},
      {"min_frames_between_keyframes", [](SlamOptions& o) -> Field { return &o.min_frames_between_keyframes; }},
      {"local_keyframes", [](SlamOptions& o) -> Field { return &o.local_keyframes; }},
      {"min_parallax_deg", [](SlamOptions& o) -> Field { return &o.min_parallax_deg; }},
      {"max_local_map_keyframes", [](SlamOptions& o) -> Field { return &o.max_local_map_keyframes; }},
      {"max_local_ba_keyframes", [](SlamOptions& o) -> Field { return &o.max_local_ba_keyframes; }},
      {"redundant_keyframe_ratio", [](SlamOptions& o) -> Field { return &o.redundant_keyframe_ratio; }},
      {"recent_point_min_found_ratio", [](SlamOptions& o) -> Field { return &o.recent_point_min_found_ratio; }},
      {"revisit_radius", [](SlamOptions& o) -> Field { return &o.revisit_radius; }},
      {"revisit_recent_keyframes", [](SlamOptions& o) -> Field { return &o.revisit_recent_keyframes; }},
      {"revisit_max_angle_deg", [](SlamOptions& o) -> Field { return &o.revisit_max_angle_deg; }},
      {"loop_closing", [](SlamOptions& o) -> Field { return &o.loop_closing; }},
      {"global_bundle_adjustment", [](SlamOptions& o) -> Field { return &o.global_bundle_adjustment; }},
      {"relocalization_frames", [](SlamOptions& o) -> Field { return &o.relocalization_frames; }},
      {"relocalization_candidates", [](SlamOptions& o) -> Field { return &o.relocalization_candidates; }},
      {"relocalization_min_bow_matches", [](SlamOptions& o) -> Field { return &o.relocalization_min_bow_matches; }},
      {"relocalization_ransac_iterations", [](SlamOptions& o) -> Field { return &o.relocalization_ransac_iterations; }},
      {"relocalization_ransac_px", [](SlamOptions& o) -> Field { return &o.relocalization_ransac_px; }},
      {"relocalization_min_pnp_inliers", [](SlamOptions& o) -> Field { return &o.relocalization_min_pnp_inliers; }},
      {"essential_graph_min_covisibility", [](SlamOptions& o) -> Field { return &o.essential_graph_min_covisibility; }},
      {"loop_consistency", [](SlamOptions& o) -> Field { return &o.loop_consistency; }},
      {"loop_min_keyframes", [](SlamOptions& o) -> Field { return &o.loop_min_keyframes; }},
      {"min_loop_matches", [](SlamOptions& o) -> Field { return &o.min_loop_matches; }},
  };
  return entries;
}

std::string_view Trim(std::string_view s) {
  const size_t begin = s.find_first_not_of(" \t\r");
  if (begin == std::string_view::npos) return {};
  const size_t end = s.find_last_not_of(" \t\r");
  return s.substr(begin, end - begin + 1);
}

template <class T>
bool ParseNumber(std::string_view text, T* out) {
  if constexpr (std::is_floating_point_v<T>) {
    // from_chars for floating point is in libstdc++ 11+; strtod keeps it portable.
    const std::string copy(text);
    char* end = nullptr;
    const double v = std::strtod(copy.c_str(), &end);
    if (copy.empty() || end != copy.c_str() + copy.size() || !std::isfinite(v)) return false;
    if (std::abs(v) > static_cast<double>(std::numeric_limits<T>::max())) return false;
    *out = static_cast<T>(v);
    return true;
  } else {
    T v{};
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (ec != std::errc() || ptr != text.data() + text.size()) return false;
    *out = v;
    return true;
  }
}

const char* TypeName(const Field& field) {
  return std::visit(
      [](auto* p) -> const char* {
        using T = std::remove_pointer_t<decltype(p)>;
        if constexpr (std::is_same_v<T, bool>)
          return "true or false";
        else if constexpr (std::is_same_v<T, BaSolver>)
          return "schur_lm or ceres";
        else if constexpr (std::is_floating_point_v<T>)
          return "a real number";
        else if constexpr (std::is_signed_v<T>)
          return "an integer";
        else
          return "a non-negative integer";
      },
      field);
}

}  // namespace

void SetSlamOption(SlamOptions* options, std::string_view key, std::string_view value, std::string_view where) {
  key = Trim(key);
  value = Trim(value);
  for (const Entry& entry : Entries()) {
    if (key != entry.key) continue;
    const Field field = entry.field(*options);
    const bool ok = std::visit(
        [&](auto* p) {
          using T = std::remove_pointer_t<decltype(p)>;
          if constexpr (std::is_same_v<T, bool>) {
            if (value == "true" || value == "1") return *p = true, true;
            if (value == "false" || value == "0") return *p = false, true;
            return false;
          } else if constexpr (std::is_same_v<T, BaSolver>) {
            if (value == "schur_lm") return *p = BaSolver::kSchurLm, true;
            if (value == "ceres") return *p = BaSolver::kCeres, true;
            return false;
          } else {
            return ParseNumber(value, p);
          }
        },
        field);
    FLATSLAM_CHECK(ok, where, ": option ", key, " needs ", TypeName(field), ", got '", value, "'");
    return;
  }
  Fail(where, ": unknown option '", key, "' (flatslam run --list-options prints every option)");
}

void ApplySlamSetting(SlamOptions* options, std::string_view setting) {
  const size_t eq = setting.find('=');
  FLATSLAM_CHECK(eq != std::string_view::npos, "--set: expected KEY=VALUE, got '", setting, "'");
  SetSlamOption(options, setting.substr(0, eq), setting.substr(eq + 1), "--set");
  const std::string problem = options->Problem();
  FLATSLAM_CHECK(problem.empty(), "--set ", setting, ": out of range (", problem, " does not hold)");
}

void LoadSlamConfig(const std::filesystem::path& path, SlamOptions* options) {
  std::ifstream in(path);
  FLATSLAM_CHECK(in.is_open(), "cannot read config file ", path);
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    std::string_view text(line);
    if (const size_t hash = text.find('#'); hash != std::string_view::npos) text = text.substr(0, hash);
    text = Trim(text);
    if (text.empty()) continue;
    const std::string where = path.string() + ":" + std::to_string(number);
    const size_t eq = text.find_first_of("=:");
    FLATSLAM_CHECK(eq != std::string_view::npos, where, ": expected 'key = value', got '", text, "'");
    SetSlamOption(options, text.substr(0, eq), text.substr(eq + 1), where);
  }
  FLATSLAM_CHECK(!in.bad(), "cannot read config file ", path);
  const std::string problem = options->Problem();
  FLATSLAM_CHECK(problem.empty(), path.string(), ": a value is out of range (", problem, " does not hold)");
}

std::vector<std::string> DescribeSlamOptions(const SlamOptions& options, std::span<const DerivedOption> derived) {
  SlamOptions copy = options;
  std::vector<std::string> out;
  for (const Entry& entry : Entries()) {
    for (const DerivedOption& d : derived)
      if (d.key == entry.key) out.push_back("# derived: " + d.rule);
    std::ostringstream line;
    line << entry.key << " = ";
    std::visit(
        [&](auto* p) {
          using T = std::remove_pointer_t<decltype(p)>;
          if constexpr (std::is_same_v<T, bool>)
            line << (*p ? "true" : "false");
          else if constexpr (std::is_same_v<T, BaSolver>)
            line << (*p == BaSolver::kCeres ? "ceres" : "schur_lm");
          else if constexpr (std::is_floating_point_v<T>) {
            char buffer[64];  // shortest text that reads back as the same value
            const auto result = std::to_chars(buffer, buffer + sizeof(buffer), *p);
            line << std::string_view(buffer, result.ptr - buffer);
          } else
            line << *p;
        },
        entry.field(copy));
    out.push_back(line.str());
  }
  return out;
}

void ApplySlamOptionSources(SlamOptions* options, const OrbSettings* settings, Sensor sensor, int features,
                            const std::string& config, const std::vector<std::string>& set) {
  if (settings)
    for (const auto& [key, value] : SettingsSlamOptions(*settings, sensor))
      SetSlamOption(options, key, value, settings->file.string());
  if (features != 0) options->orb.features = features;
  if (!config.empty()) LoadSlamConfig(config, options);
  for (const std::string& settings_list : set) {
    for (size_t pos = 0; pos <= settings_list.size();) {
      const size_t comma = std::min(settings_list.find(',', pos), settings_list.size());
      ApplySlamSetting(options, std::string_view(settings_list).substr(pos, comma - pos));
      pos = comma + 1;
    }
  }
}

}  // namespace flatslam
