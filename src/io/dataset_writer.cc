#include "io/dataset_writer.h"

#include <atomic>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <mutex>
#include <system_error>

#include <opencv2/imgcodecs.hpp>
#include <tbb/parallel_for.h>

#include "core/error.h"
#include "io/tum.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace fs = std::filesystem;

namespace {

void WriteImage(const fs::path& path, const cv::Mat& image) {
  FLATSLAM_CHECK(cv::imwrite(path.string(), image), "cannot write image ", path);
}

std::ofstream OpenText(const fs::path& path) {
  std::ofstream out(path);
  FLATSLAM_CHECK(out.good(), "cannot create ", path);
  out << std::setprecision(17);
  return out;
}

void CloseText(std::ofstream& out, const fs::path& path) {
  out.close();
  FLATSLAM_CHECK(!out.fail(), "write to ", path, " failed");
}

// Metres to 16-bit depth units; 0 (no measurement) stays 0, out-of-range saturates to 0.
cv::Mat EncodeDepth(const cv::Mat& depth_m, double factor) {
  cv::Mat out(depth_m.size(), CV_16UC1);
  for (int v = 0; v < depth_m.rows; ++v) {
    const float* in = depth_m.ptr<float>(v);
    uint16_t* o = out.ptr<uint16_t>(v);
    for (int u = 0; u < depth_m.cols; ++u) {
      const double raw = std::round(in[u] * factor);
      o[u] = (raw > 0 && raw < 65535) ? static_cast<uint16_t>(raw) : 0;
    }
  }
  return out;
}

// Reads every frame once, in parallel, and hands it to write(); returns the timestamps.
std::vector<int64_t> ForEachFrame(const Dataset& dataset, const std::function<void(const Frame&)>& write,
                                  const std::function<void(size_t, size_t)>& progress) {
  const size_t n = dataset.size();
  std::vector<int64_t> stamps(n);
  constexpr size_t kChunk = 64;
  for (size_t begin = 0; begin < n; begin += kChunk) {
    const size_t end = std::min(n, begin + kChunk);
    tbb::parallel_for(begin, end, [&](size_t i) {
      const Frame frame = dataset.read(i);
      FLATSLAM_CHECK(!frame.lens, "cannot write ", dataset.name(),
                     ": its images are not yet undistorted into its calibration's camera");
      stamps[i] = frame.t_ns;
      write(frame);
    });
    if (progress) progress(end, n);
  }
  return stamps;
}

Eigen::Matrix4d BodyFromCam0() {
  // EuRoC-like mounting: camera x along body -y, camera y along body x, small offset.
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<3, 3>(0, 0) << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  T.block<3, 1>(0, 3) << -0.02, -0.06, 0.01;
  return T;
}

void WriteSensorYaml(const fs::path& path, const Calibration& calib, const Eigen::Matrix4d& T_BS) {
  std::ofstream out = OpenText(path);
  out << "# General sensor definitions.\nsensor_type: camera\ncomment: flatslam synthetic camera\n\n"
      << "# Sensor extrinsics wrt. the body-frame.\nT_BS:\n  cols: 4\n  rows: 4\n  data: [";
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) out << T_BS(r, c) << (r == 3 && c == 3 ? "]\n" : ", ");
  const PinholeCamera& cam = calib.camera;
  out << "\n# Camera specific definitions.\nrate_hz: " << calib.frame_rate_hz << "\nresolution: [" << cam.width << ", "
      << cam.height << "]\ncamera_model: pinhole\nintrinsics: [" << cam.fx << ", " << cam.fy << ", " << cam.cx << ", "
      << cam.cy << "] #fu, fv, cu, cv\n"
      << "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n";
  CloseText(out, path);
}

