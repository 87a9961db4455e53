#include "trajectory/trajectory_io.h"

#include <fstream>
#include <random>
#include <string>

#include <gtest/gtest.h>

#include "core/error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

fs::path TempDir() {
  static const fs::path dir = testing::FreshTempDir("trajectory_io");
  return dir;
}

fs::path WriteText(const std::string& name, const std::string& text) {
  const fs::path path = TempDir() / name;
  std::ofstream(path) << text;
  return path;
}

// Message of the flatslam::Error thrown by f, or "" when none is thrown.
template <class F>
std::string ErrorOf(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// Random poses with awkward numbers: large and tiny translations, arbitrary rotations, and
// timestamps around the epoch values real datasets use.
Trajectory RandomTrajectory(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(-1, 1);
  Trajectory trajectory;
  int64_t t_ns = 1'403'715'273'262'142'976;
  for (size_t i = 0; i < n; ++i) {
    TimedPose p;
    t_ns += 1 + static_cast<int64_t>(rng() % 100'000'000);
    p.t_ns = t_ns;
    Eigen::Quaterniond q(unit(rng), unit(rng), unit(rng), unit(rng));
    q.normalize();
    p.T_world_cam.linear() = q.toRotationMatrix();
    p.T_world_cam.translation() = Eigen::Vector3d(1e3 * unit(rng), 1e-7 * unit(rng), unit(rng) / 3);
    trajectory.push_back(p);
  }
  return trajectory;
}

void ExpectSamePoses(const Trajectory& a, const Trajectory& b, bool same_times) {
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    if (same_times) {
      EXPECT_EQ(a[i].t_ns, b[i].t_ns) << "pose " << i;
    }
    EXPECT_LT((a[i].T_world_cam.matrix() - b[i].T_world_cam.matrix()).cwiseAbs().maxCoeff(), 1e-12) << "pose " << i;
  }
}

// ---- Round trips ----

TEST(TrajectoryIo, TumRoundTripIsExact) {
  const Trajectory original = RandomTrajectory(300, 7);
  const fs::path path = TempDir() / "round.txt";
  WriteTum(path, original);
  EXPECT_EQ(DetectTrajectoryFormat(path), TrajectoryFormat::kTum);
  ExpectSamePoses(original, ReadTrajectory(path), true);
}

TEST(TrajectoryIo, EurocRoundTripIsExact) {
  const Trajectory original = RandomTrajectory(300, 5);
  const fs::path path = TempDir() / "round.csv";
  WriteEuroc(path, original);
  EXPECT_EQ(DetectTrajectoryFormat(path), TrajectoryFormat::kEuroc);
  ExpectSamePoses(original, ReadTrajectory(path), true);
}

TEST(TrajectoryIo, KittiRoundTripIsExact) {
  const Trajectory original = RandomTrajectory(300, 11);
  const fs::path poses = TempDir() / "round_kitti.txt";
  const fs::path times = TempDir() / "round_times.txt";
  WriteKitti(poses, original);
  WriteKittiTimes(times, original);
  EXPECT_EQ(DetectTrajectoryFormat(poses), TrajectoryFormat::kKitti);
  TrajectoryReadOptions options;
  options.kitti_times_ns = ReadKittiTimes(times);
  ExpectSamePoses(original, ReadTrajectory(poses, options), true);
  // Without times: index / 10 Hz.
  const Trajectory untimed = ReadKitti(poses);
  ExpectSamePoses(original, untimed, false);
  EXPECT_EQ(untimed[0].t_ns, 0);
  EXPECT_EQ(untimed[7].t_ns, 700'000'000);
  EXPECT_EQ(ReadKitti(poses, {}, 20.0)[3].t_ns, 150'000'000);
}

