#include "io/orb_settings.h"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <initializer_list>
#include <map>
#include <numbers>
#include <set>
#include <string_view>
#include <system_error>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "core/error.h"
#include "io/image_io.h"
#include "io/rectify.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

constexpr std::array<const char*, 9> kCameraParameters = {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"};
constexpr std::array<const char*, 6> kBlockParameters = {"width", "height", "K", "D", "R", "P"};

// Keys read or deliberately ignored; anything else is an error.
bool IsKnownKey(const std::string& key) {
  static const std::set<std::string> known = [] {
    std::set<std::string> keys = {"File.version",
                                  "Camera.type",
                                  "Camera.width",
                                  "Camera.height",
                                  "Camera.newWidth",
                                  "Camera.newHeight",
                                  "Camera.fps",
                                  "Camera.RGB",
                                  "Camera.bf",
                                  "Camera.bFishEye",
                                  "Camera.imageScale",
                                  "ThDepth",
                                  "Stereo.ThDepth",
                                  "Stereo.b",
                                  "Stereo.T_c1_c2",
                                  "DepthMapFactor",
                                  "RGBD.DepthMapFactor",
                                  "ORBextractor.nFeatures",
                                  "ORBextractor.scaleFactor",
                                  "ORBextractor.nLevels",
                                  "ORBextractor.iniThFAST",
                                  "ORBextractor.minThFAST",
                                  "Tbc"};
    for (const char* camera : {"Camera.", "Camera1.", "Camera2."})
      for (const char* p : kCameraParameters) keys.insert(std::string(camera) + p);
    for (const char* block : {"LEFT.", "RIGHT."})
      for (const char* p : kBlockParameters) keys.insert(std::string(block) + p);
    return keys;
  }();
  for (const char* ignored : {"Viewer.", "IMU.", "System."})
    if (key.rfind(ignored, 0) == 0) return true;
  return known.count(key) > 0;
}

std::string FormatNumber(double value) {
  char buffer[64];
  const auto [end, ec] = std::to_chars(buffer, buffer + sizeof(buffer), value);
  return ec == std::errc() ? std::string(buffer, end) : std::to_string(value);
}

// Seven significant digits, for values computed from the file (a quotient prints as 0.12, not 0.12000000000000001).
std::string RoundedNumber(double value) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%.7g", value);
  return buffer;
}

// Two values of one quantity agree to 1e-4 relative (files round differently, Stereo.T_c1_c2 is float).
bool Agree(double a, double b) {
  return std::abs(a - b) <= 1e-4 * std::max({std::abs(a), std::abs(b), 1e-5});
}

bool IsRotation(const Eigen::Matrix3d& r) {
  return (r * r.transpose()).isApprox(Eigen::Matrix3d::Identity(), 1e-4) && r.determinant() > 0;
}

// What OpenCV's YAML parser found wrong, with the line: its parse errors carry
// "FILE(LINE): REASON" where an exception's function name goes, and the parser's function name
// as the error text ("skipSpaces").
std::string ParseProblem(const cv::Exception& e) {
  const std::string& where = e.func;
  const size_t close = where.find("): ");
  const size_t open = close == std::string::npos ? std::string::npos : where.rfind('(', close);
  if (open != std::string::npos) {
    const std::string line = where.substr(open + 1, close - open - 1);
    if (!line.empty() && std::all_of(line.begin(), line.end(), [](char c) { return c >= '0' && c <= '9'; }))
      return "line " + line + ": " + where.substr(close + 3);
  }
  return e.err.empty() ? e.what() : e.err;
}

// The keys of one settings file with checked, typed access; errors name the file and the key.
class SettingsFile {
 public:
  explicit SettingsFile(const fs::path& path) : path_(path) {
    std::error_code ec;
    FLATSLAM_CHECK(fs::is_regular_file(path, ec), "settings file not found: ", path.string());
    std::ifstream in(path);
    std::string first;
    std::getline(in, first);
    FLATSLAM_CHECK(first.rfind("%YAML", 0) == 0, "settings file ", path.string(),
                   " is not an OpenCV YAML file: its first line must be '%YAML:1.0' (an ORB-SLAM2/3 settings file)");
    try {
      storage_.open(path.string(), cv::FileStorage::READ);
    } catch (const cv::Exception& e) {
      Fail("cannot parse settings file ", path.string(), ": ", ParseProblem(e));
    }
    FLATSLAM_CHECK(storage_.isOpened(), "cannot open settings file ", path.string());
    const cv::FileNode root = storage_.root();
    FLATSLAM_CHECK(root.isMap(), "settings file ", path.string(), " holds no 'key: value' lines");
    for (auto it = root.begin(); it != root.end(); ++it) {
      const cv::FileNode node = *it;
      Check(nodes_.emplace(node.name(), node).second, "key '", node.name(), "' appears twice");
    }
  }

