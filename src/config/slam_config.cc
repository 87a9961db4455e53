#include "config/slam_config.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <limits>

#include "core/error.h"
#include "core/text.h"
#include "io/orb_settings.h"

namespace flatslam {
namespace {

using BaSolver = BundleAdjustmentOptions::Solver;

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

template <class T>
const char* TypeName() {
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
}

// Text that reads back as the same value.
template <class T>
std::string ValueText(const T& value) {
  if constexpr (std::is_same_v<T, bool>) {
    return value ? "true" : "false";
  } else if constexpr (std::is_same_v<T, BaSolver>) {
    return value == BaSolver::kCeres ? "ceres" : "schur_lm";
  } else {
    char buffer[64];  // shortest text that reads back as the same value
    const auto result = std::to_chars(buffer, buffer + sizeof(buffer), value);
    return std::string(buffer, result.ptr);
  }
}

// A description as comment lines of at most about 100 characters.
void AppendComment(std::string_view text, std::vector<std::string>* out) {
  constexpr size_t kWidth = 98;
  std::string line = "#";
  size_t pos = 0;
  while (pos < text.size()) {
    size_t end = text.find(' ', pos);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view word = text.substr(pos, end - pos);
    if (line.size() > 1 && line.size() + 1 + word.size() > kWidth) {
      out->push_back(line);
      line = "#";
    }
    line += ' ';
    line += word;
    pos = end + 1;
  }
  if (line.size() > 1) out->push_back(line);
}

}  // namespace

void SetSlamOption(SlamOptions* options, std::string_view key, std::string_view value, std::string_view where) {
  key = TrimBlanks(key);
  value = TrimBlanks(value);
  bool found = false;
  options->VisitAll([&](const std::string& name, auto& field, const char*) {
    using T = std::remove_reference_t<decltype(field)>;
    if (found || name != key) return;
    found = true;
    bool ok = false;
    if constexpr (std::is_same_v<T, bool>) {
      ok = value == "true" || value == "1" || value == "false" || value == "0";
      if (ok) field = value == "true" || value == "1";
    } else if constexpr (std::is_same_v<T, BaSolver>) {
      ok = value == "schur_lm" || value == "ceres";
      if (ok) field = value == "ceres" ? BaSolver::kCeres : BaSolver::kSchurLm;
    } else {
      ok = ParseNumber(value, &field);
    }
    FLATSLAM_CHECK(ok, where, ": option ", key, " needs ", TypeName<T>(), ", got '", value, "'");
  });
  if (!found) Fail(where, ": unknown option '", key, "' (flatslam run --list-options prints every option)");
}

namespace {

// Sets "KEY=VALUE" without checking the options' ranges (the caller checks them once all
// settings it was given are in, so that related values may change together).
void SetFromSetting(SlamOptions* options, std::string_view setting) {
  const size_t eq = setting.find('=');
  FLATSLAM_CHECK(eq != std::string_view::npos, "--set: expected KEY=VALUE, got '", setting, "'");
  SetSlamOption(options, setting.substr(0, eq), setting.substr(eq + 1), "--set");
}

void CheckSettingsRange(const SlamOptions& options, std::string_view settings) {
  const std::string problem = options.Problem();
  FLATSLAM_CHECK(problem.empty(), "--set ", settings, ": out of range (", problem, " does not hold)");
}

}  // namespace

void ApplySlamSetting(SlamOptions* options, std::string_view setting) {
  SetFromSetting(options, setting);
  CheckSettingsRange(*options, setting);
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
    text = TrimBlanks(text);
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
  copy.VisitAll([&](const std::string& key, const auto& field, const char* description) {
    if (!out.empty()) out.emplace_back();
    AppendComment(description, &out);
    for (const DerivedOption& d : derived)
      if (d.key == key) out.push_back("# derived: " + d.rule);
    out.push_back(key + " = " + ValueText(field));
  });
  return out;
}

void ApplySlamOptionSources(SlamOptions* options, const OrbSettings* settings, Sensor sensor, int features,
                            const std::string& config, const std::vector<std::string>& set) {
  if (settings)
    for (const auto& [key, value] : SettingsSlamOptions(*settings, sensor))
      SetSlamOption(options, key, value, settings->file.string());
  if (features != 0) options->orb.features = features;
  if (!config.empty()) LoadSlamConfig(config, options);
  // Every --set first, then one range check: lowering both FAST thresholds, say, works in either
  // order, where a check after each value would refuse the first that passes the other.
  std::string applied;
  for (const std::string& settings_list : set) {
    for (size_t pos = 0; pos <= settings_list.size();) {
      const size_t comma = std::min(settings_list.find(',', pos), settings_list.size());
      const std::string_view setting = std::string_view(settings_list).substr(pos, comma - pos);
      SetFromSetting(options, setting);
      if (!applied.empty()) applied += ',';
      applied += setting;
      pos = comma + 1;
    }
  }
  if (!applied.empty()) CheckSettingsRange(*options, applied);
}

}  // namespace flatslam
