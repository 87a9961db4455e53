#include "report/results.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <variant>

#include "core/atomic_write.h"
#include "core/error.h"
#include "core/text.h"

namespace flatslam {
namespace {

// Each column once: its name, how its cell is written and read back, and how the summary row
// combines it (sum, median, or nothing).
enum class Combine { kNone, kSum, kMedian };
using Text = std::string SequenceResult::*;
using Count = size_t SequenceResult::*;
using Real = double SequenceResult::*;
using Optional = std::optional<double> SequenceResult::*;
struct Column {
  const char* name;
  std::variant<Text, Count, Real, Optional> field;
  int decimals;  // for numbers
  Combine combine;
};

const std::vector<Column>& Columns() {
  static const std::vector<Column> columns = {
      {"sequence", &SequenceResult::name, 0, Combine::kNone},
      {"input", &SequenceResult::input, 0, Combine::kNone},
      {"dataset", &SequenceResult::dataset, 0, Combine::kNone},
      {"sensor", &SequenceResult::sensor, 0, Combine::kNone},
      {"status", &SequenceResult::status, 0, Combine::kNone},
      {"frames", &SequenceResult::frames, 0, Combine::kSum},
      {"tracked", &SequenceResult::tracked, 0, Combine::kSum},
      {"lost", &SequenceResult::lost, 0, Combine::kSum},
      {"segments", &SequenceResult::segments, 0, Combine::kSum},
      {"skipped", &SequenceResult::skipped, 0, Combine::kSum},
      {"keyframes", &SequenceResult::keyframes, 0, Combine::kSum},
      {"map_points", &SequenceResult::map_points, 0, Combine::kSum},
      {"loops", &SequenceResult::loops, 0, Combine::kSum},
      {"ate_se3_m", &SequenceResult::ate_se3_m, 4, Combine::kMedian},
      {"ate_sim3_m", &SequenceResult::ate_sim3_m, 4, Combine::kMedian},
      {"scale", &SequenceResult::scale, 4, Combine::kMedian},
      {"rpe_m", &SequenceResult::rpe_m, 4, Combine::kMedian},
      {"rpe_deg", &SequenceResult::rpe_deg, 3, Combine::kMedian},
      {"path_m", &SequenceResult::path_m, 1, Combine::kMedian},
      {"kitti_t_rel_pct", &SequenceResult::kitti_t_rel_pct, 3, Combine::kMedian},
      {"kitti_r_rel_deg_per_100m", &SequenceResult::kitti_r_rel_deg_per_100m, 3, Combine::kMedian},
      {"rig_offset_px", &SequenceResult::rig_offset_px, 3, Combine::kMedian},
      {"camera_refit_k1", &SequenceResult::camera_refit_k1, 5, Combine::kMedian},
      {"camera_refit_focal_scale", &SequenceResult::camera_refit_focal_scale, 5, Combine::kMedian},
      {"wall_s", &SequenceResult::wall_s, 2, Combine::kSum},
      {"fps", &SequenceResult::fps, 1, Combine::kMedian},
      {"cpu_ms_per_frame", &SequenceResult::cpu_ms_per_frame, 2, Combine::kMedian},
      {"peak_rss_mib", &SequenceResult::peak_rss_mib, 0, Combine::kMedian},
      {"error", &SequenceResult::error, 0, Combine::kNone},
  };
  return columns;
}

std::string Cell(const Column& column, const SequenceResult& row) {
  return std::visit(
      [&](auto field) -> std::string {
        using F = decltype(field);
        if constexpr (std::is_same_v<F, Text>) {
          return row.*field;
        } else if constexpr (std::is_same_v<F, Count>) {
          return std::to_string(row.*field);
        } else if constexpr (std::is_same_v<F, Real>) {
          return FixedDecimals(row.*field, column.decimals);
        } else {
          return (row.*field) ? FixedDecimals(*(row.*field), column.decimals) : std::string();
        }
      },
      column.field);
}

// Reads `text` into the column's field of `row`; false when it is not a number of that kind.
bool SetCell(const Column& column, const std::string& text, SequenceResult* row) {
  return std::visit(
      [&](auto field) -> bool {
        using F = decltype(field);
        if constexpr (std::is_same_v<F, Text>) {
          row->*field = text;
          return true;
        } else {
          if constexpr (std::is_same_v<F, Optional>) {
            if (text.empty()) {
              row->*field = std::nullopt;
              return true;
            }
          }
          size_t used = 0;
          try {
            if constexpr (std::is_same_v<F, Count>) {
              if (text.empty() || text[0] == '-') return false;
              row->*field = std::stoull(text, &used);
            } else {
              row->*field = std::stod(text, &used);
            }
          } catch (const std::exception&) {
            return false;
          }
          return used == text.size();
        }
      },
      column.field);
}

double Median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n % 2 == 1 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
}

std::string CsvQuoted(const std::string& text) {
  if (text.find_first_of(",\"\n\r") == std::string::npos) return text;
  std::string out = "\"";
  for (char c : text) {
    if (c == '"') out += '"';
    out += c;
  }
  return out + "\"";
}

std::string JsonObject(const SequenceResult& row) {
  std::string out = "{";
  bool first = true;
  for (const Column& column : Columns()) {
    const std::string cell = Cell(column, row);
    out += first ? "" : ", ";
    first = false;
    out += JsonString(column.name) + ": ";
    if (std::holds_alternative<Text>(column.field))
      out += JsonString(cell);
    else
      out += cell.empty() ? "null" : cell;
  }
  return out + "}";
}

// Splits one CSV record starting at `pos` of `text` (quoted cells may hold line breaks); moves
// `pos` past it and counts the lines it spans.
std::vector<std::string> CsvRecord(const std::string& text, size_t* pos, size_t* line, const std::string& where) {
  std::vector<std::string> cells(1);
  bool quoted = false;
  const size_t start_line = *line;
  for (; *pos < text.size(); ++*pos) {
    const char c = text[*pos];
    if (quoted) {
      if (c == '"' && *pos + 1 < text.size() && text[*pos + 1] == '"') {
        cells.back() += '"';
        ++*pos;
      } else if (c == '"') {
        quoted = false;
      } else {
        if (c == '\n') ++*line;
        cells.back() += c;
      }
    } else if (c == '"' && cells.back().empty()) {
      quoted = true;
    } else if (c == ',') {
      cells.emplace_back();
    } else if (c == '\n') {
      ++*pos;
      ++*line;
      return cells;
    } else if (c != '\r') {
      cells.back() += c;
    }
  }
  FLATSLAM_CHECK(!quoted, where, ":", start_line, ": a quoted cell is not closed");
  ++*line;
  return cells;
}

}  // namespace

