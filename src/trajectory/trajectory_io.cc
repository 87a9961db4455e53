#include "trajectory/trajectory_io.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>

#include "core/atomic_write.h"
#include "core/error.h"
#include "core/text.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

// One non-blank, non-comment line of a text file, with its 1-based line number.
struct DataLine {
  size_t number = 0;
  std::string text;
};

bool IsBlankOrComment(const std::string& line) {
  for (char c : line) {
    if (c == '#') return true;
    if (!std::isspace(static_cast<unsigned char>(c))) return false;
  }
  return true;
}

std::ifstream OpenForReading(const fs::path& path) {
  FLATSLAM_CHECK(!fs::is_directory(path), path.string(), ": is a directory, not a trajectory file");
  std::ifstream in(path);
  FLATSLAM_CHECK(in.is_open(), path.string(), ": cannot open file");
  return in;
}

// Reads the data lines of a file (strips '\r'); max_lines = 0 reads them all.
std::vector<DataLine> ReadDataLines(const fs::path& path, size_t max_lines = 0) {
  std::ifstream in = OpenForReading(path);
  std::vector<DataLine> lines;
  std::string line;
  size_t number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (IsBlankOrComment(line)) continue;
    lines.push_back({number, line});
    if (max_lines > 0 && lines.size() >= max_lines) break;
  }
  FLATSLAM_CHECK(!in.bad(), path.string(), ": read error after line ", number);
  FLATSLAM_CHECK(!lines.empty(), path.string(), ": no poses (the file is empty or holds only comments)");
  return lines;
}

// Splits on whitespace and commas; empty fields are dropped.
std::vector<std::string_view> SplitLoose(std::string_view text) {
  std::vector<std::string_view> out;
  size_t i = 0;
  auto is_sep = [](char c) { return c == ',' || std::isspace(static_cast<unsigned char>(c)); };
  while (i < text.size()) {
    while (i < text.size() && is_sep(text[i])) ++i;
    size_t j = i;
    while (j < text.size() && !is_sep(text[j])) ++j;
    if (j > i) out.push_back(text.substr(i, j - i));
    i = j;
  }
  return out;
}

// Splits on commas only (csv), trimming each field; empty fields are kept.
std::vector<std::string_view> SplitCsv(std::string_view text) {
  std::vector<std::string_view> out;
  size_t start = 0;
  while (true) {
    size_t comma = text.find(',', start);
    out.push_back(
        TrimBlanks(text.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start)));
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  return out;
}

std::optional<double> ParseFiniteDouble(std::string_view s) {
  if (!s.empty() && s.front() == '+') s.remove_prefix(1);
  double value = 0;
  auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  if (ec != std::errc() || ptr != s.data() + s.size() || !std::isfinite(value)) return std::nullopt;
  return value;
}

bool IsUnsignedInteger(std::string_view s) {
  return !s.empty() && std::all_of(s.begin(), s.end(), [](char c) { return c >= '0' && c <= '9'; });
}

// Names a place in a file for error messages: "path:line".
std::string Where(const fs::path& path, size_t line) {
  return path.string() + ":" + std::to_string(line);
}

double NumberAt(const fs::path& path, const DataLine& line, std::string_view token, const char* what) {
  auto value = ParseFiniteDouble(token);
  if (!value) Fail(Where(path, line.number), ": ", what, " '", token, "' is not a finite number");
  return *value;
}

Eigen::Quaterniond NormalizedQuaternion(const fs::path& path, const DataLine& line, double w, double x, double y,
                                        double z) {
  Eigen::Quaterniond q(w, x, y, z);
  const double norm = q.norm();
  if (!(norm > 1e-9)) Fail(Where(path, line.number), ": zero quaternion (norm ", norm, ")");
  q.coeffs() /= norm;
  return q;
}

void CheckTimesAreFinite(const fs::path& path, const DataLine& line, std::string_view token,
                         const std::optional<int64_t>& t_ns) {
  if (!t_ns) Fail(Where(path, line.number), ": timestamp '", token, "' is not a number of seconds");
}

std::string Lowercase(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

// Opens a file for writing; throws naming the file on failure.
void CheckWritable(const fs::path& path, const Trajectory& trajectory) {
  FLATSLAM_CHECK(!trajectory.empty(), path.string(), ": refusing to write an empty trajectory");
  for (size_t i = 0; i < trajectory.size(); ++i) {
    FLATSLAM_CHECK(trajectory[i].T_world_cam.matrix().allFinite(), path.string(), ": pose ", i, " is not finite");
  }
}

}  // namespace

