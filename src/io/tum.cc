#include "io/tum.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <fstream>
#include <iomanip>
#include <limits>
#include <system_error>
#include <tuple>

#include "core/error.h"
#include "io/image_io.h"
#include "io/rectify.h"

namespace flatslam {
namespace {

// rgb.txt / depth.txt: "timestamp filename" per line, filename relative to the sequence dir.
std::vector<io::StampedFile> ReadFileList(const std::filesystem::path& path, const std::filesystem::path& dir) {
  std::vector<io::StampedFile> list;
  for (const io::TextLine& line : io::ReadTextLines(path)) {
    const auto fields = io::SplitFields(line.text);
    FLATSLAM_CHECK(fields.size() >= 2, io::Where(path, line.number), "expected 'timestamp filename', got '", line.text,
                   "'");
    list.push_back({io::ParseSecondsNs(fields[0], path, line.number), dir / fields[1]});
  }
  FLATSLAM_CHECK(!list.empty(), path.string(), " lists no frames");
  std::stable_sort(list.begin(), list.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
  return list;
}

// Published calibration of the Freiburg Kinects' colour cameras (vision.in.tum.de, "Intrinsic
// Camera Calibration"): intrinsics and OpenCV's k1 k2 p1 p2 k3. fr3's images come undistorted.
struct FreiburgCalibration {
  PinholeCamera camera;
  std::array<double, 5> distortion{};
};

std::optional<FreiburgCalibration> FreiburgCamera(const std::string& folder_name) {
  std::string name = folder_name;
  std::transform(name.begin(), name.end(), name.begin(), [](unsigned char c) { return std::tolower(c); });
  const auto tokens = io::SplitFields(name, " _-.");
  auto has = [&](char digit) {
    const std::string fr = std::string("fr") + digit, freiburg = std::string("freiburg") + digit;
    return name.find(freiburg) != std::string::npos || std::find(tokens.begin(), tokens.end(), fr) != tokens.end();
  };
  FreiburgCalibration c;
  PinholeCamera& camera = c.camera;
  camera.width = 640;
  camera.height = 480;
  if (has('1')) {
    std::tie(camera.fx, camera.fy, camera.cx, camera.cy) = std::tuple(517.3, 516.5, 318.6, 255.3);
    c.distortion = {0.2624, -0.9531, -0.0054, 0.0026, 1.1633};
  } else if (has('2')) {
    std::tie(camera.fx, camera.fy, camera.cx, camera.cy) = std::tuple(520.9, 521.0, 325.1, 249.7);
    c.distortion = {0.2312, -0.7849, -0.0033, -0.0001, 0.9172};
  } else if (has('3')) {
    std::tie(camera.fx, camera.fy, camera.cx, camera.cy) = std::tuple(535.4, 539.2, 320.1, 247.6);
  } else {
    return std::nullopt;
  }
  return c;
}

Eigen::Isometry3d Interpolate(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b, double s) {
  const Eigen::Quaterniond qa(a.linear()), qb(b.linear());
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  out.linear() = qa.slerp(s, qb).normalized().toRotationMatrix();
  out.translation() = (1 - s) * a.translation() + s * b.translation();
  return out;
}

}  // namespace

TumCameraFile ReadTumCameraFile(const std::filesystem::path& path) {
  const auto lines = io::ReadTextLines(path);
  FLATSLAM_CHECK(!lines.empty(), path.string(), " is empty, expected 'fx fy cx cy width height [depth_factor]'");
  FLATSLAM_CHECK(lines.size() == 1, io::Where(path, lines[1].number),
                 "expected one line 'fx fy cx cy width height [depth_factor]'");
  const auto fields = io::SplitFields(lines[0].text);
  const int n = lines[0].number;
  FLATSLAM_CHECK(fields.size() == 6 || fields.size() == 7, io::Where(path, n),
                 "expected 'fx fy cx cy width height [depth_factor]', got ", fields.size(), " fields");
  TumCameraFile file;
  PinholeCamera& c = file.camera;
  c.fx = io::ParseNumber(fields[0], path, n, "fx");
  c.fy = io::ParseNumber(fields[1], path, n, "fy");
  c.cx = io::ParseNumber(fields[2], path, n, "cx");
  c.cy = io::ParseNumber(fields[3], path, n, "cy");
  const double width = io::ParseNumber(fields[4], path, n, "width");
  const double height = io::ParseNumber(fields[5], path, n, "height");
  FLATSLAM_CHECK(width == std::floor(width) && height == std::floor(height) && width < 1e6 && height < 1e6,
                 io::Where(path, n), "width and height must be integers");
  c.width = static_cast<int>(width);
  c.height = static_cast<int>(height);
  if (fields.size() == 7) file.depth_factor = io::ParseNumber(fields[6], path, n, "depth_factor");
  FLATSLAM_CHECK(c.valid(), io::Where(path, n), "fx, fy, width and height must be positive");
  FLATSLAM_CHECK(file.depth_factor > 0, io::Where(path, n), "depth_factor must be positive");
  return file;
}

void WriteTumCameraFile(const std::filesystem::path& path, const TumCameraFile& file) {
  std::ofstream out(path);
  FLATSLAM_CHECK(out.good(), "cannot write ", path.string());
  const PinholeCamera& c = file.camera;
  out << "# fx fy cx cy width height depth_factor\n"
      << std::setprecision(std::numeric_limits<double>::max_digits10) << c.fx << ' ' << c.fy << ' ' << c.cx << ' '
      << c.cy << ' ' << c.width << ' ' << c.height << ' ' << file.depth_factor << '\n';
  out.close();
  FLATSLAM_CHECK(!out.fail(), "write error in ", path.string());
}

TumDataset::TumDataset(const std::filesystem::path& sequence_dir, const TumOptions& options) : dir_(sequence_dir) {
  FLATSLAM_CHECK(options.Check(), "TumOptions: max_association_dt_ns must be positive, depth_factor not negative");
  std::error_code ec;
  FLATSLAM_CHECK(std::filesystem::is_directory(dir_, ec), "TUM sequence folder not found: ", dir_.string());
  const auto rgb_txt = dir_ / "rgb.txt", depth_txt = dir_ / "depth.txt";
  const bool has_depth = std::filesystem::is_regular_file(depth_txt, ec);
  const std::string available = has_depth ? "mono, rgbd" : "mono (no depth.txt)";

  const Sensor sensor = options.sensor.value_or(has_depth ? Sensor::kRgbd : Sensor::kMonocular);
  FLATSLAM_CHECK(sensor != Sensor::kStereo, "TUM RGB-D sequence ", dir_.string(),
                 " has no stereo; available: ", available);
  FLATSLAM_CHECK(sensor != Sensor::kRgbd || has_depth, "RGB-D requested but ", depth_txt.string(),
                 " is missing; available: ", available);

  const auto rgb = ReadFileList(rgb_txt, dir_);
  if (sensor == Sensor::kRgbd) {
    const auto depth = ReadFileList(depth_txt, dir_);
    std::vector<int64_t> rgb_t, depth_t;
    for (const auto& e : rgb) rgb_t.push_back(e.t_ns);
    for (const auto& e : depth) depth_t.push_back(e.t_ns);
    for (const auto& [i, j] : io::AssociateStamps(rgb_t, depth_t, options.max_association_dt_ns)) {
      frames_.push_back({rgb[i].t_ns, rgb[i].file, depth[j].t_ns, depth[j].file});
    }
    unmatched_rgb_ = rgb.size() - frames_.size();
    FLATSLAM_CHECK(!frames_.empty(), "no RGB frame of ", rgb_txt.string(), " has a depth image in ", depth_txt.string(),
                   " within ", options.max_association_dt_ns * 1e-6, " ms");
  } else {
    for (const auto& e : rgb) frames_.push_back({e.t_ns, e.file, 0, {}});
  }

  const auto camera_txt = dir_ / "camera.txt";
  const std::string folder = io::FolderName(dir_);
  if (options.camera) {
    calibration_.camera = *options.camera;
    if (calibration_.camera.width <= 0 || calibration_.camera.height <= 0) {
      const cv::Size size = ReadImageSize(frames_.front().rgb);
      calibration_.camera.width = size.width;
      calibration_.camera.height = size.height;
    }
    calibration_source_ = "options";
  } else if (std::filesystem::exists(camera_txt, ec)) {
    const TumCameraFile file = ReadTumCameraFile(camera_txt);
    calibration_.camera = file.camera;
    depth_factor_ = file.depth_factor;
    calibration_source_ = "camera.txt";
  } else if (const auto freiburg = FreiburgCamera(folder)) {
    calibration_.camera = freiburg->camera;
    depth_factor_ = 5000;
    calibration_source_ = "Freiburg intrinsics";
    if (std::any_of(freiburg->distortion.begin(), freiburg->distortion.end(), [](double d) { return d != 0; })) {
      // fr1/fr2: both images are undistorted with the same map (the depth image is registered to
      // the colour one), nearest-neighbour for depth; the camera keeps only valid pixels. Near
      // the corners the distortion moves a pixel by up to about 25 px (fr1).
      const PinholeCamera& raw = freiburg->camera;
      const cv::Matx33d K(raw.fx, 0, raw.cx, 0, raw.fy, raw.cy, 0, 0, 1);
      const cv::Mat D(freiburg->distortion, true);
      const cv::Size size(raw.width, raw.height);
      const cv::Matx33d k = UndistortedCameraMatrix(K, D.reshape(1, 1), size, 0);
      undistort_ = RectifyMap(K, D.reshape(1, 1), cv::Matx33d::eye(), k, size);
      calibration_.camera.fx = k(0, 0);
      calibration_.camera.fy = k(1, 1);
      calibration_.camera.cx = k(0, 2);
      calibration_.camera.cy = k(1, 2);
      calibration_source_ = "Freiburg intrinsics and distortion";
    }
  } else {
    Fail("no calibration for TUM sequence ", dir_.string(), ": ", camera_txt.string(),
         " is missing and the folder name names no freiburg1/2/3 camera");
  }
  if (options.depth_factor > 0) depth_factor_ = options.depth_factor;
  color_order_ = options.color_order;
  calibration_.sensor = sensor;
  std::vector<int64_t> stamps;
  for (const auto& f : frames_) stamps.push_back(f.t_ns);
  calibration_.frame_rate_hz = io::MedianRateHz(stamps);

  const auto gt_txt = dir_ / "groundtruth.txt";
  if (std::filesystem::exists(gt_txt, ec)) ground_truth_ = io::PosesAtTimes(io::ReadTumPoseFile(gt_txt), stamps);
}

std::string TumDataset::name() const {
  std::string name = "TUM " + io::FolderName(dir_) + (calibration_.sensor == Sensor::kRgbd ? " (RGB-D" : " (mono");
  if (unmatched_rgb_ > 0) name += ", " + std::to_string(unmatched_rgb_) + " RGB frames without depth dropped";
  return name + ")";
}

Frame TumDataset::read(size_t i) const {
  FLATSLAM_CHECK(i < frames_.size(), "frame ", i, " out of range: ", name(), " has ", frames_.size(), " frames");
  const Entry& entry = frames_[i];
  const cv::Size size(calibration_.camera.width, calibration_.camera.height);
  Frame frame;
  frame.index = i;
  frame.t_ns = entry.t_ns;
  frame.left = undistort_.Apply(ReadGrayImage(entry.rgb, size, color_order_));
  if (calibration_.sensor == Sensor::kRgbd)
    frame.depth = undistort_.Apply(ReadDepthImage(entry.depth, depth_factor_, size), Interpolation::kNearest);
  return frame;
}

namespace io {

Trajectory ReadTumPoseFile(const std::filesystem::path& path) {
  Trajectory trajectory;
  for (const TextLine& line : ReadTextLines(path)) {
    const auto fields = SplitFields(line.text, " \t,");
    FLATSLAM_CHECK(fields.size() == 8, Where(path, line.number), "expected 't tx ty tz qx qy qz qw', got ",
                   fields.size(), " fields");
    std::array<double, 7> v{};
    for (int k = 0; k < 7; ++k) v[k] = ParseNumber(fields[k + 1], path, line.number, "a pose value");
    Eigen::Quaterniond q(v[6], v[3], v[4], v[5]);  // w, x, y, z
    FLATSLAM_CHECK(q.norm() > 1e-9, Where(path, line.number), "zero quaternion");
    TimedPose pose;
    pose.t_ns = ParseSecondsNs(fields[0], path, line.number);
    pose.T_world_cam.linear() = q.normalized().toRotationMatrix();
    pose.T_world_cam.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
    trajectory.push_back(pose);
  }
  FLATSLAM_CHECK(!trajectory.empty(), path.string(), " holds no poses");
  std::stable_sort(trajectory.begin(), trajectory.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
  return trajectory;
}

Trajectory PosesAtTimes(const Trajectory& samples, const std::vector<int64_t>& t_ns,
                        const PoseSamplingOptions& options) {
  Trajectory out;
  for (const int64_t t : t_ns) {
    const auto upper = std::lower_bound(samples.begin(), samples.end(), t,
                                        [](const TimedPose& p, int64_t value) { return p.t_ns < value; });
    const TimedPose* after = upper != samples.end() ? &*upper : nullptr;
    const TimedPose* before = upper != samples.begin() ? &*(upper - 1) : nullptr;
    TimedPose pose;
    pose.t_ns = t;
    if (after && after->t_ns == t) {
      pose.T_world_cam = after->T_world_cam;
    } else if (before && after && after->t_ns - before->t_ns <= options.max_interpolation_gap_ns) {
      const double s = static_cast<double>(t - before->t_ns) / static_cast<double>(after->t_ns - before->t_ns);
      pose.T_world_cam = Interpolate(before->T_world_cam, after->T_world_cam, s);
    } else {
      const TimedPose* nearest = nullptr;
      if (before) nearest = before;
      if (after && (!nearest || after->t_ns - t < t - nearest->t_ns)) nearest = after;
      if (!nearest || std::abs(nearest->t_ns - t) > options.max_nearest_dt_ns) continue;
      pose.T_world_cam = nearest->T_world_cam;
    }
    out.push_back(pose);
  }
  return out;
}

std::vector<std::pair<size_t, size_t>> AssociateStamps(const std::vector<int64_t>& a, const std::vector<int64_t>& b,
                                                       int64_t max_dt_ns) {
  struct Candidate {
    int64_t dt;
    size_t i, j;
  };
  std::vector<Candidate> candidates;
  size_t first = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    while (first < b.size() && b[first] <= a[i] - max_dt_ns) ++first;
    for (size_t j = first; j < b.size() && b[j] < a[i] + max_dt_ns; ++j) {
      candidates.push_back({std::abs(a[i] - b[j]), i, j});
    }
  }
  std::sort(candidates.begin(), candidates.end(),
            [](const Candidate& x, const Candidate& y) { return std::tie(x.dt, x.i, x.j) < std::tie(y.dt, y.i, y.j); });
  std::vector<bool> used_a(a.size(), false), used_b(b.size(), false);
  std::vector<std::pair<size_t, size_t>> pairs;
  for (const Candidate& c : candidates) {
    if (used_a[c.i] || used_b[c.j]) continue;
    used_a[c.i] = used_b[c.j] = true;
    pairs.emplace_back(c.i, c.j);
  }
  std::sort(pairs.begin(), pairs.end());
  return pairs;
}

}  // namespace io
}  // namespace flatslam