void WriteKittiLayout(const Dataset& dataset, const fs::path& root,
                      const std::function<void(size_t, size_t)>& progress) {
  const Calibration& calib = dataset.calibration();
  FLATSLAM_CHECK(calib.sensor != Sensor::kRgbd,
                 "the KITTI layout holds mono or stereo images; write RGB-D data with --format tum");
  const bool stereo = calib.sensor == Sensor::kStereo;
  const fs::path seq = root / "sequences" / "00";
  fs::create_directories(seq / "image_0");
  if (stereo) fs::create_directories(seq / "image_1");
  fs::create_directories(root / "poses");

  const std::vector<int64_t> stamps = ForEachFrame(
      dataset,
      [&](const Frame& f) {
        char name[32];
        std::snprintf(name, sizeof(name), "%06zu.png", f.index);
        WriteImage(seq / "image_0" / name, f.left);
        if (stereo) WriteImage(seq / "image_1" / name, f.right);
      },
      progress);

  // P0 = K [I | 0]; P1 = K [I | -b e_x] for the right camera, as in KITTI's calib.txt.
  const PinholeCamera& c = calib.camera;
  std::ofstream out = OpenText(seq / "calib.txt");
  for (int k = 0; k < 4; ++k) {
    const double tx = (k % 2 == 1 && stereo) ? -c.fx * calib.baseline_m : 0.0;
    out << "P" << k << ": " << c.fx << " 0 " << c.cx << " " << tx << " 0 " << c.fy << " " << c.cy << " 0 0 0 1 0\n";
  }
  CloseText(out, seq / "calib.txt");

  Trajectory times(stamps.size());
  for (size_t i = 0; i < times.size(); ++i) times[i].t_ns = stamps[i];
  if (auto gt = dataset.ground_truth()) {
    WriteKitti(root / "poses" / "00.txt", *gt);
    WriteKittiTimes(seq / "times.txt", *gt);
  } else {
    fs::remove(root / "poses");
    WriteKittiTimes(seq / "times.txt", times);
  }
}

void WriteTumLayout(const Dataset& dataset, const fs::path& root, const std::function<void(size_t, size_t)>& progress) {
  const Calibration& calib = dataset.calibration();
  FLATSLAM_CHECK(calib.sensor != Sensor::kStereo,
                 "the TUM RGB-D layout holds RGB-D (or mono) images; write stereo data with --format kitti or euroc");
  const bool rgbd = calib.sensor == Sensor::kRgbd;
  constexpr double kDepthFactor = 5000;
  fs::create_directories(root / "rgb");
  if (rgbd) fs::create_directories(root / "depth");

  const std::vector<int64_t> stamps_ns = ForEachFrame(
      dataset,
      [&](const Frame& f) {
        const std::string stamp = FormatNsAsSeconds(f.t_ns);
        WriteImage(root / "rgb" / (stamp + ".png"), f.left);
        if (rgbd) WriteImage(root / "depth" / (stamp + ".png"), EncodeDepth(f.depth, kDepthFactor));
      },
      progress);

  std::vector<std::string> stamps;
  for (const int64_t t : stamps_ns) stamps.push_back(FormatNsAsSeconds(t));
  std::ofstream rgb = OpenText(root / "rgb.txt");
  rgb << "# color images\n# written by flatslam synth\n# timestamp filename\n";
  for (const auto& s : stamps) rgb << s << " rgb/" << s << ".png\n";
  CloseText(rgb, root / "rgb.txt");
  if (rgbd) {
    std::ofstream depth = OpenText(root / "depth.txt");
    depth << "# depth maps\n# written by flatslam synth\n# timestamp filename\n";
    for (const auto& s : stamps) depth << s << " depth/" << s << ".png\n";
    CloseText(depth, root / "depth.txt");
  }
  WriteTumCameraFile(root / "camera.txt", TumCameraFile{calib.camera, kDepthFactor});
  if (auto gt = dataset.ground_truth()) WriteTum(root / "groundtruth.txt", *gt);
}

