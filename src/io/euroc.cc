#include "io/euroc.h"

#include <algorithm>
#include <fstream>
#include <map>
#include <system_error>

#include "core/error.h"
#include "core/text.h"
#include "io/image_io.h"
#include "io/rectify.h"
#include "io/tum.h"

namespace flatslam {
namespace {

struct YamlField {
  std::string text;
  int line = 0;
};

// Block mappings of scalars and flow lists ("[a, b,\n c]"); nested keys become "T_BS.data".
// Enough for EuRoC/Kalibr sensor.yaml files; anything else is skipped, not misread.
std::map<std::string, YamlField> ReadYamlSubset(const std::filesystem::path& path) {
  std::error_code ec;
  FLATSLAM_CHECK(std::filesystem::is_regular_file(path, ec), "file not found: ", path.string());
  std::ifstream in(path);
  FLATSLAM_CHECK(in.good(), "cannot open ", path.string());
  std::map<std::string, YamlField> fields;
  std::vector<std::pair<size_t, std::string>> parents;  // (indent, key)
  std::string pending_key;                              // flow list spanning lines
  YamlField pending;
  std::string raw;
  int number = 0;
  while (std::getline(in, raw)) {
    ++number;
    const std::string line = raw.substr(0, raw.find('#'));
    if (!pending_key.empty()) {
      pending.text += ' ';
      pending.text += Trimmed(line);
      if (line.find(']') != std::string::npos) {
        fields[pending_key] = pending;
        pending_key.clear();
      }
      continue;
    }
    const std::string trimmed = Trimmed(line);
    if (trimmed.empty() || trimmed[0] == '%' || trimmed.rfind("---", 0) == 0) continue;
    const size_t colon = trimmed.find(':');
    if (colon == std::string::npos) continue;
    const size_t indent = line.find_first_not_of(' ');
    while (!parents.empty() && parents.back().first >= indent) parents.pop_back();
    std::string key;
    for (const auto& parent : parents) key += parent.second + ".";
    key += Trimmed(trimmed.substr(0, colon));
    std::string value = Trimmed(trimmed.substr(colon + 1));
    if (value.size() >= 2 && (value.front() == '"' || value.front() == '\'') && value.back() == value.front()) {
      value = value.substr(1, value.size() - 2);
    }
    if (value.empty() || value.rfind("!!", 0) == 0) {
      parents.emplace_back(indent, Trimmed(trimmed.substr(0, colon)));
    } else if (value.front() == '[' && value.find(']') == std::string::npos) {
      pending_key = key;
      pending = {value, number};
      continue;
    }
    if (!value.empty()) fields[key] = {value, number};
  }
  FLATSLAM_CHECK(pending_key.empty(), io::Where(path, pending.line), "list of '", pending_key, "' is not closed");
  return fields;
}

const YamlField& Require(const std::map<std::string, YamlField>& fields, const std::string& key,
                         const std::filesystem::path& path) {
  const auto it = fields.find(key);
  FLATSLAM_CHECK(it != fields.end(), path.string(), ": missing field '", key, "'");
  return it->second;
}

// "[a, b, c]" with exactly `count` numbers.
std::vector<double> NumberList(const std::map<std::string, YamlField>& fields, const std::string& key, size_t count,
                               const std::filesystem::path& path) {
  const YamlField& field = Require(fields, key, path);
  std::string text = Trimmed(field.text);
  FLATSLAM_CHECK(text.size() >= 2 && text.front() == '[' && text.back() == ']', io::Where(path, field.line), "field '",
                 key, "' must be a list [..]");
  std::vector<double> values;
  for (const std::string& item : io::SplitFields(text.substr(1, text.size() - 2), ",")) {
    values.push_back(io::ParseNumber(Trimmed(item), path, field.line, key));
  }
  FLATSLAM_CHECK(values.size() == count, io::Where(path, field.line), "field '", key, "' must hold ", count,
                 " numbers, got ", values.size());
  return values;
}

// mav0/camN/data.csv: "#timestamp [ns],filename"; images in mav0/camN/data/.
std::vector<io::StampedFile> ReadCameraCsv(const std::filesystem::path& camera_dir) {
  const auto csv = camera_dir / "data.csv";
  std::vector<io::StampedFile> list;
  for (const io::TextLine& line : io::ReadTextLines(csv)) {
    const auto fields = io::SplitFields(line.text, ",");
    FLATSLAM_CHECK(fields.size() == 2, io::Where(csv, line.number), "expected 'timestamp_ns,filename', got '",
                   line.text, "'");
    list.push_back({io::ParseIntegerNs(fields[0], csv, line.number), camera_dir / "data" / fields[1]});
  }
  FLATSLAM_CHECK(!list.empty(), csv.string(), " lists no frames");
  std::stable_sort(list.begin(), list.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
  return list;
}

// state_groundtruth_estimate0/data.csv: "t_ns, px, py, pz, qw, qx, qy, qz, ..." (body in world).
Trajectory ReadAslGroundTruth(const std::filesystem::path& csv) {
  Trajectory trajectory;
  for (const io::TextLine& line : io::ReadTextLines(csv)) {
    const auto fields = io::SplitFields(line.text, ",");
    FLATSLAM_CHECK(fields.size() >= 8, io::Where(csv, line.number),
                   "expected 't_ns, px, py, pz, qw, qx, qy, qz, ...', got ", fields.size(), " fields");
    double v[7];
    for (int k = 0; k < 7; ++k) v[k] = io::ParseNumber(fields[k + 1], csv, line.number, "a pose value");
    const Eigen::Quaterniond q(v[3], v[4], v[5], v[6]);
    FLATSLAM_CHECK(q.norm() > 1e-9, io::Where(csv, line.number), "zero quaternion");
    TimedPose pose;
    pose.t_ns = io::ParseIntegerNs(fields[0], csv, line.number);
    pose.T_world_cam.linear() = q.normalized().toRotationMatrix();
    pose.T_world_cam.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
    trajectory.push_back(pose);
  }
  FLATSLAM_CHECK(!trajectory.empty(), csv.string(), " holds no poses");
  std::stable_sort(trajectory.begin(), trajectory.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
  return trajectory;
}

}  // namespace

EurocCameraModel ReadEurocSensorYaml(const std::filesystem::path& path) {
  const auto fields = ReadYamlSubset(path);
  if (const auto it = fields.find("camera_model"); it != fields.end()) {
    FLATSLAM_CHECK(it->second.text == "pinhole", io::Where(path, it->second.line), "camera_model '", it->second.text,
                   "' is not supported (pinhole only)");
  }
  const YamlField& model = Require(fields, "distortion_model", path);
  FLATSLAM_CHECK(model.text == "radial-tangential" || model.text == "radtan", io::Where(path, model.line),
                 "distortion_model '", model.text, "' is not supported (radial-tangential only)");
  EurocCameraModel camera;
  const auto intrinsics = NumberList(fields, "intrinsics", 4, path);
  camera.K = cv::Matx33d(intrinsics[0], 0, intrinsics[2], 0, intrinsics[1], intrinsics[3], 0, 0, 1);
  const auto distortion = NumberList(fields, "distortion_coefficients", 4, path);
  camera.distortion = cv::Vec4d(distortion[0], distortion[1], distortion[2], distortion[3]);
  const auto resolution = NumberList(fields, "resolution", 2, path);
  camera.resolution = cv::Size(static_cast<int>(resolution[0]), static_cast<int>(resolution[1]));
  FLATSLAM_CHECK(intrinsics[0] > 0 && intrinsics[1] > 0 && camera.resolution.area() > 0, path.string(),
                 ": intrinsics fu, fv and resolution must be positive");
  if (const auto it = fields.find("rate_hz"); it != fields.end()) {
    camera.rate_hz = io::ParseNumber(it->second.text, path, it->second.line, "rate_hz");
  }
  const auto t = NumberList(fields, "T_BS.data", 16, path);
  Eigen::Matrix4d m;
  for (int k = 0; k < 16; ++k) m(k / 4, k % 4) = t[k];
  FLATSLAM_CHECK(m.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1)), path.string(),
                 ": T_BS.data last row must be [0, 0, 0, 1]");
  const Eigen::Matrix3d rotation = m.topLeftCorner<3, 3>();
  FLATSLAM_CHECK(
      (rotation * rotation.transpose()).isApprox(Eigen::Matrix3d::Identity(), 1e-4) && rotation.determinant() > 0,
      path.string(), ": T_BS rotation is not a rotation");
  camera.T_body_sensor.linear() = Eigen::Quaterniond(rotation).normalized().toRotationMatrix();
  camera.T_body_sensor.translation() = m.topRightCorner<3, 1>();
  return camera;
}

EurocDataset::EurocDataset(const std::filesystem::path& sequence_dir, const EurocOptions& options) {
  FLATSLAM_CHECK(options.Check(), "EurocOptions: rectify_alpha must be in [0, 1], max_stereo_dt_ns >= 0");
  std::error_code ec;
  if (std::filesystem::is_directory(sequence_dir / "mav0", ec)) {
    dir_ = sequence_dir;
  } else if (io::FolderName(sequence_dir) == "mav0") {
    dir_ = std::filesystem::absolute(sequence_dir).lexically_normal();
    if (!dir_.has_filename()) dir_ = dir_.parent_path();
    dir_ = dir_.parent_path();
  } else {
    Fail("EuRoC sequence ", sequence_dir.string(), " has no mav0/ folder");
  }
  const auto mav0 = dir_ / "mav0";
  FLATSLAM_CHECK(std::filesystem::is_directory(mav0 / "cam0", ec), "EuRoC sequence ", dir_.string(),
                 " has no mav0/cam0/ folder");
  const bool has_right = std::filesystem::is_directory(mav0 / "cam1", ec);
  const std::string available = has_right ? "mono, stereo" : "mono (no mav0/cam1/)";
  const Sensor sensor = options.sensor.value_or(has_right ? Sensor::kStereo : Sensor::kMonocular);
  FLATSLAM_CHECK(sensor != Sensor::kRgbd, "EuRoC sequence ", dir_.string(), " has no RGB-D; available: ", available);
  FLATSLAM_CHECK(sensor != Sensor::kStereo || has_right, "stereo requested but ", (mav0 / "cam1").string(),
                 " is missing; available: ", available);
  const bool stereo = sensor == Sensor::kStereo;

  raw_.push_back(ReadEurocSensorYaml(mav0 / "cam0" / "sensor.yaml"));
  const auto left = ReadCameraCsv(mav0 / "cam0");
  if (stereo) {
    raw_.push_back(ReadEurocSensorYaml(mav0 / "cam1" / "sensor.yaml"));
    FLATSLAM_CHECK(raw_[1].resolution == raw_[0].resolution, (mav0 / "cam1" / "sensor.yaml").string(),
                   ": resolution differs from cam0's; stereo rectification needs equal sizes");
    const auto right = ReadCameraCsv(mav0 / "cam1");
    std::vector<int64_t> left_t, right_t;
    for (const auto& e : left) left_t.push_back(e.t_ns);
    for (const auto& e : right) right_t.push_back(e.t_ns);
    for (const auto& [i, j] : io::AssociateStamps(left_t, right_t, options.max_stereo_dt_ns + 1)) {
      frames_.push_back({left[i].t_ns, left[i].file, right[j].file});
    }
    unmatched_ = left.size() + right.size() - 2 * frames_.size();
    FLATSLAM_CHECK(!frames_.empty(), "no frame of ", (mav0 / "cam0" / "data.csv").string(), " has a partner in ",
                   (mav0 / "cam1" / "data.csv").string(), " within ", options.max_stereo_dt_ns, " ns");
  } else {
    for (const auto& e : left) frames_.push_back({e.t_ns, e.file, {}});
  }

  // Maps are computed once here; read() only remaps.
  const cv::Size size = raw_[0].resolution;
  const cv::Mat D0(raw_[0].distortion);
  maps_.resize(stereo ? 2 : 1);
  if (!options.undistort) {
    // Raw images: the calibration is cam0's raw K (and the cameras' distance as the baseline).
    rotation_.assign(maps_.size(), cv::Matx33d::eye());
    for (const EurocCameraModel& camera : raw_) {
      const cv::Matx33d& k = camera.K;
      projection_.emplace_back(k(0, 0), k(0, 1), k(0, 2), 0, k(1, 0), k(1, 1), k(1, 2), 0, 0, 0, 1, 0);
    }
    if (stereo) {
      calibration_.baseline_m = (raw_[1].T_body_sensor.inverse() * raw_[0].T_body_sensor).translation().norm();
    }
  } else if (stereo) {
    const Eigen::Isometry3d T_cam1_cam0 = raw_[1].T_body_sensor.inverse() * raw_[0].T_body_sensor;
    const cv::Mat D1(raw_[1].distortion);
    const StereoRectification rectified =
        RectifyStereo(raw_[0].K, D0, raw_[1].K, D1, size, T_cam1_cam0, options.rectify_alpha);
    rotation_ = {rectified.R_left, rectified.R_right};
    projection_ = {rectified.P_left, rectified.P_right};
    maps_[0] = RectifyMap(raw_[0].K, D0, rectified.R_left, rectified.P_left.get_minor<3, 3>(0, 0), size);
    maps_[1] = RectifyMap(raw_[1].K, D1, rectified.R_right, rectified.P_right.get_minor<3, 3>(0, 0), size);
    calibration_.baseline_m = rectified.baseline_m();
  } else {
    const cv::Matx33d k = UndistortedCameraMatrix(raw_[0].K, D0, size, options.rectify_alpha);
    rotation_ = {cv::Matx33d::eye()};
    projection_ = {cv::Matx34d(k(0, 0), k(0, 1), k(0, 2), 0, k(1, 0), k(1, 1), k(1, 2), 0, 0, 0, 1, 0)};
    maps_[0] = RectifyMap(raw_[0].K, D0, cv::Matx33d::eye(), k, size);
  }
  const cv::Matx34d& P = projection_[0];
  calibration_.sensor = sensor;
  calibration_.camera = {P(0, 0), P(1, 1), P(0, 2), P(1, 2), size.width, size.height};
  // The rectified frame is the raw cam0 frame rotated by R0: x_rect = R0 x_raw.
  calibration_.T_body_cam = raw_[0].T_body_sensor * RawFromRectified(rotation_[0]);
  std::vector<int64_t> stamps;
  for (const auto& f : frames_) stamps.push_back(f.t_ns);
  calibration_.frame_rate_hz = raw_[0].rate_hz > 0 ? raw_[0].rate_hz : io::MedianRateHz(stamps);

  const auto asl_gt = mav0 / "state_groundtruth_estimate0" / "data.csv";
  const auto tum_gt = dir_ / "groundtruth_tum.txt";
  Trajectory body;
  if (std::filesystem::is_regular_file(asl_gt, ec)) {
    ground_truth_file_ = asl_gt;
    body = ReadAslGroundTruth(asl_gt);
  } else if (std::filesystem::is_regular_file(tum_gt, ec)) {
    ground_truth_file_ = tum_gt;
    body = io::ReadTumPoseFile(tum_gt);
  }
  if (!ground_truth_file_.empty()) {
    Trajectory cam = io::PosesAtTimes(body, stamps);
    for (TimedPose& pose : cam) pose.T_world_cam = pose.T_world_cam * calibration_.T_body_cam;
    ground_truth_ = std::move(cam);
  }
}

std::string EurocDataset::name() const {
  std::string name = "EuRoC " + io::FolderName(dir_) + (calibration_.sensor == Sensor::kStereo ? " (stereo" : " (mono");
  if (unmatched_ > 0) name += ", " + std::to_string(unmatched_) + " unmatched frames dropped";
  return name + ")";
}

Frame EurocDataset::read(size_t i) const {
  FLATSLAM_CHECK(i < frames_.size(), "frame ", i, " out of range: ", name(), " has ", frames_.size(), " frames");
  const Entry& entry = frames_[i];
  Frame frame;
  frame.index = i;
  frame.t_ns = entry.t_ns;
  frame.left = maps_[0].Apply(ReadGrayImage(entry.left, raw_[0].resolution));
  if (calibration_.sensor == Sensor::kStereo) {
    frame.right = maps_[1].Apply(ReadGrayImage(entry.right, raw_[1].resolution));
  }
  return frame;
}

}  // namespace flatslam