  [[nodiscard]] const fs::path& path() const { return path_; }
  [[nodiscard]] bool has(const std::string& key) const { return nodes_.count(key) > 0; }
  [[nodiscard]] std::vector<std::string> keys() const {
    std::vector<std::string> out;
    for (const auto& [key, node] : nodes_) out.push_back(key);
    return out;
  }

  template <class... Args>
  [[noreturn]] void Error(Args&&... args) const {
    Fail("settings file ", path_.string(), ": ", std::forward<Args>(args)...);
  }
  template <class... Args>
  void Check(bool condition, Args&&... args) const {
    if (!condition) Error(std::forward<Args>(args)...);
  }

  [[nodiscard]] std::optional<double> Number(const std::string& key) const {
    const cv::FileNode* node = Find(key);
    if (!node) return std::nullopt;
    Check(node->isInt() || node->isReal(), "'", key, "' must be a number");
    const double value = node->real();
    Check(std::isfinite(value), "'", key, "' must be a finite number");
    return value;
  }

  [[nodiscard]] std::optional<int> Integer(const std::string& key) const {
    const auto value = Number(key);
    if (!value) return std::nullopt;
    Check(*value == std::floor(*value) && std::abs(*value) < 1e9, "'", key, "' must be an integer, got ",
          FormatNumber(*value));
    return static_cast<int>(*value);
  }

  [[nodiscard]] std::optional<std::string> Text(const std::string& key) const {
    const cv::FileNode* node = Find(key);
    if (!node) return std::nullopt;
    if (node->isInt() || node->isReal()) return FormatNumber(node->real());
    Check(node->isString(), "'", key, "' must be a string");
    return node->string();
  }

  // An !!opencv-matrix as CV_64F; shape: rows x cols, or (vector_lengths set) 1 x n or n x 1 with
  // n one of vector_lengths, returned as 1 x n.
  [[nodiscard]] std::optional<cv::Mat> Matrix(const std::string& key, int rows, int cols,
                                              std::initializer_list<int> vector_lengths = {}) const {
    const cv::FileNode* node = Find(key);
    if (!node) return std::nullopt;
    cv::Mat m;
    try {
      if (node->isMap()) *node >> m;
    } catch (const cv::Exception&) {
      m.release();
    }
    Check(!m.empty() && m.channels() == 1, "'", key, "' must be an !!opencv-matrix (rows, cols, dt, data)");
    const int n = static_cast<int>(m.total());
    const bool vector = vector_lengths.size() > 0;
    const bool shape = vector
                           ? (m.rows == 1 || m.cols == 1) && std::count(vector_lengths.begin(), vector_lengths.end(), n)
                           : m.rows == rows && m.cols == cols;
    Check(shape, "'", key, "' must be a ", rows, "x", cols, " matrix, got ", m.rows, "x", m.cols);
    m.convertTo(m, CV_64F);
    for (int r = 0; r < m.rows; ++r)
      for (int c = 0; c < m.cols; ++c) Check(std::isfinite(m.at<double>(r, c)), "'", key, "' holds a non-finite value");
    return vector ? m.reshape(1, 1) : m;
  }

  // One quantity under two names (ORB-SLAM2's and ORB-SLAM3's): both given must agree.
  [[nodiscard]] std::optional<double> Either(const std::string& a, const std::string& b) const {
    const auto va = Number(a), vb = Number(b);
    if (va && vb) {
      Check(Agree(*va, *vb), "'", a, "' (", FormatNumber(*va), ") and '", b, "' (", FormatNumber(*vb),
            ") disagree; give one, or the same value");
    }
    return va ? va : vb;
  }
  // Name of whichever of a, b is given (for messages).
  [[nodiscard]] std::string Given(const std::string& a, const std::string& b) const { return has(a) ? a : b; }

 private:
  [[nodiscard]] const cv::FileNode* Find(const std::string& key) const {
    const auto it = nodes_.find(key);
    return it == nodes_.end() ? nullptr : &it->second;
  }

  fs::path path_;
  cv::FileStorage storage_;  // owns what the nodes point into
  std::map<std::string, cv::FileNode> nodes_;
};

const char* const kFisheye =
    "the fisheye (Kannala-Brandt) camera model is not supported: flatslam reads pinhole cameras with "
    "radial-tangential distortion (undistort the images, or use a PinHole calibration)";