std::string JsonString(std::string_view text) {
  std::string out = "\"";
  for (size_t i = 0; i < text.size(); ++i) {
    const unsigned char c = static_cast<unsigned char>(text[i]);
    char escaped[8];
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20 || c == '<' || c == '>' || c == '&') {
      std::snprintf(escaped, sizeof(escaped), "\\u%04x", c);
      out += escaped;
    } else if (c == 0xE2 && i + 2 < text.size() && static_cast<unsigned char>(text[i + 1]) == 0x80 &&
               (static_cast<unsigned char>(text[i + 2]) == 0xA8 || static_cast<unsigned char>(text[i + 2]) == 0xA9)) {
      out += static_cast<unsigned char>(text[i + 2]) == 0xA8 ? "\\u2028" : "\\u2029";
      i += 2;
    } else {
      out += static_cast<char>(c);
    }
  }
  return out + "\"";
}

const std::vector<std::string>& ResultColumns() {
  static const std::vector<std::string> names = [] {
    std::vector<std::string> out;
    for (const Column& c : Columns()) out.push_back(c.name);
    return out;
  }();
  return names;
}

std::vector<std::string> ResultCells(const SequenceResult& result) {
  std::vector<std::string> out;
  for (const Column& c : Columns()) out.push_back(Cell(c, result));
  return out;
}

SequenceResult SummarizeResults(const std::vector<SequenceResult>& rows) {
  SequenceResult summary;
  summary.name = "summary";
  size_t ok = 0;
  for (const SequenceResult& r : rows) ok += r.status == "ok";
  summary.status = std::to_string(ok) + " of " + std::to_string(rows.size()) + " ok";
  for (const Column& column : Columns()) {
    if (column.combine == Combine::kNone) continue;
    std::vector<double> values;
    for (const SequenceResult& r : rows) {
      std::visit(
          [&](auto field) {
            using F = decltype(field);
            if constexpr (std::is_same_v<F, Count> || std::is_same_v<F, Real>) {
              values.push_back(static_cast<double>(r.*field));
            } else if constexpr (std::is_same_v<F, Optional>) {
              if (r.*field) values.push_back(*(r.*field));
            }
          },
          column.field);
    }
    double combined = 0;
    if (column.combine == Combine::kSum)
      for (double v : values) combined += v;
    else if (!values.empty())
      combined = Median(values);
    std::visit(
        [&](auto field) {
          using F = decltype(field);
          if constexpr (std::is_same_v<F, Count>) {
            summary.*field = static_cast<size_t>(std::llround(combined));
          } else if constexpr (std::is_same_v<F, Real>) {
            summary.*field = combined;
          } else if constexpr (std::is_same_v<F, Optional>) {
            if (!values.empty()) summary.*field = combined;
          }
        },
        column.field);
  }
  return summary;
}

