#include "io/image_folder.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <system_error>
#include <utility>

#include "core/error.h"
#include "io/tum.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

// Subfolder pairs of a stereo layout, in the order they are looked for.
constexpr std::array<std::pair<const char*, const char*>, 3> kStereoFolders = {
    {{"left", "right"}, {"image_0", "image_1"}, {"cam0", "cam1"}}};

bool IsImageFile(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext == ".png" || ext == ".jpg" || ext == ".jpeg";
}

// "123", "1305031102.175304": digits with at most one decimal point.
bool IsPlainNumber(const std::string& text) {
  bool digit = false, point = false;
  for (const char c : text) {
    if (std::isdigit(static_cast<unsigned char>(c))) {
      digit = true;
    } else if (c == '.' && !point) {
      point = true;
    } else {
      return false;
    }
  }
  return digit;
}

// Image files directly in `dir`, sorted by name, or by value when every name is a number.
std::vector<fs::path> ListImages(const fs::path& dir) {
  std::vector<fs::path> files;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.is_regular_file(ec) && IsImageFile(entry.path())) files.push_back(entry.path());
  }
  const bool numeric =
      std::all_of(files.begin(), files.end(), [](const fs::path& f) { return IsPlainNumber(f.stem().string()); });
  std::sort(files.begin(), files.end(), [numeric](const fs::path& a, const fs::path& b) {
    if (numeric) {
      const double va = std::strtod(a.stem().c_str(), nullptr), vb = std::strtod(b.stem().c_str(), nullptr);
      if (va != vb) return va < vb;
    }
    return a.filename() < b.filename();
  });
  return files;
}

std::optional<std::pair<std::string, std::string>> FindStereoFolders(const fs::path& dir) {
  std::error_code ec;
  for (const auto& [left, right] : kStereoFolders) {
    if (fs::is_directory(dir / left, ec) && fs::is_directory(dir / right, ec)) return std::pair(left, right);
  }
  return std::nullopt;
}

bool HasRgbdFolders(const fs::path& dir) {
  std::error_code ec;
  return fs::is_directory(dir / "rgb", ec) && fs::is_directory(dir / "depth", ec);
}

int64_t FrameTimeNs(double n, double frame_rate_hz) {
  return std::llround(n * 1e9 / frame_rate_hz);
}

// Timestamps from file names that are all numbers; nullopt when some name is not one.
std::optional<std::vector<int64_t>> TimesFromNames(const std::vector<fs::path>& files, double frame_rate_hz,
                                                   const fs::path& folder, std::string* source) {
  std::vector<std::string> stems;
  for (const fs::path& f : files) stems.push_back(f.stem().string());
  if (!std::all_of(stems.begin(), stems.end(), IsPlainNumber)) return std::nullopt;
  std::vector<int64_t> t;
  // Integers counting up by one (000000, 000001, ...) number the frames; they are not times.
  bool counting = std::none_of(stems.begin(), stems.end(),
                               [](const std::string& s) { return s.find('.') != std::string::npos || s.size() > 12; });
  for (size_t i = 1; counting && i < stems.size(); ++i) counting = std::stoll(stems[i]) == std::stoll(stems[i - 1]) + 1;
  if (counting && stems.size() > 1) {
    FLATSLAM_CHECK(frame_rate_hz > 0, "image folder ", folder.string(), ": the file names number the frames (",
                   files.front().filename().string(), ", ", files[1].filename().string(),
                   ", ...) and give no times: set Camera.fps in the settings file or add times.txt");
    for (const std::string& s : stems) t.push_back(FrameTimeNs(static_cast<double>(std::stoll(s)), frame_rate_hz));
    *source = "frame numbers";
    return t;
  }
  for (size_t i = 0; i < stems.size(); ++i) {
    const double value = std::strtod(stems[i].c_str(), nullptr);
    if (value > 1e12) {
      t.push_back(stems[i].find('.') == std::string::npos ? io::ParseIntegerNs(stems[i], files[i], 0)
                                                          : std::llround(value));
    } else {
      t.push_back(io::ParseSecondsNs(stems[i], files[i], 0));
    }
  }
  *source = "file names";
  return t;
}

}  // namespace