// Camera.* / Camera1.* (or Camera2.*): intrinsics required, distortion optional.
SettingsCamera ReadCamera(const SettingsFile& file, const std::string& orb2, const std::string& orb3) {
  SettingsCamera camera;
  std::array<double, 9> values{};
  for (size_t k = 0; k < kCameraParameters.size(); ++k) {
    const std::string a = orb2.empty() ? "" : orb2 + kCameraParameters[k], b = orb3 + kCameraParameters[k];
    const auto value = a.empty() ? file.Number(b) : file.Either(a, b);
    if (k < 4) {
      file.Check(value.has_value(), "missing key '", a.empty() ? b : a, "'",
                 a.empty() ? std::string() : " (ORB-SLAM3: '" + b + "')");
    }
    values[k] = value.value_or(0);
  }
  camera.fx = values[0];
  camera.fy = values[1];
  camera.cx = values[2];
  camera.cy = values[3];
  std::copy(values.begin() + 4, values.end(), camera.distortion.begin());
  for (size_t k = 0; k < 2; ++k) {
    const std::string name = kCameraParameters[k];
    const std::string key = orb2.empty() ? orb3 + name : file.Given(orb2 + name, orb3 + name);
    file.Check(values[k] > 0, "focal length '", key, "' must be positive, got ", FormatNumber(values[k]));
  }
  return camera;
}

std::optional<RectificationBlock> ReadBlock(const SettingsFile& file, const std::string& name) {
  bool any = false;
  for (const char* p : kBlockParameters) any = any || file.has(name + "." + p);
  if (!any) return std::nullopt;
  for (const char* p : kBlockParameters) {
    file.Check(file.has(name + "." + p), "rectification block ", name, ".* lacks '", name, ".", p,
               "' (it needs width, height, K, D, R and P)");
  }
  RectificationBlock block;
  block.size = cv::Size(*file.Integer(name + ".width"), *file.Integer(name + ".height"));
  file.Check(block.size.width > 0 && block.size.height > 0, "'", name, ".width' and '", name,
             ".height' must be positive");
  block.K = cv::Matx33d(*file.Matrix(name + ".K", 3, 3));
  block.D = *file.Matrix(name + ".D", 1, 5, {4, 5});  // k1 k2 p1 p2 [k3]
  block.R = cv::Matx33d(*file.Matrix(name + ".R", 3, 3));
  block.P = cv::Matx34d(*file.Matrix(name + ".P", 3, 4));
  file.Check(block.K(0, 0) > 0 && block.K(1, 1) > 0, "focal lengths of '", name, ".K' must be positive");
  file.Check(block.P(0, 0) > 0 && block.P(1, 1) > 0, "focal lengths of '", name, ".P' must be positive");
  Eigen::Matrix3d r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r(i, j) = block.R(i, j);
  file.Check(IsRotation(r), "'", name, ".R' is not a rotation matrix");
  return block;
}

}  // namespace

bool SettingsCamera::distorted() const {
  return std::any_of(distortion.begin(), distortion.end(), [](double d) { return d != 0; });
}

cv::Mat SettingsCamera::distortion_mat() const {
  cv::Mat d(1, 5, CV_64F);
  for (int k = 0; k < 5; ++k) d.at<double>(0, k) = distortion[k];
  return d;
}

PinholeCamera OrbSettings::raw_camera() const {
  if (left_block) {
    const cv::Matx33d& k = left_block->K;
    return {k(0, 0), k(1, 1), k(0, 2), k(1, 2), left_block->size.width, left_block->size.height};
  }
  return {camera.fx, camera.fy, camera.cx, camera.cy, size.width, size.height};
}