void WriteResultsCsv(const std::filesystem::path& path, const std::vector<SequenceResult>& rows) {
  auto line = [](const std::vector<std::string>& cells) {
    std::string out;
    for (size_t i = 0; i < cells.size(); ++i) {
      if (i > 0) out += ',';
      out += CsvQuoted(cells[i]);
    }
    return out + "\n";
  };
  std::string text = line(ResultColumns());
  for (const SequenceResult& row : rows) text += line(ResultCells(row));
  WriteFileAtomically(path, [&](std::FILE* f) { std::fputs(text.c_str(), f); });
}

std::vector<SequenceResult> ReadResultsCsv(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  FLATSLAM_CHECK(in.good(), path.string(), ": cannot open the results table");
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  size_t pos = 0, line = 1;
  const std::vector<std::string> header = CsvRecord(text, &pos, &line, path.string());
  // Columns are matched by name, so a table with fewer or reordered columns still reads.
  std::vector<const Column*> columns;
  for (const std::string& name : header) {
    const auto it = std::find_if(Columns().begin(), Columns().end(), [&](const Column& c) { return name == c.name; });
    FLATSLAM_CHECK(it != Columns().end(), path.string(), ":1: unknown column '", name, "'");
    columns.push_back(&*it);
  }
  FLATSLAM_CHECK(std::find(header.begin(), header.end(), "sequence") != header.end(), path.string(),
                 ":1: no 'sequence' column (not a results table)");
  std::vector<SequenceResult> rows;
  while (pos < text.size()) {
    const size_t row_line = line;
    const std::vector<std::string> cells = CsvRecord(text, &pos, &line, path.string());
    if (cells.size() == 1 && cells[0].empty()) continue;
    FLATSLAM_CHECK(cells.size() == columns.size(), path.string(), ":", row_line, ": ", cells.size(),
                   " cells, expected ", columns.size());
    SequenceResult row;
    for (size_t i = 0; i < cells.size(); ++i)
      FLATSLAM_CHECK(SetCell(*columns[i], cells[i], &row), path.string(), ":", row_line, ": column '", columns[i]->name,
                     "': cannot read '", cells[i], "'");
    rows.push_back(std::move(row));
  }
  return rows;
}

void WriteResultsJson(const std::filesystem::path& path, const std::vector<SequenceResult>& rows) {
  std::string text = "{\n  \"sequences\": [";
  for (size_t i = 0; i < rows.size(); ++i) text += (i ? ",\n    " : "\n    ") + JsonObject(rows[i]);
  text += rows.empty() ? "],\n" : "\n  ],\n";
  text += "  \"summary\": " + JsonObject(SummarizeResults(rows)) + "\n}\n";
  WriteFileAtomically(path, [&](std::FILE* f) { std::fputs(text.c_str(), f); });
}

std::string ResultsMarkdown(const std::vector<SequenceResult>& rows) {
  // The columns a reader scans first; the files hold all of them.
  static const std::vector<std::string> kShown = {
      "sequence", "sensor",          "status", "frames",           "lost",        "segments",
      "skipped",  "keyframes",       "loops",  "ate_se3_m",        "ate_sim3_m",  "scale",
      "rpe_m",    "kitti_t_rel_pct", "fps",    "cpu_ms_per_frame", "peak_rss_mib"};
  std::vector<size_t> shown;
  for (const std::string& name : kShown)
    shown.push_back(std::find(ResultColumns().begin(), ResultColumns().end(), name) - ResultColumns().begin());
  auto line = [&](const std::vector<std::string>& cells) {
    std::string out = "|";
    for (size_t i : shown) {
      std::string cell = cells[i];
      std::replace(cell.begin(), cell.end(), '|', '/');
      out += " " + cell + " |";
    }
    return out + "\n";
  };
  std::string out = line(ResultColumns()) + "|";
  for (size_t i = 0; i < shown.size(); ++i) out += "---|";
  out += "\n";
  for (const SequenceResult& row : rows) out += line(ResultCells(row));
  out += line(ResultCells(SummarizeResults(rows)));
  return out;
}

}  // namespace flatslam