const char* TrajectoryFormatName(TrajectoryFormat format) {
  switch (format) {
    case TrajectoryFormat::kAuto:
      return "auto";
    case TrajectoryFormat::kTum:
      return "tum";
    case TrajectoryFormat::kKitti:
      return "kitti";
    case TrajectoryFormat::kEuroc:
      return "euroc";
  }
  return "?";
}

std::optional<TrajectoryFormat> ParseTrajectoryFormat(std::string_view name) {
  for (auto f : {TrajectoryFormat::kAuto, TrajectoryFormat::kTum, TrajectoryFormat::kKitti, TrajectoryFormat::kEuroc}) {
    if (name == TrajectoryFormatName(f)) return f;
  }
  return std::nullopt;
}

std::optional<int64_t> ParseSecondsToNs(std::string_view s) {
  size_t i = 0;
  bool negative = false;
  if (i < s.size() && (s[i] == '+' || s[i] == '-')) negative = s[i++] == '-';
  // Significant digits as an integer mantissa; digits past 36 only shift the exponent.
  unsigned __int128 mantissa = 0;
  int significant = 0, dropped = 0, fraction_digits = 0, digits = 0;
  bool in_fraction = false;
  for (; i < s.size(); ++i) {
    const char c = s[i];
    if (c == '.' && !in_fraction) {
      in_fraction = true;
      continue;
    }
    if (c < '0' || c > '9') break;
    ++digits;
    if (in_fraction) ++fraction_digits;
    if (significant == 0 && c == '0') continue;
    if (significant < 36) {
      mantissa = mantissa * 10 + static_cast<unsigned>(c - '0');
      ++significant;
    } else {
      ++dropped;
    }
  }
  if (digits == 0) return std::nullopt;
  int exponent = 0;
  if (i < s.size() && (s[i] == 'e' || s[i] == 'E')) {
    ++i;
    bool exp_negative = false;
    if (i < s.size() && (s[i] == '+' || s[i] == '-')) exp_negative = s[i++] == '-';
    int exp_digits = 0;
    for (; i < s.size() && s[i] >= '0' && s[i] <= '9'; ++i, ++exp_digits) {
      if (exponent < 10000) exponent = exponent * 10 + (s[i] - '0');
    }
    if (exp_digits == 0) return std::nullopt;
    if (exp_negative) exponent = -exponent;
  }
  if (i != s.size()) return std::nullopt;
  // Value in ns = mantissa * 10^power.
  int power = exponent - fraction_digits + dropped + 9;
  constexpr auto kMax = static_cast<unsigned __int128>(std::numeric_limits<int64_t>::max());
  if (mantissa == 0) return 0;
  if (power >= 0) {
    for (; power > 0; --power) {
      if (mantissa > kMax) return std::nullopt;
      mantissa *= 10;
    }
  } else if (power < -38) {
    mantissa = 0;
  } else {
    unsigned __int128 divisor = 1;
    for (int k = 0; k < -power; ++k) divisor *= 10;
    const unsigned __int128 remainder = mantissa % divisor;
    mantissa /= divisor;
    if (2 * remainder >= divisor) ++mantissa;
  }
  if (mantissa > kMax) return std::nullopt;
  const auto magnitude = static_cast<int64_t>(mantissa);
  return negative ? -magnitude : magnitude;
}

std::string FormatNsAsSeconds(int64_t t_ns) {
  const bool negative = t_ns < 0;
  const uint64_t magnitude = negative ? uint64_t{0} - static_cast<uint64_t>(t_ns) : static_cast<uint64_t>(t_ns);
  char buffer[48];
  std::snprintf(buffer, sizeof(buffer), "%s%" PRIu64 ".%09" PRIu64, negative ? "-" : "", magnitude / 1000000000u,
                magnitude % 1000000000u);
  return buffer;
}

bool TrajectoryReadOptions::Check() const {
  return std::isfinite(kitti_frame_rate_hz) && kitti_frame_rate_hz > 0;
}

TrajectoryFormat DetectTrajectoryFormat(const fs::path& path) {
  const auto lines = ReadDataLines(path, 2);
  DataLine line = lines.front();
  bool csv = Lowercase(path.extension().string()) == ".csv" || line.text.find(',') != std::string::npos;
  // A csv header without the leading '#' ("timestamp,p_x,...") is not data.
  if (csv && std::isalpha(static_cast<unsigned char>(TrimBlanks(line.text).front()))) {
    FLATSLAM_CHECK(lines.size() > 1, path.string(), ": no poses (only a header)");
    line = lines[1];
  }
  const auto fields = SplitLoose(line.text);
  if (csv && fields.size() >= 8 && IsUnsignedInteger(fields.front())) return TrajectoryFormat::kEuroc;
  if (fields.size() == 8) return TrajectoryFormat::kTum;
  if (fields.size() == 12) return TrajectoryFormat::kKitti;
  Fail(Where(path, line.number), ": cannot detect the trajectory format from ", fields.size(),
       " columns (TUM has 8, KITTI 12, EuRoC csv 8 or more with integer ns timestamps); "
       "name the format explicitly");
}

