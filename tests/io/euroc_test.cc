#include "io/euroc.h"

#include <algorithm>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::ExpectErrorMentions;

fs::path Sequence() {
  return testing::DatasetsDir() / "euroc/V1_01_first20";
}

// Projects a point given in the raw camera frame through the distorted model.
cv::Point2d ProjectRaw(const EurocCameraModel& camera, const Eigen::Vector3d& p) {
  std::vector<cv::Point3d> object{{p.x(), p.y(), p.z()}};
  std::vector<cv::Point2d> image;
  cv::projectPoints(object, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), camera.K, camera.distortion, image);
  return image[0];
}

// Raw pixel of camera `i` to its rectified pixel (iterated to convergence, not the default 5 steps).
cv::Point2d RectifyRaw(const EurocDataset& dataset, int i, cv::Point2d raw) {
  const EurocCameraModel& camera = dataset.raw_camera(i);
  std::vector<cv::Point2d> in{raw}, out;
  cv::undistortPoints(in, out, camera.K, camera.distortion, dataset.rectification_rotation(i),
                      dataset.rectified_projection(i),
                      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 200, 1e-12));
  return out[0];
}

bool Inside(cv::Point2d p, cv::Size size) {
  return p.x >= 0 && p.y >= 0 && p.x < size.width && p.y < size.height;
}

TEST(Euroc, SensorYamlIsParsed) {
  const auto camera = ReadEurocSensorYaml(Sequence() / "mav0/cam0/sensor.yaml");
  EXPECT_DOUBLE_EQ(camera.K(0, 0), 458.654);
  EXPECT_DOUBLE_EQ(camera.K(1, 1), 457.296);
  EXPECT_DOUBLE_EQ(camera.K(0, 2), 367.215);
  EXPECT_DOUBLE_EQ(camera.K(1, 2), 248.375);
  EXPECT_DOUBLE_EQ(camera.distortion[0], -0.28340811);
  EXPECT_DOUBLE_EQ(camera.distortion[3], 1.76187114e-05);
  EXPECT_EQ(camera.resolution, cv::Size(752, 480));
  EXPECT_DOUBLE_EQ(camera.rate_hz, 20);
  EXPECT_DOUBLE_EQ(camera.T_body_sensor.translation().x(), -0.0216401454975);
  EXPECT_DOUBLE_EQ(camera.T_body_sensor.translation().z(), 0.00981073058949);
  EXPECT_NEAR(camera.T_body_sensor.linear()(1, 0), 0.999557249008, 1e-9);
}

TEST(Euroc, StereoSnippetLoads) {
  const auto dataset = OpenDataset(Sequence().string());
  EXPECT_EQ(dataset->name(), "EuRoC V1_01_first20 (stereo)");
  ASSERT_EQ(dataset->size(), 20u);
  const Calibration& calib = dataset->calibration();
  EXPECT_EQ(calib.sensor, Sensor::kStereo);
  EXPECT_EQ(calib.camera.width, 752);
  EXPECT_EQ(calib.camera.height, 480);
  EXPECT_NEAR(calib.baseline_m, 0.110, 0.002);
  EXPECT_DOUBLE_EQ(calib.frame_rate_hz, 20);
  std::printf("EuRoC rectified: %dx%d fx %.3f fy %.3f cx %.3f cy %.3f baseline %.5f m\n", calib.camera.width,
              calib.camera.height, calib.camera.fx, calib.camera.fy, calib.camera.cx, calib.camera.cy,
              calib.baseline_m);

  const Frame frame = dataset->read(19);
  EXPECT_EQ(frame.t_ns, 1403715274212143104);
  ASSERT_EQ(frame.left.type(), CV_8UC1);
  ASSERT_EQ(frame.right.type(), CV_8UC1);
  EXPECT_EQ(frame.left.size(), cv::Size(752, 480));
  EXPECT_EQ(frame.right.size(), cv::Size(752, 480));
  // alpha = 0: no black border from the remap.
  EXPECT_GT(frame.left.at<uchar>(0, 0) + frame.left.at<uchar>(479, 751) + frame.left.at<uchar>(240, 0), 0);
}