ImageFolderDataset::ImageFolderDataset(const fs::path& dir, const ImageFolderOptions& options) : dir_(dir) {
  FLATSLAM_CHECK(options.Check(),
                 "ImageFolderOptions: frame_rate_hz and baseline_m must not be negative, depth_factor positive");
  std::error_code ec;
  FLATSLAM_CHECK(fs::is_directory(dir_, ec), "image folder not found: ", dir_.string());
  const auto stereo = FindStereoFolders(dir_);
  const bool rgbd = HasRgbdFolders(dir_);
  const std::vector<fs::path> direct = ListImages(dir_);
  std::string available = direct.empty() && !stereo && !rgbd ? "none" : "mono";
  if (stereo) available += std::string(", stereo (") + stereo->first + "/ + " + stereo->second + "/)";
  if (rgbd) available += ", rgbd (rgb/ + depth/)";
  const Sensor sensor = options.sensor.value_or(stereo ? Sensor::kStereo : rgbd ? Sensor::kRgbd : Sensor::kMonocular);

  std::vector<fs::path> left, second;
  fs::path left_dir = dir_, second_dir;
  switch (sensor) {
    case Sensor::kStereo:
      FLATSLAM_CHECK(
          stereo, "stereo requested but image folder ", dir_.string(),
          " has no left/ + right/ (or image_0/ + image_1/, cam0/ + cam1/) subfolders; available: ", available);
      left_dir = dir_ / stereo->first;
      second_dir = dir_ / stereo->second;
      break;
    case Sensor::kRgbd:
      FLATSLAM_CHECK(rgbd, "RGB-D requested but image folder ", dir_.string(),
                     " has no rgb/ + depth/ subfolders; available: ", available);
      left_dir = dir_ / "rgb";
      second_dir = dir_ / "depth";
      break;
    case Sensor::kMonocular:
      if (direct.empty() && stereo) left_dir = dir_ / stereo->first;
      if (direct.empty() && !stereo && rgbd) left_dir = dir_ / "rgb";
      break;
  }
  left = left_dir == dir_ ? direct : ListImages(left_dir);
  FLATSLAM_CHECK(!left.empty(), "image folder ", left_dir.string(),
                 " holds no .png, .jpg or .jpeg images (a plain image folder holds images, left/ + right/, "
                 "image_0/ + image_1/, cam0/ + cam1/ or rgb/ + depth/)");
  if (!second_dir.empty()) {
    second = ListImages(second_dir);
    FLATSLAM_CHECK(second.size() == left.size(), "image folder ", dir_.string(), ": ", left_dir.filename().string(),
                   "/ holds ", left.size(), " images but ", second_dir.filename().string(), "/ holds ", second.size(),
                   "; they pair in order, so the counts must be equal");
  }

  const fs::path times_txt = dir_ / "times.txt";
  std::vector<int64_t> t;
  if (fs::is_regular_file(times_txt, ec)) {
    for (const io::TextLine& line : io::ReadTextLines(times_txt)) {
      t.push_back(io::ParseSecondsNs(io::SplitFields(line.text)[0], times_txt, line.number));
    }
    FLATSLAM_CHECK(t.size() == left.size(), times_txt.string(), " lists ", t.size(), " times but ", left_dir.string(),
                   " holds ", left.size(), " images");
    time_source_ = "times.txt";
  } else if (auto from_names = TimesFromNames(left, options.frame_rate_hz, left_dir, &time_source_)) {
    t = std::move(*from_names);
  } else {
    FLATSLAM_CHECK(options.frame_rate_hz > 0 || left.size() == 1, "image folder ", dir_.string(),
                   ": no times.txt and the file names are not times: set Camera.fps in the settings file "
                   "or add times.txt (one time in seconds per line)");
    for (size_t i = 0; i < left.size(); ++i) {
      t.push_back(left.size() == 1 ? 0 : FrameTimeNs(static_cast<double>(i), options.frame_rate_hz));
    }
    time_source_ = "frame rate";
  }
  for (size_t i = 1; i < t.size(); ++i) {
    FLATSLAM_CHECK(t[i] > t[i - 1], "image folder ", dir_.string(), ": timestamps (from ", time_source_,
                   ") must increase, but frame ", i, " (", left[i].filename().string(), ") is not after frame ", i - 1);
  }
  for (size_t i = 0; i < left.size(); ++i) frames_.push_back({t[i], left[i], second.empty() ? fs::path() : second[i]});

  calibration_.sensor = sensor;
  calibration_.camera = options.camera;
  if (calibration_.camera.width <= 0 || calibration_.camera.height <= 0) {
    const cv::Size size = ReadImageSize(left.front());
    calibration_.camera.width = size.width;
    calibration_.camera.height = size.height;
  }
  calibration_.baseline_m = sensor == Sensor::kStereo ? options.baseline_m : 0;
  calibration_.frame_rate_hz = options.frame_rate_hz > 0 ? options.frame_rate_hz : io::MedianRateHz(t);
  depth_factor_ = options.depth_factor;
  color_order_ = options.color_order;

  const fs::path gt_txt = dir_ / "groundtruth.txt";
  if (fs::is_regular_file(gt_txt, ec)) ground_truth_ = io::PosesAtTimes(io::ReadTumPoseFile(gt_txt), t);
}

std::string ImageFolderDataset::name() const {
  return "images " + io::FolderName(dir_) + " (" + SensorName(calibration_.sensor) + ")";
}

Frame ImageFolderDataset::read(size_t i) const {
  FLATSLAM_CHECK(i < frames_.size(), "frame ", i, " out of range: ", name(), " has ", frames_.size(), " frames");
  const Entry& entry = frames_[i];
  const cv::Size size(calibration_.camera.width, calibration_.camera.height);
  Frame frame;
  frame.index = i;
  frame.t_ns = entry.t_ns;
  frame.left = ReadGrayImage(entry.left, size, color_order_);
  if (calibration_.sensor == Sensor::kStereo) frame.right = ReadGrayImage(entry.second, size, color_order_);
  if (calibration_.sensor == Sensor::kRgbd) frame.depth = ReadDepthImage(entry.second, depth_factor_, size);
  return frame;
}

bool LooksLikeImageFolder(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return false;
  if (FindStereoFolders(dir) || HasRgbdFolders(dir) || !ListImages(dir).empty()) return true;
  for (const auto& [left, right] : kStereoFolders) {
    if (fs::is_directory(dir / left, ec)) return true;
  }
  return fs::is_directory(dir / "rgb", ec);
}

}  // namespace flatslam