TEST(TrajectoryIo, SecondsParseToExactNanoseconds) {
  EXPECT_EQ(ParseSecondsToNs("1.403715529112143517e+09"), 1'403'715'529'112'143'517);
  EXPECT_EQ(ParseSecondsToNs("1311868164.363181"), 1'311'868'164'363'181'000);
  EXPECT_EQ(ParseSecondsToNs("1.038752e-01"), 103'875'200);
  EXPECT_EQ(ParseSecondsToNs("-1.5"), -1'500'000'000);
  EXPECT_EQ(ParseSecondsToNs("+.25"), 250'000'000);
  EXPECT_EQ(ParseSecondsToNs("0.0000000005"), 1);  // half a nanosecond rounds away from zero
  EXPECT_EQ(ParseSecondsToNs("0.0000000004999"), 0);
  EXPECT_EQ(ParseSecondsToNs("12"), 12'000'000'000);
  EXPECT_EQ(ParseSecondsToNs("0e0"), 0);
  EXPECT_FALSE(ParseSecondsToNs("abc"));
  EXPECT_FALSE(ParseSecondsToNs("1.2.3"));
  EXPECT_FALSE(ParseSecondsToNs("1e"));
  EXPECT_FALSE(ParseSecondsToNs("."));
  EXPECT_FALSE(ParseSecondsToNs("nan"));
  EXPECT_FALSE(ParseSecondsToNs("1e400"));
  EXPECT_FALSE(ParseSecondsToNs("9300000000"));  // beyond int64 nanoseconds
  EXPECT_EQ(FormatNsAsSeconds(-1), "-0.000000001");
  EXPECT_EQ(FormatNsAsSeconds(1'311'868'164'363'181'000), "1311868164.363181000");
}

// ---- Real files ----

TEST(TrajectoryIo, ReadsEurocCsvGroundTruth) {
  const fs::path path = testing::DatasetsDir() / "trajectories/V102_groundtruth.csv";
  EXPECT_EQ(DetectTrajectoryFormat(path), TrajectoryFormat::kEuroc);
  const Trajectory gt = ReadTrajectory(path);
  ASSERT_EQ(gt.size(), 16702u);
  EXPECT_EQ(gt[0].t_ns, 1'403'715'524'907'143'168);
  EXPECT_NEAR(gt[0].T_world_cam.translation().x(), 0.515356, 1e-15);
  const Eigen::Quaterniond q(gt[0].T_world_cam.linear());
  EXPECT_NEAR(std::abs(q.w()), Eigen::Vector4d(0.161996, 0.789985, -0.205376, 0.554528).normalized()[0], 1e-12);
}

TEST(TrajectoryIo, ReadsTumFilesWithComments) {
  const fs::path path = testing::DatasetsDir() / "trajectories/fr2_desk_groundtruth.txt";
  EXPECT_EQ(DetectTrajectoryFormat(path), TrajectoryFormat::kTum);
  const Trajectory gt = ReadTrajectory(path);
  ASSERT_EQ(gt.size(), 20957u);
  EXPECT_EQ(gt[0].t_ns, 1'311'868'163'869'700'000);
  EXPECT_EQ(ReadTrajectory(testing::DatasetsDir() / "trajectories/V102.txt").size(), 807u);
}

TEST(TrajectoryIo, ReadsKittiPosesAndTimes) {
  const fs::path kitti = testing::DatasetsDir() / "kitti";
  EXPECT_EQ(DetectTrajectoryFormat(kitti / "poses/07.txt"), TrajectoryFormat::kKitti);
  TrajectoryReadOptions options;
  options.kitti_times_ns = ReadKittiTimes(kitti / "sequences/07/times.txt");
  const Trajectory gt = ReadTrajectory(kitti / "poses/07.txt", options);
  ASSERT_EQ(gt.size(), 160u);
  EXPECT_EQ(gt[1].t_ns, 103'875'200);
  EXPECT_NEAR(gt[1].T_world_cam.translation().z(), 0.09154274, 1e-15);
  // Times of another sequence do not fit.
  options.kitti_times_ns = ReadKittiTimes(kitti / "sequences/06/times.txt");
  const std::string message = ErrorOf([&] { (void)ReadTrajectory(kitti / "poses/07.txt", options); });
  EXPECT_NE(message.find("07.txt: 160 poses but 51 timestamps"), std::string::npos) << message;
}

// ---- Errors name file and line ----

TEST(TrajectoryIo, KittiParseErrorNamesFileAndLine) {
  std::string text;
  for (int i = 0; i < 16; ++i) text += "1 0 0 0 0 1 0 0 0 0 1 " + std::to_string(i) + "\n";
  text += "1 0 0 0 0 1 0 0 0 0 1\n";
  const fs::path path = WriteText("poses.txt", text);
  const std::string message = ErrorOf([&] { (void)ReadKitti(path); });
  EXPECT_NE(message.find("poses.txt:17: expected 12 numbers"), std::string::npos) << message;
  EXPECT_NE(message.find("got 11"), std::string::npos) << message;
}

TEST(TrajectoryIo, TumParseErrorsNameFileLineAndProblem) {
  const std::string good = "1.0 0 0 0 0 0 0 1\n";
  struct Case {
    std::string line, expected;
  };
  const Case cases[] = {
      {"2.0 0 0 0 0 0 1\n", "bad.txt:3: expected 8 numbers"},
      {"2.0 0 abc 0 0 0 0 1\n", "bad.txt:3: ty 'abc' is not a finite number"},
      {"2.0 0 0 0 0 0 0 nan\n", "bad.txt:3: qw 'nan' is not a finite number"},
      {"x 0 0 0 0 0 0 1\n", "bad.txt:3: timestamp 'x' is not a number"},
      {"2.0 0 0 0 0 0 0 0\n", "bad.txt:3: zero quaternion"},
  };
  for (const Case& c : cases) {
    const fs::path path = WriteText("bad.txt", "# header\n" + good + c.line + good);
    const std::string message = ErrorOf([&] { (void)ReadTum(path); });
    EXPECT_NE(message.find(c.expected), std::string::npos) << c.line << " -> " << message;
  }
}

TEST(TrajectoryIo, KittiRejectsWhatIsNoRotation) {
  const fs::path path = WriteText("scaled.txt", "2 0 0 0 0 2 0 0 0 0 2 0\n");
  EXPECT_NE(ErrorOf([&] { (void)ReadKitti(path); }).find("scaled.txt:1: the left 3x3 block is not a rotation"),
            std::string::npos);
  const fs::path inf = WriteText("inf.txt", "1 0 0 inf 0 1 0 0 0 0 1 0\n");
  EXPECT_NE(ErrorOf([&] { (void)ReadKitti(inf); }).find("inf.txt:1: value 'inf' is not a finite number"),
            std::string::npos);
}

TEST(TrajectoryIo, EurocParseErrorsNameFileAndLine) {
  const std::string header = "#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z\n";
  const fs::path short_line = WriteText("gt.csv", header + "100,1,2,3,1,0,0,0\n200,1,2,3,1,0,0\n");
  EXPECT_NE(ErrorOf([&] { (void)ReadEuroc(short_line); }).find("gt.csv:3: expected at least 8"), std::string::npos);
  const fs::path float_time = WriteText("gt2.csv", header + "1.5,1,2,3,1,0,0,0\n");
  EXPECT_NE(ErrorOf([&] { (void)ReadEuroc(float_time); }).find("gt2.csv:2: timestamp '1.5' is not an integer"),
            std::string::npos);
  // A header without '#' is skipped; extra columns are ignored.
  const fs::path plain = WriteText("gt3.csv", "timestamp,x,y,z,qw,qx,qy,qz,v\n100, 1, 2, 3, 1, 0, 0, 0, 9\n");
  const Trajectory t = ReadTrajectory(plain);
  ASSERT_EQ(t.size(), 1u);
  EXPECT_EQ(t[0].t_ns, 100);
  EXPECT_EQ(t[0].T_world_cam.translation(), Eigen::Vector3d(1, 2, 3));
}

TEST(TrajectoryIo, EmptyAndMissingFilesAreErrorsNamingTheFile) {
  const fs::path empty = WriteText("empty.txt", "");
  const fs::path comments = WriteText("comments.txt", "# nothing\n\n   \n");
  for (const fs::path& path : {empty, comments}) {
    for (auto format :
         {TrajectoryFormat::kAuto, TrajectoryFormat::kTum, TrajectoryFormat::kKitti, TrajectoryFormat::kEuroc}) {
      TrajectoryReadOptions options;
      options.format = format;
      const std::string message = ErrorOf([&] { (void)ReadTrajectory(path, options); });
      EXPECT_NE(message.find(path.string() + ": no poses"), std::string::npos) << message;
    }
    EXPECT_NE(ErrorOf([&] { (void)ReadKittiTimes(path); }).find(path.filename().string()), std::string::npos);
  }
  const std::string header_only = ErrorOf([&] { (void)ReadEuroc(WriteText("h.csv", "timestamp,x,y,z,a,b,c,d\n")); });
  EXPECT_NE(header_only.find("h.csv: no poses"), std::string::npos) << header_only;
  const std::string missing = ErrorOf([&] { (void)ReadTrajectory(TempDir() / "missing.txt"); });
  EXPECT_NE(missing.find("missing.txt: cannot open"), std::string::npos) << missing;
}

// ---- Quaternions and detection ----

TEST(TrajectoryIo, NonUnitQuaternionsAreNormalized) {
  const fs::path path = WriteText("scaled_q.txt", "0.5 1 2 3 0 0 0 2\n1.5 1 2 3 0 0 3 3\n");
  const Trajectory t = ReadTum(path);
  ASSERT_EQ(t.size(), 2u);
  EXPECT_EQ(t[0].t_ns, 500'000'000);
  EXPECT_LT((t[0].T_world_cam.linear() - Eigen::Matrix3d::Identity()).norm(), 1e-15);
  EXPECT_LT(
      (t[1].T_world_cam.linear() - Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix()).norm(),
      1e-15);
}

TEST(TrajectoryIo, DetectsFormatsAndExplainsFailures) {
  EXPECT_EQ(DetectTrajectoryFormat(WriteText("a.txt", "# c\n1 0 0 0 0 0 0 1\n")), TrajectoryFormat::kTum);
  EXPECT_EQ(DetectTrajectoryFormat(WriteText("b.csv", "1.5,0,0,0,0,0,0,1\n")), TrajectoryFormat::kTum);
  EXPECT_EQ(DetectTrajectoryFormat(WriteText("c.csv", "#t\n100,0,0,0,1,0,0,0,5,5\n")), TrajectoryFormat::kEuroc);
  EXPECT_EQ(DetectTrajectoryFormat(WriteText("d.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n")), TrajectoryFormat::kKitti);
  const std::string message = ErrorOf([&] { (void)DetectTrajectoryFormat(WriteText("e.txt", "\n1 2 3\n")); });
  EXPECT_NE(message.find("e.txt:2: cannot detect the trajectory format from 3 columns"), std::string::npos) << message;
  // An explicit format wins over detection.
  TrajectoryReadOptions options;
  options.format = TrajectoryFormat::kKitti;
  EXPECT_NE(ErrorOf([&] {
              (void)ReadTrajectory(WriteText("f.txt", "1 0 0 0 0 0 0 1\n"), options);
            }).find("f.txt:1: expected 12 numbers"),
            std::string::npos);
  EXPECT_EQ(ParseTrajectoryFormat("euroc"), TrajectoryFormat::kEuroc);
  EXPECT_FALSE(ParseTrajectoryFormat("csv"));
}

TEST(TrajectoryIo, WritersRefuseBadInput) {
  EXPECT_THROW(WriteTum(TempDir() / "none.txt", {}), Error);
  Trajectory nan_pose(1);
  nan_pose[0].T_world_cam.translation().x() = std::nan("");
  EXPECT_THROW(WriteKitti(TempDir() / "nan.txt", nan_pose), Error);
  EXPECT_NE(
      ErrorOf([&] { WriteTum(TempDir() / "no_dir/x.txt", RandomTrajectory(2, 1)); }).find("cannot open for writing"),
      std::string::npos);
}

}  // namespace
}  // namespace flatslam