TEST(Euroc, RectificationAlignsRows) {
  const EurocDataset dataset(Sequence());
  const Calibration& calib = dataset.calibration();
  const cv::Size size(calib.camera.width, calib.camera.height);
  const double b = calib.baseline_m;
  const std::vector<Eigen::Vector3d> points_cam0 = {{0, 0, 1},         {0.5, -0.3, 2},  {-1, 0.6, 3}, {2, 1.2, 10},
                                                    {-0.2, -0.4, 0.8}, {0.9, 0.7, 1.5}, {-3, -2, 8},  {0.05, 0.05, 50}};
  int checked = 0;
  for (const Eigen::Vector3d& p_cam0 : points_cam0) {
    const Eigen::Vector3d p_body = dataset.raw_camera(0).T_body_sensor * p_cam0;
    const Eigen::Vector3d p_cam1 = dataset.raw_camera(1).T_body_sensor.inverse() * p_body;
    const cv::Point2d raw0 = ProjectRaw(dataset.raw_camera(0), p_cam0);
    const cv::Point2d raw1 = ProjectRaw(dataset.raw_camera(1), p_cam1);
    if (!Inside(raw0, size) || !Inside(raw1, size)) continue;
    ++checked;
    const cv::Point2d rect0 = RectifyRaw(dataset, 0, raw0), rect1 = RectifyRaw(dataset, 1, raw1);
    EXPECT_NEAR(rect0.y, rect1.y, 0.1) << "point " << p_cam0.transpose();
    // The published pinhole and T_body_cam reproduce the rectified left pixel...
    const Eigen::Vector3d p = calib.T_body_cam.inverse() * p_body;
    const double u = calib.camera.fx * p.x() / p.z() + calib.camera.cx;
    const double v = calib.camera.fy * p.y() / p.z() + calib.camera.cy;
    EXPECT_NEAR(rect0.x, u, 0.1);
    EXPECT_NEAR(rect0.y, v, 0.1);
    // ... and the right one is the same camera moved by the baseline along +x.
    EXPECT_NEAR(rect1.x, calib.camera.fx * (p.x() - b) / p.z() + calib.camera.cx, 0.1);
  }
  EXPECT_GE(checked, 6);
}

// The remapped images themselves: matched features sit on the same row, disparity >= 0.
TEST(Euroc, RectifiedImagesMatchAlongRows) {
  const EurocDataset dataset(Sequence());
  const Frame frame = dataset.read(0);
  auto orb = cv::ORB::create(1500);
  std::vector<cv::KeyPoint> kl, kr;
  cv::Mat dl, dr;
  orb->detectAndCompute(frame.left, cv::noArray(), kl, dl);
  orb->detectAndCompute(frame.right, cv::noArray(), kr, dr);
  cv::BFMatcher matcher(cv::NORM_HAMMING, true);
  std::vector<cv::DMatch> matches;
  matcher.match(dl, dr, matches);
  std::vector<double> dv;
  int negative_disparity = 0;
  for (const auto& m : matches) {
    const auto& a = kl[m.queryIdx];
    const auto& c = kr[m.trainIdx];
    if (m.distance > 40 || a.octave != 0 || c.octave != 0 || std::abs(a.pt.y - c.pt.y) > 4) continue;
    dv.push_back(a.pt.y - c.pt.y);
    if (a.pt.x - c.pt.x < -1) ++negative_disparity;
  }
  ASSERT_GE(dv.size(), 30u);
  // Octave-0 ORB corners sit on integer pixels: the mean resolves the sub-pixel offset.
  double mean = 0;
  for (double d : dv) mean += d / static_cast<double>(dv.size());
  std::nth_element(dv.begin(), dv.begin() + dv.size() / 2, dv.end());
  const double median = dv[dv.size() / 2];
  std::printf("EuRoC rectified ORB matches: %zu, row offset median %.3f mean %.3f px\n", dv.size(), median, mean);
  EXPECT_LT(std::abs(median), 0.3);
  EXPECT_LT(std::abs(mean), 0.3);
  EXPECT_LT(negative_disparity, static_cast<int>(dv.size() / 10));
}