OrbSettings ReadOrbSettings(const fs::path& path) {
  const SettingsFile file(path);
  OrbSettings settings;
  settings.file = path;

  if (const auto version = file.Text("File.version")) {
    file.Check(*version == "1.0" || *version == "1", "'File.version' ", *version,
               " is not supported (\"1.0\" is ORB-SLAM3's format; ORB-SLAM2 files have no version)");
    settings.orb_slam_version = 3;
  }
  // The camera model first: a fisheye file fails on that, not on its fisheye-only keys.
  const std::string type = file.Text("Camera.type").value_or("PinHole");
  file.Check(type != "KannalaBrandt8", "'Camera.type' is KannalaBrandt8: ", kFisheye);
  file.Check(type == "PinHole" || type == "Rectified", "'Camera.type' ", type,
             " is not supported (PinHole or Rectified)");
  file.Check(file.Number("Camera.bFishEye").value_or(0) == 0, "'Camera.bFishEye' is set: ", kFisheye);
  for (const char* camera : {"Camera.k4", "Camera1.k4", "Camera2.k4"})
    file.Check(!file.has(camera), "'", camera, "' is a fisheye coefficient: ", kFisheye);

  std::vector<std::string> unknown;
  for (const std::string& key : file.keys())
    if (!IsKnownKey(key)) unknown.push_back("'" + key + "'");
  if (!unknown.empty()) {
    std::string list;
    for (const std::string& key : unknown) list += (list.empty() ? "" : ", ") + key;
    file.Error("unknown key", unknown.size() > 1 ? "s " : " ", list,
               " (not one of the ORB-SLAM2/3 settings flatslam reads, listed in src/io/orb_settings.h)");
  }

  const double scale = file.Number("Camera.imageScale").value_or(1);
  file.Check(scale == 1, "'Camera.imageScale' ", FormatNumber(scale),
             " asks to resize the images; resizing is not supported (resize them beforehand and scale the camera)");

  settings.camera = ReadCamera(file, "Camera.", "Camera1.");
  if (type == "Rectified") {
    for (size_t k = 4; k < kCameraParameters.size(); ++k) {
      const std::string key =
          file.Given(std::string("Camera.") + kCameraParameters[k], std::string("Camera1.") + kCameraParameters[k]);
      file.Check(settings.camera.distortion[k - 4] == 0, "'Camera.type' Rectified takes no distortion, but '", key,
                 "' is ", FormatNumber(settings.camera.distortion[k - 4]));
    }
  }

  const auto width = file.Integer("Camera.width"), height = file.Integer("Camera.height");
  file.Check(width.has_value() == height.has_value(), "'Camera.width' and 'Camera.height' go together");
  if (width) {
    file.Check(*width > 0 && *height > 0, "'Camera.width' and 'Camera.height' must be positive");
    settings.size = cv::Size(*width, *height);
  }
  const auto new_width = file.Integer("Camera.newWidth"), new_height = file.Integer("Camera.newHeight");
  if (new_width || new_height) {
    const cv::Size resized(new_width.value_or(settings.size.width), new_height.value_or(settings.size.height));
    file.Check(resized == settings.size, "'Camera.newWidth' / 'Camera.newHeight' ask to resize the images to ",
               io::SizeText(resized), "; resizing is not supported (resize them beforehand and scale the camera)");
  }

  // ORB-SLAM2 rectification blocks: the camera is LEFT.P, the rectified one.
  settings.left_block = ReadBlock(file, "LEFT");
  settings.right_block = ReadBlock(file, "RIGHT");
  file.Check(settings.left_block.has_value() == settings.right_block.has_value(),
             settings.left_block ? "LEFT.* rectification block without RIGHT.*"
                                 : "RIGHT.* rectification block without LEFT.*");
  // Baselines from every key that gives one; they must agree.
  std::vector<std::pair<std::string, double>> baselines;
  if (settings.left_block) {
    const RectificationBlock& left = *settings.left_block;
    const RectificationBlock& right = *settings.right_block;
    for (size_t k = 4; k < kCameraParameters.size(); ++k) {
      const std::string key =
          file.Given(std::string("Camera.") + kCameraParameters[k], std::string("Camera1.") + kCameraParameters[k]);
      file.Check(settings.camera.distortion[k - 4] == 0, "'", key,
                 "' must be 0 with LEFT/RIGHT rectification blocks: the rectified images have no distortion "
                 "(the raw cameras' distortion is LEFT.D and RIGHT.D)");
    }
    const std::array<std::pair<const char*, double>, 4> rectified = {
        {{"fx", left.P(0, 0)}, {"fy", left.P(1, 1)}, {"cx", left.P(0, 2)}, {"cy", left.P(1, 2)}}};
    const std::array<double, 4> given = {settings.camera.fx, settings.camera.fy, settings.camera.cx,
                                         settings.camera.cy};
    for (size_t k = 0; k < rectified.size(); ++k) {
      const std::string key =
          file.Given(std::string("Camera.") + rectified[k].first, std::string("Camera1.") + rectified[k].first);
      file.Check(Agree(given[k], rectified[k].second), "'", key, "' (", FormatNumber(given[k]), ") and 'LEFT.P' ",
                 rectified[k].first, " (", FormatNumber(rectified[k].second),
                 ") disagree: with LEFT/RIGHT blocks the camera is the rectified one, LEFT.P");
    }
    file.Check(Agree(left.P(0, 0), right.P(0, 0)) && Agree(left.P(1, 1), right.P(1, 1)) &&
                   Agree(left.P(0, 2), right.P(0, 2)) && Agree(left.P(1, 2), right.P(1, 2)),
               "'LEFT.P' and 'RIGHT.P' give different rectified intrinsics; a rectified pair shares one camera");
    file.Check(right.P(0, 3) < 0, "'RIGHT.P'[0][3] must be -fx times the baseline (negative), got ",
               FormatNumber(right.P(0, 3)));
    file.Check(left.size == right.size, "'LEFT.width x LEFT.height' (", io::SizeText(left.size),
               ") and 'RIGHT.width x RIGHT.height' (", io::SizeText(right.size), ") differ");
    if (width) {
      file.Check(left.size == settings.size, "'Camera.width x Camera.height' (", io::SizeText(settings.size),
                 ") and 'LEFT.width x LEFT.height' (", io::SizeText(left.size), ") disagree");
    }
    settings.size = left.size;
    settings.camera = {left.P(0, 0), left.P(1, 1), left.P(0, 2), left.P(1, 2), {}};
    baselines.emplace_back("RIGHT.P", -right.P(0, 3) / right.P(0, 0));
  }

  // ORB-SLAM3 stereo: Camera2.* and the pose of camera 2 in camera 1.
  bool any_camera2 = false;
  for (const char* p : kCameraParameters) any_camera2 = any_camera2 || file.has(std::string("Camera2.") + p);
  if (any_camera2) {
    file.Check(!settings.left_block, "'Camera2.*' and the LEFT/RIGHT blocks both describe the right camera; keep one");
    file.Check(type != "Rectified", "'Camera.type' Rectified takes no 'Camera2.*' (a rectified pair shares Camera1)");
    settings.right_camera = ReadCamera(file, "", "Camera2.");
  }
  if (const auto t = file.Matrix("Stereo.T_c1_c2", 4, 4)) {
    Eigen::Matrix4d m;
    for (int r = 0; r < 4; ++r)
      for (int c = 0; c < 4; ++c) m(r, c) = t->at<double>(r, c);
    file.Check(m.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1), 1e-6),
               "'Stereo.T_c1_c2' last row must be [0, 0, 0, 1]");
    file.Check(IsRotation(m.topLeftCorner<3, 3>()), "'Stereo.T_c1_c2' rotation is not a rotation matrix");
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::Quaterniond(Eigen::Matrix3d(m.topLeftCorner<3, 3>())).normalized().toRotationMatrix();
    T.translation() = m.topRightCorner<3, 1>();
    const double length = T.translation().norm();
    file.Check(length > 0, "'Stereo.T_c1_c2' puts both cameras at one place (zero baseline)");
    if (!settings.right_camera) {
      // No second camera to rectify with: the pair must already be rectified (camera 2 on camera 1's x axis).
      const double angle_deg = Eigen::AngleAxisd(T.linear()).angle() * 180 / std::numbers::pi;
      file.Check(angle_deg < 0.01 && T.translation().x() > 0.999 * length,
                 "'Stereo.T_c1_c2' is not a rectified pair (rotated ", FormatNumber(angle_deg),
                 " deg, or camera 2 not along camera 1's +x axis) and no 'Camera2.*' is given to rectify it");
    }
    file.Check(!settings.left_block,
               "'Stereo.T_c1_c2' and the LEFT/RIGHT blocks both give the stereo geometry; keep one");
    settings.T_left_right = T;
    baselines.emplace_back("Stereo.T_c1_c2", length);
  } else {
    file.Check(!settings.right_camera,
               "'Camera2.*' (a second camera) needs 'Stereo.T_c1_c2', the pose of camera 2 "
               "in camera 1");
  }
  if (const auto bf = file.Number("Camera.bf")) {
    file.Check(*bf > 0, "'Camera.bf' (fx times the baseline) must be positive, got ", FormatNumber(*bf));
    baselines.emplace_back("Camera.bf / fx", *bf / settings.camera.fx);
  }
  if (const auto b = file.Number("Stereo.b")) {
    file.Check(*b > 0, "'Stereo.b' (the baseline in metres) must be positive, got ", FormatNumber(*b));
    baselines.emplace_back("Stereo.b", *b);
  }
  for (size_t k = 1; k < baselines.size(); ++k) {
    file.Check(Agree(baselines[0].second, baselines[k].second), "the stereo baseline from '", baselines[0].first, "' (",
               RoundedNumber(baselines[0].second), " m) and from '", baselines[k].first, "' (",
               RoundedNumber(baselines[k].second), " m) disagree");
  }
  if (!baselines.empty()) settings.baseline_m = baselines[0].second;

  settings.frame_rate_hz = file.Number("Camera.fps").value_or(0);
  file.Check(settings.frame_rate_hz >= 0, "'Camera.fps' must not be negative");
  const int rgb = file.Integer("Camera.RGB").value_or(0);
  file.Check(rgb == 0 || rgb == 1, "'Camera.RGB' must be 0 (BGR) or 1 (RGB), got ", rgb);
  settings.rgb = rgb == 1;
  if (const auto factor = file.Either("DepthMapFactor", "RGBD.DepthMapFactor")) {
    file.Check(*factor > 0, "'", file.Given("DepthMapFactor", "RGBD.DepthMapFactor"),
               "' (raw depth units per metre) must be positive, got ", FormatNumber(*factor));
    settings.depth_map_factor = *factor;
  }

  // SLAM options, checked here so the message names the settings key.
  auto& options = settings.slam_options;
  if (const auto features = file.Integer("ORBextractor.nFeatures")) {
    file.Check(*features > 0, "'ORBextractor.nFeatures' must be positive");
    options.emplace_back("orb.features", std::to_string(*features));
  }
  if (const auto factor = file.Number("ORBextractor.scaleFactor")) {
    file.Check(*factor > 1, "'ORBextractor.scaleFactor' must be above 1, got ", FormatNumber(*factor));
    options.emplace_back("orb.scale_factor", FormatNumber(*factor));
  }
  if (const auto levels = file.Integer("ORBextractor.nLevels")) {
    file.Check(*levels >= 1, "'ORBextractor.nLevels' must be at least 1");
    options.emplace_back("orb.levels", std::to_string(*levels));
  }
  const auto initial = file.Integer("ORBextractor.iniThFAST"), minimum = file.Integer("ORBextractor.minThFAST");
  if (initial) {
    file.Check(*initial > 0 && *initial < 256, "'ORBextractor.iniThFAST' must be in 1..255, got ", *initial);
    options.emplace_back("orb.fast_threshold", std::to_string(*initial));
  }
  if (minimum) {
    file.Check(*minimum > 0 && *minimum <= initial.value_or(*minimum), "'ORBextractor.minThFAST' must be in 1..",
               initial ? "'ORBextractor.iniThFAST'" : "255", ", got ", *minimum);
    options.emplace_back("orb.min_fast_threshold", std::to_string(*minimum));
  }
  if (const auto th_depth = file.Either("ThDepth", "Stereo.ThDepth")) {
    file.Check(*th_depth > 0, "'", file.Given("ThDepth", "Stereo.ThDepth"), "' (in baselines) must be positive");
    options.emplace_back("close_depth_baselines", FormatNumber(*th_depth));
  }
  return settings;
}

