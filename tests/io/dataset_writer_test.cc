#include "io/dataset_writer.h"

#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

std::unique_ptr<Dataset> SmallScene(const std::string& sensor) {
  return OpenDataset("synth:room:width=320,height=240,duration=2,sensor=" + sensor);
}

void ExpectSamePoses(const Trajectory& a, const Trajectory& b) {
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_EQ(a[i].t_ns, b[i].t_ns) << "pose " << i;
    EXPECT_LT((a[i].T_world_cam.matrix() - b[i].T_world_cam.matrix()).cwiseAbs().maxCoeff(), 1e-9) << "pose " << i;
  }
}

double MaxDiff(const cv::Mat& a, const cv::Mat& b) {
  return cv::norm(a, b, cv::NORM_INF);
}

TEST(DatasetWriter, KittiStereoRoundTrip) {
  const auto source = SmallScene("stereo");
  const fs::path dir = testing::FreshTempDir("writer_kitti") / "out";
  const DatasetWriteResult written = WriteDataset(*source, dir, DatasetFormat::kKitti);
  EXPECT_EQ(written.frames, source->size());
  const auto back = OpenDataset(written.dataset_path.string());
  ASSERT_EQ(back->size(), source->size());
  EXPECT_EQ(back->calibration().sensor, Sensor::kStereo);
  EXPECT_NEAR(back->calibration().baseline_m, source->calibration().baseline_m, 1e-12);
  EXPECT_NEAR(back->calibration().camera.fx, source->calibration().camera.fx, 1e-9);
  EXPECT_NEAR(back->calibration().camera.cx, source->calibration().camera.cx, 1e-9);
  ExpectSamePoses(*source->ground_truth(), *back->ground_truth());
  for (size_t i : {size_t{0}, source->size() - 1}) {
    const Frame a = source->read(i), b = back->read(i);
    EXPECT_EQ(a.t_ns, b.t_ns);
    EXPECT_EQ(MaxDiff(a.left, b.left), 0.0);  // PNG is lossless
    EXPECT_EQ(MaxDiff(a.right, b.right), 0.0);
  }
}

TEST(DatasetWriter, TumRgbdRoundTrip) {
  const auto source = SmallScene("rgbd");
  const fs::path dir = testing::FreshTempDir("writer_tum") / "out";
  const DatasetWriteResult written = WriteDataset(*source, dir, DatasetFormat::kTum);
  const auto back = OpenDataset(written.dataset_path.string());
  ASSERT_EQ(back->size(), source->size());
  EXPECT_EQ(back->calibration().sensor, Sensor::kRgbd);
  EXPECT_NEAR(back->calibration().camera.fy, source->calibration().camera.fy, 1e-9);
  ExpectSamePoses(*source->ground_truth(), *back->ground_truth());
  const Frame a = source->read(7), b = back->read(7);
  EXPECT_EQ(MaxDiff(a.left, b.left), 0.0);
  ASSERT_EQ(b.depth.type(), CV_32FC1);
  // 16-bit depth at 5000 units per metre: within half a unit wherever it is representable.
  for (int v = 0; v < a.depth.rows; v += 7) {
    for (int u = 0; u < a.depth.cols; u += 7) {
      const float za = a.depth.at<float>(v, u), zb = b.depth.at<float>(v, u);
      if (za > 0 && za < 13.0f) {
        EXPECT_NEAR(za, zb, 0.5 / 5000 + 1e-6) << u << "," << v;
      }
      if (za == 0) {
        EXPECT_EQ(zb, 0.0f);
      }
    }
  }
}

TEST(DatasetWriter, EurocStereoRoundTrip) {
  const auto source = SmallScene("stereo");
  const fs::path dir = testing::FreshTempDir("writer_euroc") / "out";
  const DatasetWriteResult written = WriteDataset(*source, dir, DatasetFormat::kEuroc);
  const auto back = OpenDataset(written.dataset_path.string());
  ASSERT_EQ(back->size(), source->size());
  EXPECT_EQ(back->calibration().sensor, Sensor::kStereo);
  EXPECT_NEAR(back->calibration().baseline_m, source->calibration().baseline_m, 1e-9);
  // Ground truth is written for the body (IMU) frame and converted back through T_BS.
  ExpectSamePoses(*source->ground_truth(), *back->ground_truth());
  const Frame a = source->read(3), b = back->read(3);
  EXPECT_EQ(b.left.size(), a.left.size());
}

TEST(DatasetWriter, MonoToKittiAndEuroc) {
  const auto source = SmallScene("mono");
  const fs::path root = testing::FreshTempDir("writer_mono");
  for (DatasetFormat format : {DatasetFormat::kKitti, DatasetFormat::kEuroc}) {
    const fs::path dir = root / (format == DatasetFormat::kKitti ? "kitti" : "euroc");
    const auto back = OpenDataset(WriteDataset(*source, dir, format).dataset_path.string());
    EXPECT_EQ(back->calibration().sensor, Sensor::kMonocular);
    ExpectSamePoses(*source->ground_truth(), *back->ground_truth());
  }
}

TEST(DatasetWriter, RefusesToOverwriteAndLeavesNothingOnError) {
  const auto stereo = SmallScene("stereo");
  const fs::path root = testing::FreshTempDir("writer_errors");
  // A folder that already holds something is never touched.
  const fs::path used = root / "used";
  fs::create_directories(used);
  std::ofstream(used / "keep.txt") << "precious";
  EXPECT_THROW(WriteDataset(*stereo, used, DatasetFormat::kKitti), Error);
  EXPECT_TRUE(fs::exists(used / "keep.txt"));
  EXPECT_EQ(std::distance(fs::directory_iterator(used), fs::directory_iterator()), 1);
  // A sensor the layout cannot hold fails before writing anything.
  try {
    WriteDataset(*stereo, root / "tum", DatasetFormat::kTum);
    FAIL() << "stereo data written as TUM RGB-D";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("TUM"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(fs::exists(root / "tum"));
  EXPECT_FALSE(fs::exists(root / "tum.partial"));
  EXPECT_THROW(WriteDataset(*SmallScene("rgbd"), root / "k", DatasetFormat::kKitti), Error);
  EXPECT_FALSE(fs::exists(root / "k"));
  EXPECT_THROW((void)ParseDatasetFormat("bag"), Error);
  // Frames whose images are not yet undistorted into the calibration's camera (a refined
  // camera's lens) would be written with a calibration they do not have.
  try {
    WriteDataset(*ApplyCameraRefit(SmallScene("mono"), CameraRefit{1.01, 0.02}), root / "refined",
                 DatasetFormat::kKitti);
    FAIL() << "images written with a calibration they do not have";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("not yet undistorted"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(fs::exists(root / "refined"));
}

}  // namespace
}  // namespace flatslam