TEST(Euroc, GroundTruthIsTheRectifiedLeftCamera) {
  const EurocDataset dataset(Sequence());
  EXPECT_EQ(dataset.ground_truth_file().filename(), "groundtruth_tum.txt");
  const auto gt = dataset.ground_truth();
  ASSERT_TRUE(gt.has_value());
  ASSERT_EQ(gt->size(), 20u);
  for (size_t i = 0; i < gt->size(); ++i) EXPECT_EQ((*gt)[i].t_ns, dataset.read(i).t_ns);
  // First line of groundtruth_tum.txt: body at 0.878895 2.183400 0.948427, q = (x -0.824237,
  // y -0.106942, z -0.551702, w 0.069433).
  const Eigen::Isometry3d T_world_body = gt->front().T_world_cam * dataset.calibration().T_body_cam.inverse();
  EXPECT_NEAR((T_world_body.translation() - Eigen::Vector3d(0.878895, 2.183400, 0.948427)).norm(), 0, 1e-4);
  const Eigen::Quaterniond q(0.069433, -0.824237, -0.106942, -0.551702);
  EXPECT_LT(Eigen::Quaterniond(T_world_body.linear()).angularDistance(q.normalized()), 1e-4);
  // T_body_cam is cam0's T_BS turned by the (small) rectification rotation.
  const Eigen::Isometry3d T_cam0_rect =
      dataset.raw_camera(0).T_body_sensor.inverse() * dataset.calibration().T_body_cam;
  EXPECT_LT(T_cam0_rect.translation().norm(), 1e-12);
  EXPECT_LT(Eigen::AngleAxisd(T_cam0_rect.linear()).angle(), 0.05);
}

TEST(Euroc, MonoUndistortsCam0) {
  EurocOptions options;
  options.sensor = Sensor::kMonocular;
  const EurocDataset dataset(Sequence(), options);
  EXPECT_EQ(dataset.name(), "EuRoC V1_01_first20 (mono)");
  EXPECT_EQ(dataset.calibration().baseline_m, 0);
  EXPECT_TRUE(dataset.calibration().T_body_cam.isApprox(dataset.raw_camera(0).T_body_sensor));
  const Frame frame = dataset.read(3);
  EXPECT_EQ(frame.left.size(), cv::Size(752, 480));
  EXPECT_TRUE(frame.right.empty());
  // A raw point lands where the undistorted pinhole says.
  const Eigen::Vector3d p(0.4, -0.3, 2.0);
  const cv::Point2d rect = RectifyRaw(dataset, 0, ProjectRaw(dataset.raw_camera(0), p));
  const PinholeCamera& c = dataset.calibration().camera;
  EXPECT_NEAR(rect.x, c.fx * p.x() / p.z() + c.cx, 0.1);
  EXPECT_NEAR(rect.y, c.fy * p.y() / p.z() + c.cy, 0.1);

  DatasetOptions rgbd;
  rgbd.sensor = Sensor::kRgbd;
  ExpectErrorMentions([&] { (void)OpenDataset(Sequence().string(), rgbd); }, {"RGB-D", "mono, stereo"});
}

// A two-frame copy of the snippet, to break one file at a time.
class EurocBadInput : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = testing::FreshTempDir("euroc_bad") / "V1_tiny";
    for (const char* cam : {"cam0", "cam1"}) {
      const fs::path from = Sequence() / "mav0" / cam, to = root_ / "mav0" / cam;
      fs::create_directories(to / "data");
      fs::copy_file(from / "sensor.yaml", to / "sensor.yaml");
      std::ofstream csv(to / "data.csv");
      csv << "#timestamp [ns],filename\n";
      for (const char* stamp : {"1403715273262142976", "1403715273312143104"}) {
        csv << stamp << "," << stamp << ".png\n";
        fs::copy_file(from / "data" / (std::string(stamp) + ".png"), to / "data" / (std::string(stamp) + ".png"));
      }
    }
  }
  void TearDown() override { fs::remove_all(root_.parent_path()); }

  fs::path Image(const char* cam, int i) const {
    return root_ / "mav0" / cam / "data" / (i == 0 ? "1403715273262142976.png" : "1403715273312143104.png");
  }

  fs::path root_;
};

