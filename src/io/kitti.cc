#include "io/kitti.h"

#include <array>
#include <cstdio>
#include <map>
#include <system_error>

#include <Eigen/SVD>

#include "core/error.h"
#include "io/image_io.h"

namespace flatslam {
namespace {

using Matrix34d = Eigen::Matrix<double, 3, 4, Eigen::RowMajor>;

// Parses the 12 numbers of a row-major 3x4 matrix starting at fields[first].
Matrix34d ParseMatrix34(const std::vector<std::string>& fields, size_t first, const std::filesystem::path& path,
                        int line, std::string_view what) {
  FLATSLAM_CHECK(fields.size() == first + 12, io::Where(path, line), "expected 12 numbers for ", what, ", got ",
                 fields.size() - first);
  Matrix34d m;
  for (int k = 0; k < 12; ++k) m(k / 4, k % 4) = io::ParseNumber(fields[first + k], path, line, what);
  return m;
}

// calib.txt: "P0: 12 numbers" lines (also Tr:, ignored); returns the projection matrices by name.
std::map<std::string, Matrix34d> ReadCalib(const std::filesystem::path& path) {
  std::map<std::string, Matrix34d> matrices;
  for (const io::TextLine& line : io::ReadTextLines(path)) {
    const auto fields = io::SplitFields(line.text);
    std::string key = fields[0];
    if (key.empty() || key.back() != ':') continue;
    key.pop_back();
    if (key.size() == 2 && key[0] == 'P') matrices[key] = ParseMatrix34(fields, 1, path, line.number, key);
  }
  return matrices;
}

// Nearest rotation (KITTI poses are orthonormal only to ~1e-6).
Eigen::Matrix3d Orthonormalize(const Eigen::Matrix3d& m) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(m, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d r = svd.matrixU() * svd.matrixV().transpose();
  if (r.determinant() < 0) {
    Eigen::Matrix3d u = svd.matrixU();
    u.col(2) *= -1;
    r = u * svd.matrixV().transpose();
  }
  return r;
}

}  // namespace

KittiDataset::KittiDataset(const std::filesystem::path& sequence_dir, const KittiOptions& options)
    : dir_(sequence_dir), sequence_(io::FolderName(sequence_dir)) {
  std::error_code ec;
  FLATSLAM_CHECK(std::filesystem::is_directory(dir_, ec), "KITTI sequence folder not found: ", dir_.string());
  FLATSLAM_CHECK(std::filesystem::is_directory(dir_ / "image_0", ec), "KITTI sequence ", dir_.string(),
                 " has no image_0/ folder");
  const bool has_right = std::filesystem::is_directory(dir_ / "image_1", ec);
  const std::string available = has_right ? "mono, stereo" : "mono (no image_1/)";
  const Sensor sensor = options.sensor.value_or(has_right ? Sensor::kStereo : Sensor::kMonocular);
  FLATSLAM_CHECK(sensor != Sensor::kRgbd, "KITTI sequence ", dir_.string(), " has no RGB-D; available: ", available);
  FLATSLAM_CHECK(sensor != Sensor::kStereo || has_right, "stereo requested but ", (dir_ / "image_1").string(),
                 " is missing; available: ", available);

  const auto calib_txt = dir_ / "calib.txt";
  const auto projections = ReadCalib(calib_txt);
  const auto p0 = projections.find("P0");
  FLATSLAM_CHECK(p0 != projections.end(), calib_txt.string(), " has no 'P0:' line");
  calibration_.sensor = sensor;
  calibration_.camera.fx = p0->second(0, 0);
  calibration_.camera.fy = p0->second(1, 1);
  calibration_.camera.cx = p0->second(0, 2);
  calibration_.camera.cy = p0->second(1, 2);
  if (sensor == Sensor::kStereo) {
    const auto p1 = projections.find("P1");
    FLATSLAM_CHECK(p1 != projections.end(), calib_txt.string(), " has no 'P1:' line (needed for stereo)");
    FLATSLAM_CHECK(p1->second(0, 0) > 0, calib_txt.string(), ": P1[0][0] must be positive");
    calibration_.baseline_m = -p1->second(0, 3) / p1->second(0, 0);
    FLATSLAM_CHECK(calibration_.baseline_m > 0, calib_txt.string(), ": P1 gives a non-positive baseline (",
                   calibration_.baseline_m, " m)");
  }

  const auto times_txt = dir_ / "times.txt";
  for (const io::TextLine& line : io::ReadTextLines(times_txt)) {
    times_ns_.push_back(io::ParseSecondsNs(io::SplitFields(line.text)[0], times_txt, line.number));
  }
  FLATSLAM_CHECK(!times_ns_.empty(), times_txt.string(), " lists no frames");
  calibration_.frame_rate_hz = io::MedianRateHz(times_ns_);

  // The first left image fixes the size; the last images must exist (catches a short download).
  const cv::Size size = ReadImageSize(image_path(0, 0));
  calibration_.camera.width = size.width;
  calibration_.camera.height = size.height;
  for (int camera = 0; camera < (sensor == Sensor::kStereo ? 2 : 1); ++camera) {
    const auto last = image_path(camera, times_ns_.size() - 1);
    FLATSLAM_CHECK(std::filesystem::is_regular_file(last, ec), "image not found: ", last.string(), " (",
                   times_txt.string(), " lists ", times_ns_.size(), " frames)");
  }

  std::filesystem::path poses = options.poses_file;
  if (poses.empty()) {
    const auto fallback = dir_ / ".." / ".." / "poses" / (sequence_ + ".txt");
    if (std::filesystem::is_regular_file(fallback, ec)) poses = fallback.lexically_normal();
  }
  if (!poses.empty()) {
    Trajectory trajectory;
    for (const io::TextLine& line : io::ReadTextLines(poses)) {
      FLATSLAM_CHECK(trajectory.size() < times_ns_.size(), io::Where(poses, line.number), "more poses than the ",
                     times_ns_.size(), " frames of ", times_txt.string());
      const Matrix34d m = ParseMatrix34(io::SplitFields(line.text), 0, poses, line.number, "a 3x4 pose");
      TimedPose pose;
      pose.t_ns = times_ns_[trajectory.size()];
      pose.T_world_cam.linear() = Orthonormalize(m.leftCols<3>());
      pose.T_world_cam.translation() = m.col(3);
      trajectory.push_back(pose);
    }
    FLATSLAM_CHECK(trajectory.size() == times_ns_.size(), poses.string(), " has ", trajectory.size(),
                   " poses, expected one per frame of ", times_txt.string(), " (", times_ns_.size(), ")");
    ground_truth_ = std::move(trajectory);
  }
}

std::string KittiDataset::name() const {
  return "KITTI " + sequence_ + (calibration_.sensor == Sensor::kStereo ? " (stereo)" : " (mono)");
}

std::filesystem::path KittiDataset::image_path(int camera, size_t i) const {
  char file[32];
  std::snprintf(file, sizeof(file), "%06zu.png", i);
  return dir_ / (camera == 0 ? "image_0" : "image_1") / file;
}

Frame KittiDataset::read(size_t i) const {
  FLATSLAM_CHECK(i < times_ns_.size(), "frame ", i, " out of range: ", name(), " has ", times_ns_.size(), " frames");
  const cv::Size size(calibration_.camera.width, calibration_.camera.height);
  Frame frame;
  frame.index = i;
  frame.t_ns = times_ns_[i];
  frame.left = ReadGrayImage(image_path(0, i), size);
  if (calibration_.sensor == Sensor::kStereo) frame.right = ReadGrayImage(image_path(1, i), size);
  return frame;
}

}  // namespace flatslam