void WriteEurocLayout(const Dataset& dataset, const fs::path& root,
                      const std::function<void(size_t, size_t)>& progress) {
  const Calibration& calib = dataset.calibration();
  FLATSLAM_CHECK(calib.sensor != Sensor::kRgbd,
                 "the EuRoC layout holds mono or stereo images; write RGB-D data with --format tum");
  const bool stereo = calib.sensor == Sensor::kStereo;
  const fs::path mav0 = root / "mav0";
  const int cameras = stereo ? 2 : 1;
  for (int c = 0; c < cameras; ++c) fs::create_directories(mav0 / ("cam" + std::to_string(c)) / "data");

  const std::vector<int64_t> stamps = ForEachFrame(
      dataset,
      [&](const Frame& f) {
        const std::string name = std::to_string(f.t_ns) + ".png";
        WriteImage(mav0 / "cam0" / "data" / name, f.left);
        if (stereo) WriteImage(mav0 / "cam1" / "data" / name, f.right);
      },
      progress);

  const Eigen::Matrix4d T_B_C0 = BodyFromCam0();
  Eigen::Matrix4d T_C0_C1 = Eigen::Matrix4d::Identity();
  T_C0_C1(0, 3) = calib.baseline_m;
  for (int c = 0; c < cameras; ++c) {
    const fs::path dir = mav0 / ("cam" + std::to_string(c));
    WriteSensorYaml(dir / "sensor.yaml", calib, c == 0 ? T_B_C0 : Eigen::Matrix4d(T_B_C0 * T_C0_C1));
    std::ofstream csv = OpenText(dir / "data.csv");
    csv << "#timestamp [ns],filename\n";
    for (const int64_t t : stamps) csv << t << "," << t << ".png\n";
    CloseText(csv, dir / "data.csv");
  }
  if (auto gt = dataset.ground_truth()) {
    const fs::path dir = mav0 / "state_groundtruth_estimate0";
    fs::create_directories(dir);
    std::ofstream csv = OpenText(dir / "data.csv");
    csv << "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n";
    const Eigen::Isometry3d T_C0_B(T_B_C0.inverse());
    for (const TimedPose& p : *gt) {
      const Eigen::Isometry3d T_world_body = p.T_world_cam * T_C0_B;
      const Eigen::Quaterniond q(T_world_body.linear());
      const Eigen::Vector3d t = T_world_body.translation();
      csv << p.t_ns << "," << t.x() << "," << t.y() << "," << t.z() << "," << q.w() << "," << q.x() << "," << q.y()
          << "," << q.z() << "\n";
    }
    CloseText(csv, dir / "data.csv");
  }
}

}  // namespace

DatasetFormat ParseDatasetFormat(const std::string& name) {
  if (name == "kitti") return DatasetFormat::kKitti;
  if (name == "tum") return DatasetFormat::kTum;
  if (name == "euroc") return DatasetFormat::kEuroc;
  Fail("unknown dataset format '", name, "' (known: kitti, tum, euroc)");
}

DatasetWriteResult WriteDataset(const Dataset& dataset, const fs::path& dir, DatasetFormat format,
                                const std::function<void(size_t, size_t)>& progress) {
  FLATSLAM_CHECK(dataset.size() > 0, "dataset ", dataset.name(), " has no frames to write");
  std::error_code ec;
  if (fs::exists(dir)) {
    FLATSLAM_CHECK(fs::is_directory(dir) && fs::is_empty(dir), "output ", dir,
                   " already exists and is not an empty folder; refusing to overwrite it");
  }
  const fs::path target = fs::absolute(dir).lexically_normal();
  const fs::path parent = target.parent_path();
  fs::create_directories(parent, ec);
  FLATSLAM_CHECK(!ec, "cannot create ", parent, ": ", ec.message());
  const fs::path staging = parent / (target.filename().string() + ".partial");
  fs::remove_all(staging, ec);
  fs::create_directories(staging, ec);
  FLATSLAM_CHECK(!ec, "cannot create ", staging, ": ", ec.message());

  DatasetWriteResult result;
  result.frames = dataset.size();
  try {
    switch (format) {
      case DatasetFormat::kKitti:
        WriteKittiLayout(dataset, staging, progress);
        result.dataset_path = target / "sequences" / "00";
        break;
      case DatasetFormat::kTum:
        WriteTumLayout(dataset, staging, progress);
        result.dataset_path = target;
        break;
      case DatasetFormat::kEuroc:
        WriteEurocLayout(dataset, staging, progress);
        result.dataset_path = target;
        break;
    }
  } catch (...) {
    fs::remove_all(staging, ec);
    throw;
  }
  if (fs::exists(target)) fs::remove(target);  // the empty folder checked above
  fs::rename(staging, target, ec);
  FLATSLAM_CHECK(!ec, "cannot move ", staging, " to ", target, ": ", ec.message());
  return result;
}

}  // namespace flatslam