std::vector<std::pair<std::string, std::string>> SettingsSlamOptions(const OrbSettings& settings, Sensor sensor) {
  auto options = settings.slam_options;
  if (sensor == Sensor::kRgbd && settings.baseline_m > 0)
    options.emplace_back("rgbd_virtual_baseline_m", FormatNumber(settings.baseline_m));
  return options;
}

namespace {

PinholeCamera CameraOf(const cv::Matx33d& k, cv::Size size) {
  return {k(0, 0), k(1, 1), k(0, 2), k(1, 2), size.width, size.height};
}

cv::Matx33d MatrixOf(const PinholeCamera& c) { return {c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1}; }

// The camera a single (not stereo) settings camera's images are undistorted to: every pixel valid
// (alpha 0), or the camera itself when it has no distortion.
PinholeCamera UndistortedCamera(const SettingsCamera& camera, cv::Size size) {
  if (!camera.distorted()) return CameraOf(camera.K(), size);
  return CameraOf(UndistortedCameraMatrix(camera.K(), camera.distortion_mat(), size, 0), size);
}

// The settings camera ApplyCameraRefit sees a dataset's images through.
SettingsCamera RefitLens(const PinholeCamera& given, const CameraRefit& refit) {
  SettingsCamera lens;
  lens.fx = given.fx * refit.focal_scale;
  lens.fy = given.fy * refit.focal_scale;
  lens.cx = given.cx;
  lens.cy = given.cy;
  lens.distortion[0] = refit.k1;
  return lens;
}

// A dataset delivering raw images, seen through a settings file's calibration.
class SettingsDataset final : public Dataset {
 public:
  SettingsDataset(std::unique_ptr<Dataset> raw, std::shared_ptr<const OrbSettings> settings)
      : raw_(std::move(raw)), settings_(std::move(settings)) {
    const OrbSettings& s = *settings_;
    const std::string file = s.file.string();
    const Calibration& inner = raw_->calibration();
    const cv::Size size(inner.camera.width, inner.camera.height);
    const cv::Size expected = s.left_block ? s.left_block->size : s.size;
    FLATSLAM_CHECK(expected.empty() || expected == size, "settings file ", file, ": ",
                   s.left_block ? "LEFT.width x LEFT.height" : "Camera.width x Camera.height", " is ",
                   io::SizeText(expected), " but the images of ", raw_->name(), " are ", io::SizeText(size));
    const bool stereo = inner.sensor == Sensor::kStereo;
    FLATSLAM_CHECK(!stereo || s.baseline_m > 0, "settings file ", file,
                   " gives no stereo baseline ('Camera.bf', 'Stereo.b', 'Stereo.T_c1_c2' or LEFT/RIGHT blocks) but ",
                   raw_->name(), " is read as stereo: add the baseline, or read it as monocular");

    calibration_ = inner;
    calibration_.baseline_m = stereo ? s.baseline_m : 0;
    if (s.frame_rate_hz > 0) calibration_.frame_rate_hz = s.frame_rate_hz;
    cv::Matx33d R_left = cv::Matx33d::eye();
    if (s.left_block) {
      const RectificationBlock& left = *s.left_block;
      const RectificationBlock& right = *s.right_block;
      left_map_ = RectifyMap(left.K, left.D, left.R, left.P.get_minor<3, 3>(0, 0), size);
      if (stereo) right_map_ = RectifyMap(right.K, right.D, right.R, right.P.get_minor<3, 3>(0, 0), size);
      R_left = left.R;
      calibration_.camera = CameraOf(left.P.get_minor<3, 3>(0, 0), size);
    } else if (stereo && s.right_camera) {
      const SettingsCamera& right = *s.right_camera;
      const StereoRectification rectified = RectifyStereo(s.camera.K(), s.camera.distortion_mat(), right.K(),
                                                          right.distortion_mat(), size, s.T_left_right->inverse(), 0);
      left_map_ = RectifyMap(s.camera.K(), s.camera.distortion_mat(), rectified.R_left,
                             rectified.P_left.get_minor<3, 3>(0, 0), size);
      right_map_ = RectifyMap(right.K(), right.distortion_mat(), rectified.R_right,
                              rectified.P_right.get_minor<3, 3>(0, 0), size);
      R_left = rectified.R_left;
      calibration_.camera = CameraOf(rectified.P_left.get_minor<3, 3>(0, 0), size);
      calibration_.baseline_m = rectified.baseline_m();
    } else if (s.camera.distorted()) {
      FLATSLAM_CHECK(!stereo, "settings file ", file,
                     ": distortion (Camera.k1 ...) on a stereo pair needs its rectification: LEFT/RIGHT blocks "
                     "(ORB-SLAM2) or Camera2.* with Stereo.T_c1_c2 (ORB-SLAM3)");
      calibration_.camera = UndistortedCamera(s.camera, size);
      left_map_ = RectifyMap(s.camera.K(), s.camera.distortion_mat(), cv::Matx33d::eye(),
                             MatrixOf(calibration_.camera), size);
    } else {
      calibration_.camera = UndistortedCamera(s.camera, size);
    }
    // The rectified left camera is the raw one rotated by R_left; poses follow it.
    const Eigen::Isometry3d T_raw_rect = RawFromRectified(R_left);
    calibration_.T_body_cam = inner.T_body_cam * T_raw_rect;
    if (auto truth = raw_->ground_truth()) {
      for (TimedPose& pose : *truth) pose.T_world_cam = pose.T_world_cam * T_raw_rect;
      ground_truth_ = std::move(truth);
    }
  }

