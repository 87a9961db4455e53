#include "io/manifest.h"

#include <algorithm>
#include <fstream>
#include <map>
#include <set>

#include "core/error.h"
#include "core/text.h"
#include "io/dataset.h"

namespace flatslam {
namespace {

// The line without a '#' comment (a '#' inside quotes is kept).
std::string WithoutComment(const std::string& line) {
  char quote = 0;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quote != 0) {
      if (c == quote) quote = 0;
    } else if (c == '"' || c == '\'') {
      quote = c;
    } else if (c == '#' && (i == 0 || line[i - 1] == ' ' || line[i - 1] == '\t')) {
      return line.substr(0, i);
    }
  }
  return line;
}

std::string Unquoted(const std::string& text) {
  if (text.size() >= 2 && (text.front() == '"' || text.front() == '\'') && text.back() == text.front())
    return text.substr(1, text.size() - 2);
  return text;
}

// Relative paths are taken from the manifest's folder; synth:SPEC is not a path.
std::string Resolve(const std::filesystem::path& base, const std::string& path) {
  if (path.empty() || path.rfind("synth:", 0) == 0 || std::filesystem::path(path).is_absolute()) return path;
  return (base / path).lexically_normal().string();
}

uint64_t ReadCount(const std::string& text, const std::string& where, const std::string& what) {
  size_t used = 0;
  uint64_t value = 0;
  try {
    if (!text.empty() && text[0] != '-') value = std::stoull(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  FLATSLAM_CHECK(used > 0 && used == text.size(), where, ": ", what, " '", text, "' is not a whole number");
  return value;
}

// Sets one field of `spec` by its manifest name (a line flag without "--" or a YAML key).
void SetField(SequenceSpec* spec, const std::string& key, const std::string& value, const std::filesystem::path& base,
              const std::string& where) {
  if (key == "path" || key == "dataset") {
    spec->dataset = Resolve(base, value);
  } else if (key == "name") {
    spec->name = value;
  } else if (key == "sensor") {
    try {
      spec->sensor = ParseSensor(value);
    } catch (const Error& e) {
      Fail(where, ": ", e.what());
    }
  } else if (key == "settings") {
    spec->settings = Resolve(base, value);
  } else if (key == "config") {
    spec->config = Resolve(base, value);
  } else if (key == "set" || key == "options") {
    for (size_t pos = 0; pos <= value.size();) {
      const size_t comma = std::min(value.find(',', pos), value.size());
      const std::string item = Trimmed(value.substr(pos, comma - pos));
      FLATSLAM_CHECK(item.find('=') != std::string::npos && item.find('=') > 0, where, ": option '", item,
                     "' is not KEY=VALUE");
      spec->set.push_back(item);
      pos = comma + 1;
    }
  } else if (key == "seed") {
    spec->seed = ReadCount(value, where, "seed");
  } else if (key == "max-frames" || key == "max_frames") {
    spec->max_frames = ReadCount(value, where, "max_frames");
  } else if (key == "camera-from" || key == "camera_from") {
    spec->camera_from = Resolve(base, value);
  } else if (key == "keep-camera" || key == "keep_camera") {
    if (value == "true" || value == "yes" || value == "1")
      spec->keep_camera = true;
    else if (value == "false" || value == "no" || value == "0")
      spec->keep_camera = false;
    else
      Fail(where, ": keep_camera '", value, "' is not true or false");
  } else {
    Fail(where, ": unknown key '", key,
         "' (path, name, sensor, settings, config, options/set, seed, max_frames, keep_camera, camera_from)");
  }
}

void RequireDataset(const SequenceSpec& spec) {
  FLATSLAM_CHECK(!spec.dataset.empty(), spec.where, ": the sequence names no dataset (path:)");
}

// The words of a line, split at blanks outside quotes ('...' or "..."), quotes removed.
std::vector<std::string> Words(const std::string& line, const std::string& where) {
  std::vector<std::string> words;
  std::string word;
  bool in_word = false;
  char quote = 0;
  for (char c : line) {
    if (quote != 0) {
      if (c == quote)
        quote = 0;
      else
        word += c;
    } else if (c == '"' || c == '\'') {
      quote = c;
      in_word = true;
    } else if (c == ' ' || c == '\t' || c == '\r') {
      if (in_word) words.push_back(word);
      word.clear();
      in_word = false;
    } else {
      word += c;
      in_word = true;
    }
  }
  FLATSLAM_CHECK(quote == 0, where, ": a quote is not closed");
  if (in_word) words.push_back(word);
  return words;
}

// "DATASET --flag value ..." lines.
std::vector<SequenceSpec> ReadLineManifest(const std::vector<std::string>& lines, const std::string& file,
                                           const std::filesystem::path& base) {
  std::vector<SequenceSpec> out;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string line = Trimmed(WithoutComment(lines[i]));
    if (line.empty()) continue;
    const std::string where = file + ":" + std::to_string(i + 1);
    const std::vector<std::string> tokens = Words(line, where);
    SequenceSpec spec;
    spec.where = where;
    for (size_t t = 0; t < tokens.size(); ++t) {
      const std::string& token = tokens[t];
      if (token.rfind("--", 0) == 0) {
        std::string key = token.substr(2), value;
        const size_t eq = key.find('=');
        if (eq != std::string::npos) {
          value = key.substr(eq + 1);
          key = key.substr(0, eq);
        } else if (key == "keep-camera") {
          value = "true";  // a switch, as on flatslam run's command line
        } else {
          FLATSLAM_CHECK(t + 1 < tokens.size(), where, ": ", token, " needs a value");
          value = tokens[++t];
        }
        FLATSLAM_CHECK(key != "path" && key != "dataset", where, ": the dataset is the line's first word, not ", token);
        SetField(&spec, key, value, base, where);
      } else {
        FLATSLAM_CHECK(spec.dataset.empty(), where, ": a second dataset '", token, "' (one sequence per line)");
        spec.dataset = Resolve(base, token);
      }
    }
    RequireDataset(spec);
    out.push_back(std::move(spec));
  }
  return out;
}

size_t Indent(const std::string& line) {
  const size_t n = line.find_first_not_of(' ');
  return n == std::string::npos ? line.size() : n;
}

// The YAML subset above: a list of flat mappings, "options" being a nested mapping or a string.
std::vector<SequenceSpec> ReadYamlManifest(const std::vector<std::string>& lines, const std::string& file,
                                           const std::filesystem::path& base) {
  std::vector<SequenceSpec> out;
  std::optional<size_t> item_indent;     // column of the item's keys
  std::optional<size_t> options_indent;  // inside "options:", the column of its keys
  for (size_t i = 0; i < lines.size(); ++i) {
    std::string raw = WithoutComment(lines[i]);
    const std::string where = file + ":" + std::to_string(i + 1);
    FLATSLAM_CHECK(raw.find('\t') == std::string::npos || Trimmed(raw).empty(), where,
                   ": a tab in the indentation (YAML indents with spaces)");
    if (Trimmed(raw).empty() || Trimmed(raw) == "---") continue;
    size_t indent = Indent(raw);
    std::string content = Trimmed(raw);
    if (content == "sequences:" && indent == 0) continue;
    bool new_item = false;
    if (content.rfind("- ", 0) == 0 || content == "-") {
      new_item = true;
      content = Trimmed(content.substr(1));
      indent += 2;
      while (indent < raw.size() && raw[indent] == ' ') ++indent;
      if (out.size() > 0) RequireDataset(out.back());
      out.emplace_back();
      out.back().where = where;
      item_indent = indent;
      options_indent.reset();
      if (content.empty()) continue;
    }
    FLATSLAM_CHECK(!out.empty(), where, ": expected a list item ('- path: DATASET')");
    const size_t colon = content.find(':');
    FLATSLAM_CHECK(colon != std::string::npos && colon > 0, where, ": expected 'key: value', got '", content, "'");
    const std::string key = Trimmed(content.substr(0, colon));
    const std::string value = Unquoted(Trimmed(content.substr(colon + 1)));
    if (options_indent && !new_item && indent > *item_indent) {
      // A key of the options mapping.
      FLATSLAM_CHECK(value.find(',') == std::string::npos, where, ": option ", key, " has a ',' in its value");
      SetField(&out.back(), "options", key + "=" + value, base, where);
      continue;
    }
    FLATSLAM_CHECK(new_item || indent == *item_indent, where, ": indentation does not match the item's keys");
    options_indent.reset();
    if (key == "options" && value.empty()) {
      options_indent = indent + 1;
      continue;
    }
    FLATSLAM_CHECK(!value.empty(), where, ": key '", key, "' has no value");
    SetField(&out.back(), key, value, base, where);
  }
  if (!out.empty()) RequireDataset(out.back());
  return out;
}

// A name safe as a folder name: letters, digits and ._=+- kept, anything else '_'.
std::string SafeName(const std::string& text) {
  std::string out;
  for (char c : text) {
    const bool keep =
        std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-' || c == '=' || c == '+';
    out += keep ? c : '_';
  }
  if (out.empty() || out == "." || out == "..") out = "sequence";
  return out;
}

// The default name of a dataset: synth:room:duration=5 -> synth_room_duration=5;
// .../kitti/sequences/06 -> kitti_06 (a bare number says little); other folders by base name.
std::string DefaultName(const std::string& dataset) {
  if (dataset.rfind("synth:", 0) == 0) return SafeName(dataset);
  const std::filesystem::path path = std::filesystem::path(dataset).lexically_normal();
  std::string base = path.filename().string();
  if (base.empty()) base = path.parent_path().filename().string();
  const bool numeric = !base.empty() && std::all_of(base.begin(), base.end(), ::isdigit);
  if (numeric) {
    const std::filesystem::path parent = path.has_filename() ? path.parent_path() : path.parent_path().parent_path();
    const std::string above =
        parent.filename() == "sequences" ? parent.parent_path().filename().string() : parent.filename().string();
    if (!above.empty()) base = above + "_" + base;
  }
  return SafeName(base);
}

bool IsDataset(const std::filesystem::path& folder) {
  try {
    return DetectDatasetLayout(folder.string(), false) != DatasetLayout::kImageFolder;
  } catch (const Error&) {
    return false;
  }
}

}  // namespace