TEST_F(EurocBadInput, CopyOpensFromMav0Too) {
  const EurocDataset dataset(root_ / "mav0");
  EXPECT_EQ(dataset.size(), 2u);
  EXPECT_EQ(dataset.unmatched_dropped(), 0u);
  EXPECT_FALSE(dataset.ground_truth().has_value());
}

TEST_F(EurocBadInput, EmptyDataCsv) {
  std::ofstream(root_ / "mav0/cam1/data.csv") << "#timestamp [ns],filename\n";
  ExpectErrorMentions([&] { (void)EurocDataset(root_); }, {"cam1", "data.csv", "no frames"});
}

TEST_F(EurocBadInput, UnmatchedStereoFramesAreDroppedAndCounted) {
  std::ofstream(root_ / "mav0/cam1/data.csv") << "#timestamp [ns],filename\n"
                                              << "1403715273312143104,1403715273312143104.png\n";
  const EurocDataset dataset(root_);
  ASSERT_EQ(dataset.size(), 1u);
  EXPECT_EQ(dataset.read(0).t_ns, 1403715273312143104);
  EXPECT_EQ(dataset.unmatched_dropped(), 1u);
  EXPECT_NE(dataset.name().find("1 unmatched"), std::string::npos) << dataset.name();
}

TEST_F(EurocBadInput, MissingYamlField) {
  const auto yaml = root_ / "mav0/cam0/sensor.yaml";
  std::ifstream in(yaml);
  std::string text, line;
  while (std::getline(in, line)) {
    if (line.rfind("intrinsics", 0) != 0) text += line + "\n";
  }
  in.close();
  std::ofstream(yaml) << text;
  ExpectErrorMentions([&] { (void)EurocDataset(root_); }, {"sensor.yaml", "intrinsics"});
}

TEST_F(EurocBadInput, UnsupportedDistortionModel) {
  std::ofstream(root_ / "mav0/cam1/sensor.yaml", std::ios::app) << "distortion_model: equidistant\n";
  ExpectErrorMentions([&] { (void)EurocDataset(root_); }, {"cam1", "sensor.yaml", "equidistant"});
}

TEST_F(EurocBadInput, TruncatedAndWrongSizeImages) {
  fs::resize_file(Image("cam1", 0), fs::file_size(Image("cam1", 0)) / 2);
  ASSERT_TRUE(cv::imwrite(Image("cam0", 1).string(), cv::Mat(240, 376, CV_8UC1, cv::Scalar(7))));
  const EurocDataset dataset(root_);
  ExpectErrorMentions([&] { (void)dataset.read(0); }, {Image("cam1", 0).string(), "truncated"});
  ExpectErrorMentions([&] { (void)dataset.read(1); }, {Image("cam0", 1).string(), "376x240", "752x480"});
}

TEST_F(EurocBadInput, AslGroundTruthIsInterpolated) {
  fs::create_directories(root_ / "mav0/state_groundtruth_estimate0");
  // Body moves 1 m along x between two stamps 100 ms apart, bracketing both frames.
  std::ofstream(root_ / "mav0/state_groundtruth_estimate0/data.csv")
      << "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n"
      << "1403715273262142976,0,0,0,1,0,0,0\n"
      << "1403715273362142976,1,0,0,1,0,0,0\n";
  const EurocDataset dataset(root_);
  EXPECT_EQ(dataset.ground_truth_file().filename(), "data.csv");
  const auto gt = dataset.ground_truth();
  ASSERT_TRUE(gt.has_value());
  ASSERT_EQ(gt->size(), 2u);
  const Eigen::Isometry3d& T_body_cam = dataset.calibration().T_body_cam;
  EXPECT_TRUE((*gt)[0].T_world_cam.isApprox(T_body_cam, 1e-12));
  const Eigen::Vector3d body = ((*gt)[1].T_world_cam * T_body_cam.inverse()).translation();
  EXPECT_NEAR(body.x(), 0.50000128, 1e-6);  // 50.000128 ms of 100 ms
}

}  // namespace
}  // namespace flatslam