  [[nodiscard]] std::string name() const override {
    return raw_->name() + ", calibration from " + settings_->file.filename().string();
  }
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return raw_->size(); }
  [[nodiscard]] Frame read(size_t i) const override {
    Frame frame = raw_->read(i);
    frame.left = left_map_.Apply(frame.left);
    if (!frame.right.empty()) frame.right = right_map_.Apply(frame.right);
    if (!frame.depth.empty()) frame.depth = left_map_.Apply(frame.depth, Interpolation::kNearest);
    return frame;
  }
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return ground_truth_; }

 private:
  std::unique_ptr<Dataset> raw_;
  std::shared_ptr<const OrbSettings> settings_;
  Calibration calibration_;
  RectifyMap left_map_, right_map_;  // empty: the images pass unchanged
  std::optional<Trajectory> ground_truth_;
};

// A monocular dataset seen through a refined camera: the images pass unchanged, each with the
// lens that moves its keypoints into the refined camera (Frame::lens).
class RefitDataset final : public Dataset {
 public:
  RefitDataset(std::unique_ptr<Dataset> given, std::shared_ptr<const RefinedCamera> lens)
      : given_(std::move(given)), lens_(std::move(lens)), calibration_(given_->calibration()) {
    calibration_.camera = lens_->camera();
  }

