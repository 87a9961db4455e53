// Reading and writing trajectory files: TUM, KITTI odometry poses and EuRoC ASL ground truth.
// Concurrency: stateless free functions, callable from any thread (distinct files).
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>

#include <Eigen/Geometry>
#include <string_view>
#include <vector>

#include "trajectory/trajectory.h"

namespace flatslam {

enum class TrajectoryFormat {
  kAuto,   // detect from extension and content (see DetectTrajectoryFormat)
  kTum,    // "t tx ty tz qx qy qz qw", t in seconds, '#' comments
  kKitti,  // 12 numbers a line: the 3x4 row-major [R|t], no timestamps
  kEuroc,  // ASL csv: "timestamp_ns, px, py, pz, qw, qx, qy, qz, ..." (extra columns ignored)
};

// "auto", "tum", "kitti" or "euroc".
[[nodiscard]] const char* TrajectoryFormatName(TrajectoryFormat format);
// Inverse of TrajectoryFormatName; nullopt for an unknown name.
[[nodiscard]] std::optional<TrajectoryFormat> ParseTrajectoryFormat(std::string_view name);

// Looks at the first data line (after a csv header): a ".csv" file or comma-separated line
// whose first field is an integer (ns) is EuRoC; otherwise 8 columns is TUM and 12 is KITTI.
// Throws flatslam::Error naming the file when it cannot be read, holds no data or fits no format.
[[nodiscard]] TrajectoryFormat DetectTrajectoryFormat(const std::filesystem::path& path);

struct TrajectoryReadOptions {
  // Format of the file; kAuto detects it.
  TrajectoryFormat format = TrajectoryFormat::kAuto;
  // KITTI only: timestamps of the poses (one per pose, e.g. from ReadKittiTimes). When
  // empty, pose i gets the time i / kitti_frame_rate_hz.
  std::vector<int64_t> kitti_times_ns;
  // KITTI only: frame rate used when kitti_times_ns is empty; KITTI odometry is 10 Hz.
  double kitti_frame_rate_hz = 10.0;

  [[nodiscard]] bool Check() const;
};

// Reads any supported format. Every parse error names the file, the line and what is
// wrong ("poses.txt:17: expected 12 numbers, got 11"); a file without poses is an error.
// Quaternions are normalized; a zero quaternion is an error.
[[nodiscard]] Trajectory ReadTrajectory(const std::filesystem::path& path, const TrajectoryReadOptions& options = {});

[[nodiscard]] Trajectory ReadTum(const std::filesystem::path& path);
// times_ns: one per pose, or empty to use index / frame_rate_hz.
[[nodiscard]] Trajectory ReadKitti(const std::filesystem::path& path, const std::vector<int64_t>& times_ns = {},
                                   double frame_rate_hz = 10.0);
[[nodiscard]] Trajectory ReadEuroc(const std::filesystem::path& path);
// KITTI times.txt: one time in seconds per line.
[[nodiscard]] std::vector<int64_t> ReadKittiTimes(const std::filesystem::path& path);

// Writers use max_digits10 so that reading back gives the same poses (to ~1e-15) and the
// same nanosecond timestamps. They replace the file atomically (core/atomic_write.h): a reader
// or a crash sees the old file or the new one, never a mix. Throw flatslam::Error naming the
// file when it cannot be written.
void WriteTum(const std::filesystem::path& path, const Trajectory& trajectory);
// KITTI drops the timestamps (write them with WriteKittiTimes if needed).
void WriteKitti(const std::filesystem::path& path, const Trajectory& trajectory);
void WriteKittiTimes(const std::filesystem::path& path, const Trajectory& trajectory);
// EuRoC csv: "#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z" then one pose a line (ReadEuroc's input).
void WriteEuroc(const std::filesystem::path& path, const Trajectory& trajectory);
// The unit quaternion of a rotation with w >= 0: of the two equal ones always the same, so that
// files written from equal poses are equal (TUM, EuRoC, COLMAP exports).
[[nodiscard]] Eigen::Quaterniond CanonicalQuaternion(const Eigen::Matrix3d& rotation);
// The first line of a TUM file written here, and one pose as a TUM line (with its newline), for
// writers that append poses as they come (flatslam run's streamed trajectory).
inline constexpr const char* kTumHeader = "# timestamp tx ty tz qx qy qz qw\n";
[[nodiscard]] std::string FormatTumLine(const TimedPose& pose);

// Parses a decimal time in seconds ("1311868164.363181", "1.4037e+09") into exact
// nanoseconds, rounding half away from zero below 1 ns; nullopt when it is not a number.
[[nodiscard]] std::optional<int64_t> ParseSecondsToNs(std::string_view text);
// Formats nanoseconds as seconds with 9 decimals, exact ("-0.000000001").
[[nodiscard]] std::string FormatNsAsSeconds(int64_t t_ns);

}  // namespace flatslam