Trajectory ReadTum(const fs::path& path) {
  Trajectory trajectory;
  for (const DataLine& line : ReadDataLines(path)) {
    const auto f = SplitLoose(line.text);
    if (f.size() != 8) Fail(Where(path, line.number), ": expected 8 numbers (t tx ty tz qx qy qz qw), got ", f.size());
    const auto t_ns = ParseSecondsToNs(f[0]);
    CheckTimesAreFinite(path, line, f[0], t_ns);
    double v[8];
    static const char* const kNames[8] = {"t", "tx", "ty", "tz", "qx", "qy", "qz", "qw"};
    for (int k = 1; k < 8; ++k) v[k] = NumberAt(path, line, f[k], kNames[k]);
    TimedPose pose;
    pose.t_ns = *t_ns;
    pose.T_world_cam.linear() = NormalizedQuaternion(path, line, v[7], v[4], v[5], v[6]).toRotationMatrix();
    pose.T_world_cam.translation() = Eigen::Vector3d(v[1], v[2], v[3]);
    trajectory.push_back(pose);
  }
  return trajectory;
}

Trajectory ReadKitti(const fs::path& path, const std::vector<int64_t>& times_ns, double frame_rate_hz) {
  FLATSLAM_CHECK(std::isfinite(frame_rate_hz) && frame_rate_hz > 0, path.string(),
                 ": KITTI frame rate must be positive, got ", frame_rate_hz);
  Trajectory trajectory;
  for (const DataLine& line : ReadDataLines(path)) {
    const auto f = SplitLoose(line.text);
    if (f.size() != 12) Fail(Where(path, line.number), ": expected 12 numbers (3x4 row-major pose), got ", f.size());
    Eigen::Matrix<double, 3, 4> m;
    for (int k = 0; k < 12; ++k) m(k / 4, k % 4) = NumberAt(path, line, f[k], "value");
    const Eigen::Matrix3d r = m.leftCols<3>();
    // Files keep ~6 digits, so allow small deviations but reject what is plainly no rotation.
    const double deviation = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
    if (!(deviation < 1e-2) || r.determinant() <= 0)
      Fail(Where(path, line.number), ": the left 3x3 block is not a rotation (|R^T R - I| = ", deviation,
           ", det = ", r.determinant(), ")");
    TimedPose pose;
    const size_t index = trajectory.size();
    pose.t_ns = std::llround(static_cast<double>(index) * 1e9 / frame_rate_hz);
    pose.T_world_cam.linear() = r;
    pose.T_world_cam.translation() = m.col(3);
    trajectory.push_back(pose);
  }
  if (!times_ns.empty()) {
    FLATSLAM_CHECK(times_ns.size() == trajectory.size(), path.string(), ": ", trajectory.size(), " poses but ",
                   times_ns.size(), " timestamps");
    for (size_t i = 0; i < trajectory.size(); ++i) trajectory[i].t_ns = times_ns[i];
  }
  return trajectory;
}