  [[nodiscard]] std::string name() const override {
    return given_->name() + ", calibration from the camera its map refined";
  }
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return given_->size(); }
  [[nodiscard]] Frame read(size_t i) const override {
    Frame frame = given_->read(i);
    // Refinements compose into one of the given camera (ThenRefit), never one onto another.
    FLATSLAM_CHECK(!frame.lens, given_->name(), " already delivers frames through a refined camera");
    frame.lens = lens_;
    return frame;
  }
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return given_->ground_truth(); }

 private:
  std::unique_ptr<Dataset> given_;
  std::shared_ptr<const RefinedCamera> lens_;
  Calibration calibration_;
};

}  // namespace

std::unique_ptr<Dataset> ApplyOrbSettings(std::unique_ptr<Dataset> raw, std::shared_ptr<const OrbSettings> settings) {
  FLATSLAM_CHECK(raw && settings, "ApplyOrbSettings: null dataset or settings");
  return std::make_unique<SettingsDataset>(std::move(raw), std::move(settings));
}

std::unique_ptr<Dataset> ApplyCameraRefit(std::unique_ptr<Dataset> dataset, const CameraRefit& refit) {
  FLATSLAM_CHECK(dataset, "ApplyCameraRefit: null dataset");
  auto lens = std::make_shared<const RefinedCamera>(dataset->calibration().camera, refit);
  return ApplyCameraRefit(std::move(dataset), std::move(lens));
}