std::vector<SequenceSpec> ReadManifest(const std::filesystem::path& path) {
  std::ifstream in(path);
  FLATSLAM_CHECK(in.good(), path.string(), ": cannot open the manifest");
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  const std::filesystem::path base = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  const std::string ext = path.extension().string();
  bool yaml = ext == ".yaml" || ext == ".yml";
  for (const std::string& line : lines) {
    const std::string content = Trimmed(WithoutComment(line));
    if (content.empty()) continue;
    yaml = yaml || content == "sequences:" || content == "---" || content.rfind("- ", 0) == 0;
    break;
  }
  std::vector<SequenceSpec> specs =
      yaml ? ReadYamlManifest(lines, path.string(), base) : ReadLineManifest(lines, path.string(), base);
  FLATSLAM_CHECK(!specs.empty(), path.string(), ": the manifest lists no sequence");
  return specs;
}

std::vector<SequenceSpec> ExpandBatchInputs(const std::vector<std::string>& inputs, const SequenceSpec& defaults) {
  std::vector<SequenceSpec> specs;
  auto add = [&](SequenceSpec spec) {
    if (!spec.sensor) spec.sensor = defaults.sensor;
    if (!spec.seed) spec.seed = defaults.seed;
    if (spec.settings.empty()) spec.settings = defaults.settings;
    if (spec.config.empty()) spec.config = defaults.config;
    // The batch's options first, the sequence's own after them (later settings win).
    spec.set.insert(spec.set.begin(), defaults.set.begin(), defaults.set.end());
    if (spec.max_frames == 0) spec.max_frames = defaults.max_frames;
    if (!spec.keep_camera) spec.keep_camera = defaults.keep_camera;
    if (spec.camera_from.empty()) spec.camera_from = defaults.camera_from;
    if (spec.name.empty()) spec.name = DefaultName(spec.dataset);
    specs.push_back(std::move(spec));
  };
  for (const std::string& input : inputs) {
    SequenceSpec spec;
    spec.where = input;
    if (input.rfind("synth:", 0) == 0) {
      spec.dataset = input;
      add(spec);
      continue;
    }
    const std::filesystem::path path(input);
    FLATSLAM_CHECK(std::filesystem::exists(path), input, ": no such file or folder");
    if (std::filesystem::is_directory(path)) {
      if (IsDataset(path)) {
        spec.dataset = input;
        add(spec);
        continue;
      }
      // A folder of datasets; a KITTI root holds them under sequences/.
      const std::filesystem::path folder =
          std::filesystem::is_directory(path / "sequences") ? path / "sequences" : path;
      std::vector<std::filesystem::path> children;
      for (const auto& entry : std::filesystem::directory_iterator(folder))
        if (entry.is_directory() && IsDataset(entry.path())) children.push_back(entry.path());
      FLATSLAM_CHECK(!children.empty(), input,
                     ": not a dataset (KITTI sequence, EuRoC, TUM RGB-D) nor a folder of datasets");
      std::sort(children.begin(), children.end());
      for (const auto& child : children) {
        SequenceSpec one = spec;
        one.dataset = child.string();
        one.where = child.string();
        add(one);
      }
      continue;
    }
    for (SequenceSpec& listed : ReadManifest(path)) add(listed);
  }
  FLATSLAM_CHECK(!specs.empty(), "no sequence to run");
  // Unique folder names, in input order.
  std::set<std::string> used;
  for (SequenceSpec& spec : specs) {
    spec.name = SafeName(spec.name);
    std::string name = spec.name;
    for (int k = 2; used.count(name); ++k) name = spec.name + "-" + std::to_string(k);
    spec.name = name;
    used.insert(name);
  }
  return specs;
}

std::vector<size_t> ShardPositions(size_t sequences, size_t index, size_t count) {
  FLATSLAM_CHECK(count > 0 && index < count, "shard ", index, "/", count, ": expected I/N with 0 <= I < N");
  std::vector<size_t> out;
  for (size_t p = index; p < sequences; p += count) out.push_back(p);
  return out;
}

}  // namespace flatslam