Trajectory ReadEuroc(const fs::path& path) {
  Trajectory trajectory;
  const auto lines = ReadDataLines(path);
  for (size_t n = 0; n < lines.size(); ++n) {
    const DataLine& line = lines[n];
    const auto f = SplitCsv(line.text);
    // A header without the leading '#' ("timestamp,p_x,...") is skipped.
    if (n == 0 && !f.front().empty() && std::isalpha(static_cast<unsigned char>(f.front().front()))) continue;
    if (f.size() < 8)
      Fail(Where(path, line.number),
           ": expected at least 8 comma-separated values "
           "(timestamp_ns, px, py, pz, qw, qx, qy, qz), got ",
           f.size());
    if (!IsUnsignedInteger(f[0]))
      Fail(Where(path, line.number), ": timestamp '", f[0], "' is not an integer number of nanoseconds");
    int64_t t_ns = 0;
    auto [ptr, ec] = std::from_chars(f[0].data(), f[0].data() + f[0].size(), t_ns);
    if (ec != std::errc() || ptr != f[0].data() + f[0].size())
      Fail(Where(path, line.number), ": timestamp '", f[0], "' is out of range");
    static const char* const kNames[8] = {"t", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"};
    double v[8];
    for (int k = 1; k < 8; ++k) v[k] = NumberAt(path, line, f[k], kNames[k]);
    TimedPose pose;
    pose.t_ns = t_ns;
    pose.T_world_cam.linear() = NormalizedQuaternion(path, line, v[4], v[5], v[6], v[7]).toRotationMatrix();
    pose.T_world_cam.translation() = Eigen::Vector3d(v[1], v[2], v[3]);
    trajectory.push_back(pose);
  }
  FLATSLAM_CHECK(!trajectory.empty(), path.string(), ": no poses (only a header)");
  return trajectory;
}

std::vector<int64_t> ReadKittiTimes(const fs::path& path) {
  std::vector<int64_t> times;
  for (const DataLine& line : ReadDataLines(path)) {
    const auto f = SplitLoose(line.text);
    if (f.size() != 1) Fail(Where(path, line.number), ": expected 1 time in seconds, got ", f.size(), " values");
    const auto t_ns = ParseSecondsToNs(f[0]);
    CheckTimesAreFinite(path, line, f[0], t_ns);
    times.push_back(*t_ns);
  }
  return times;
}

Trajectory ReadTrajectory(const fs::path& path, const TrajectoryReadOptions& options) {
  FLATSLAM_CHECK(options.Check(), path.string(), ": invalid read options (KITTI frame rate ",
                 options.kitti_frame_rate_hz, ")");
  TrajectoryFormat format = options.format;
  if (format == TrajectoryFormat::kAuto) format = DetectTrajectoryFormat(path);
  FLATSLAM_CHECK(format == TrajectoryFormat::kKitti || options.kitti_times_ns.empty(), path.string(),
                 ": timestamps were given, but only KITTI files take them (this is ", TrajectoryFormatName(format),
                 ")");
  switch (format) {
    case TrajectoryFormat::kTum:
      return ReadTum(path);
    case TrajectoryFormat::kKitti:
      return ReadKitti(path, options.kitti_times_ns, options.kitti_frame_rate_hz);
    case TrajectoryFormat::kEuroc:
      return ReadEuroc(path);
    case TrajectoryFormat::kAuto:
      break;
  }
  Fail(path.string(), ": unknown trajectory format");
}

Eigen::Quaterniond CanonicalQuaternion(const Eigen::Matrix3d& rotation) {
  Eigen::Quaterniond q(rotation);
  q.normalize();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  return q;
}

std::string FormatTumLine(const TimedPose& pose) {
  const Eigen::Quaterniond q = CanonicalQuaternion(pose.T_world_cam.linear());
  const Eigen::Vector3d t = pose.T_world_cam.translation();
  char line[256];
  std::snprintf(line, sizeof(line), "%s %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n",
                FormatNsAsSeconds(pose.t_ns).c_str(), t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w());
  return line;
}

void WriteTum(const fs::path& path, const Trajectory& trajectory) {
  CheckWritable(path, trajectory);
  WriteFileAtomically(path, [&](std::FILE* file) {
    std::fputs(kTumHeader, file);
    for (const TimedPose& pose : trajectory) std::fputs(FormatTumLine(pose).c_str(), file);
  });
}

void WriteKitti(const fs::path& path, const Trajectory& trajectory) {
  CheckWritable(path, trajectory);
  WriteFileAtomically(path, [&](std::FILE* file) {
    for (const TimedPose& pose : trajectory) {
      const Eigen::Matrix<double, 3, 4> m = pose.T_world_cam.matrix().topRows<3>();
      for (int k = 0; k < 12; ++k) std::fprintf(file, k == 0 ? "%.17g" : " %.17g", m(k / 4, k % 4));
      std::fputc('\n', file);
    }
  });
}

void WriteEuroc(const fs::path& path, const Trajectory& trajectory) {
  CheckWritable(path, trajectory);
  WriteFileAtomically(path, [&](std::FILE* file) {
    std::fputs("#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []\n", file);
    for (const TimedPose& pose : trajectory) {
      const Eigen::Quaterniond q = CanonicalQuaternion(pose.T_world_cam.linear());
      const Eigen::Vector3d t = pose.T_world_cam.translation();
      std::fprintf(file, "%lld,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g\n", static_cast<long long>(pose.t_ns), t.x(),
                   t.y(), t.z(), q.w(), q.x(), q.y(), q.z());
    }
  });
}

void WriteKittiTimes(const fs::path& path, const Trajectory& trajectory) {
  CheckWritable(path, trajectory);
  WriteFileAtomically(path, [&](std::FILE* file) {
    for (const TimedPose& pose : trajectory) std::fprintf(file, "%s\n", FormatNsAsSeconds(pose.t_ns).c_str());
  });
}

}  // namespace flatslam