std::unique_ptr<Dataset> ApplyCameraRefit(std::unique_ptr<Dataset> dataset, std::shared_ptr<const RefinedCamera> lens) {
  FLATSLAM_CHECK(dataset && lens, "ApplyCameraRefit: null dataset or lens");
  const Calibration& given = dataset->calibration();
  FLATSLAM_CHECK(given.sensor == Sensor::kMonocular, "a refined camera applies to monocular datasets; ",
                 dataset->name(), " is read as ", given.sensor == Sensor::kStereo ? "stereo" : "RGB-D");
  return std::make_unique<RefitDataset>(std::move(dataset), std::move(lens));
}

RefinedCamera::RefinedCamera(const PinholeCamera& given, const CameraRefit& refit)
    : lens_(RefitLens(given, refit)), camera_(UndistortedCamera(lens_, cv::Size(given.width, given.height))) {}

std::vector<Eigen::Vector2d> RefinedCamera::ToGiven(std::span<const Eigen::Vector2d> p) const {
  // RectifyMap's undistortion samples the given image where the lens distorts the normalized ray
  // of a refined pixel: the same forward model here.
  std::vector<cv::Point3d> rays;
  rays.reserve(p.size());
  for (const Eigen::Vector2d& x : p)
    rays.emplace_back((x.x() - camera_.cx) / camera_.fx, (x.y() - camera_.cy) / camera_.fy, 1.0);
  std::vector<cv::Point2d> q;
  if (!rays.empty())
    cv::projectPoints(rays, cv::Vec3d::zeros(), cv::Vec3d::zeros(), lens_.K(), lens_.distortion_mat(), q);
  std::vector<Eigen::Vector2d> out;
  out.reserve(q.size());
  for (const cv::Point2d& x : q) out.emplace_back(x.x, x.y);
  return out;
}

std::vector<Eigen::Vector2d> RefinedCamera::FromGiven(std::span<const Eigen::Vector2d> q) const {
  std::vector<cv::Point2d> given;
  given.reserve(q.size());
  for (const Eigen::Vector2d& x : q) given.emplace_back(x.x(), x.y());
  std::vector<cv::Point2d> p;
  if (!given.empty())
    cv::undistortPoints(given, p, lens_.K(), lens_.distortion_mat(), cv::noArray(), MatrixOf(camera_),
                        cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 50, 1e-12));
  std::vector<Eigen::Vector2d> out;
  out.reserve(p.size());
  for (const cv::Point2d& x : p) out.emplace_back(x.x, x.y);
  return out;
}

std::vector<Eigen::Vector2d> Reexpress(const RefinedCamera& from, const RefinedCamera& to,
                                       std::span<const Eigen::Vector2d> p) {
  return to.FromGiven(from.ToGiven(p));
}

}  // namespace flatslam
