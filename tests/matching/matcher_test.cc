// The matcher's searches on hand-built scenes: map points with known descriptors, keypoints placed
// at their exact projections (descriptors a few bits off) among distractors, and the matches each
// search must (and must not) make.
#include "matching/matcher.h"

#include <algorithm>
#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "geometry/geometry_fixtures.h"

namespace flatslam {
namespace {

constexpr int kPoints = 120;

CameraGeometry Geometry() {
  CameraGeometry g;
  g.camera = testing::TestCamera();
  g.pyramid = ScalePyramid::Make(8, 1.2f);
  return g;
}

Descriptor RandomDescriptor(std::mt19937_64& rng) {
  return {rng(), rng(), rng(), rng()};
}

// The descriptor with `bits` of its bits flipped (distinct bits).
Descriptor Flip(Descriptor d, int bits, std::mt19937_64& rng) {
  std::vector<int> order(256);
  for (int i = 0; i < 256; ++i) order[i] = i;
  std::shuffle(order.begin(), order.end(), rng);
  for (int k = 0; k < bits; ++k) d[order[k] / 64] ^= uint64_t{1} << (order[k] % 64);
  return d;
}

// kPoints map points 4-8 m ahead of a keyframe at the origin that sees each one at keypoint j
// (octave 0, angle 0), with the point's descriptor its keyframe descriptor.
struct Scene {
  CameraGeometry g = Geometry();
  Map map;
  KeyFrameHandle kf;
  std::vector<PointHandle> points;
  std::vector<Descriptor> descriptors;
  std::mt19937_64 rng{7};

  Scene() {
    std::uniform_real_distribution<double> u(-1, 1);
    KeyFrame k;
    k.resize(kPoints);
    std::vector<Eigen::Vector3d> X;
    for (int j = 0; j < kPoints; ++j) {
      const double z = 6 + 2 * u(rng);
      X.emplace_back(0.55 * z * u(rng), 0.4 * z * u(rng), z);
      k.uv.mutable_data()[j] = Pixel(Eigen::Isometry3d::Identity(), X.back());
      descriptors.push_back(RandomDescriptor(rng));
      k.descriptor.mutable_data()[j] = descriptors.back();
    }
    kf = map.AddKeyFrame(std::move(k));
    for (int j = 0; j < kPoints; ++j) {
      points.push_back(map.AddPoint(X[j], kf));
      map.AddObservation(points[j], kf, static_cast<uint32_t>(j));
      map.UpdatePointStats(points[j], MapScales{});
    }
  }
  [[nodiscard]] Eigen::Vector2f Pixel(const Eigen::Isometry3d& T_cam_world, const Eigen::Vector3d& X) const {
    const Eigen::Vector3d Xc = T_cam_world * X;
    return Eigen::Vector2f(static_cast<float>(g.camera.fx * Xc.x() / Xc.z() + g.camera.cx),
                           static_cast<float>(g.camera.fy * Xc.y() / Xc.z() + g.camera.cy));
  }
  // A frame at T_cam_world: keypoint j sees point j (descriptor `noise_bits` off; points that
  // leave the image get a random pixel), then as many random distractors.
  [[nodiscard]] TrackedFrame FrameAt(const Eigen::Isometry3d& T_cam_world, int noise_bits) {
    TrackedFrame f;
    f.T_cam_world = T_cam_world;
    f.keypoints.resize(2 * kPoints);
    std::uniform_real_distribution<float> px(0, 1);
    for (int j = 0; j < kPoints; ++j) {
      f.keypoints.uv[j] = Pixel(T_cam_world, map.point(points[j]).position);
      f.keypoints.descriptor[j] = Flip(descriptors[j], noise_bits, rng);
    }
    for (int j = kPoints; j < 2 * kPoints; ++j) {
      f.keypoints.uv[j] = Eigen::Vector2f(639 * px(rng), 479 * px(rng));
      f.keypoints.descriptor[j] = RandomDescriptor(rng);
    }
    f.Prepare(g.camera.width, g.camera.height);
    return f;
  }
  // The same view as a keyframe (pose, pixels, descriptors) of no map yet.
  [[nodiscard]] KeyFrame KeyFrameAt(const Eigen::Isometry3d& T_cam_world, int noise_bits) {
    const TrackedFrame f = FrameAt(T_cam_world, noise_bits);
    KeyFrame k;
    k.resize(f.size());
    k.T_cam_world = T_cam_world;
    k.uv = f.keypoints.uv;
    k.descriptor = f.keypoints.descriptor;
    return k;
  }
};

Eigen::Isometry3d Moved(double x, double yaw_deg) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(yaw_deg * M_PI / 180, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(x, 0, 0);
  return T;
}

// Keypoints matched to the point they see, and to any other point.
std::pair<int, int> Score(const TrackedFrame& f, const Scene& s) {
  int right = 0, wrong = 0;
  for (size_t k = 0; k < f.size(); ++k) {
    if (f.points[k].is_null()) continue;
    if (k < kPoints && f.points[k] == s.points[k])
      ++right;
    else
      ++wrong;
  }
  return {right, wrong};
}

TEST(MatchByProjection, FindsThePointsAtThePredictedPose) {
  Scene s;
  const Eigen::Isometry3d T = Moved(-0.2, 2);
  TrackedFrame f = s.FrameAt(T, 10);
  const KeyFrame& kf = s.map.keyframe(s.kf);
  const int n = MatchByProjection(f, kf, s.map, s.g, 7, MatcherOptions{});
  const auto [right, wrong] = Score(f, s);
  EXPECT_EQ(n, right + wrong);
  EXPECT_GE(right, 100);  // of the points still in view
  EXPECT_EQ(wrong, 0);
  // A second search adds nothing: matched keypoints and points are taken.
  EXPECT_EQ(MatchByProjection(f, kf, s.map, s.g, 7, MatcherOptions{}), 0);
}

TEST(MatchByProjection, MissesWhenThePoseIsOffByMoreThanTheRadius) {
  Scene s;
  TrackedFrame f = s.FrameAt(Moved(-0.2, 2), 10);
  f.T_cam_world = Moved(-0.2, 6);  // 4 degrees off: about 35 px
  EXPECT_LT(MatchByProjection(f, s.map.keyframe(s.kf), s.map, s.g, 7, MatcherOptions{}), 10);
}

TEST(MatchByProjection, DescriptorsBeyondTheGateDoNotMatch) {
  Scene s;
  TrackedFrame f = s.FrameAt(Moved(-0.2, 2), 110);  // over max_distance (100)
  EXPECT_EQ(MatchByProjection(f, s.map.keyframe(s.kf), s.map, s.g, 7, MatcherOptions{}), 0);
}

TEST(MatchLocalPoints, MatchesPointsInTheFrustumAndReportsThem) {
  Scene s;
  TrackedFrame f = s.FrameAt(Moved(0.3, -3), 8);
  std::vector<PointHandle> seen;
  const int n = MatchLocalPoints(f, s.map, s.points, s.g, 1.0f, MatcherOptions{}, &seen);
  const auto [right, wrong] = Score(f, s);
  EXPECT_EQ(n, right + wrong);
  EXPECT_GE(right, 100);
  EXPECT_EQ(wrong, 0);
  EXPECT_GE(seen.size(), static_cast<size_t>(right));
  // Looking away, nothing is in the frustum.
  TrackedFrame away = s.FrameAt(Moved(0, 0), 8);
  away.T_cam_world = Moved(0, 180);
  seen.clear();
  EXPECT_EQ(MatchLocalPoints(away, s.map, s.points, s.g, 1.0f, MatcherOptions{}, &seen), 0);
  EXPECT_TRUE(seen.empty());
}

TEST(MatchForInitialization, PairsKeypointsWithinTheWindow) {
  Scene s;
  TrackedFrame first = s.FrameAt(Eigen::Isometry3d::Identity(), 0);
  TrackedFrame second = s.FrameAt(Moved(-0.3, -1), 6);
  const auto pairs = MatchForInitialization(first, second, 100.0f, MatcherOptions{});
  int right = 0;
  for (const auto& [i1, i2] : pairs) right += i1 == i2 && i1 < static_cast<uint32_t>(kPoints);
  EXPECT_GE(right, 100);
  EXPECT_LE(static_cast<int>(pairs.size()) - right, 2);  // distractors rarely pair
  // A small window pairs only keypoints that moved less than it.
  int within = 0;
  for (int j = 0; j < kPoints; ++j)
    within += (first.keypoints.uv[j] - second.keypoints.uv[j]).cwiseAbs().maxCoeff() <= 5.0f;
  const auto near = MatchForInitialization(first, second, 5.0f, MatcherOptions{});
  EXPECT_LT(within, 100);
  EXPECT_LE(static_cast<int>(near.size()), within + 2);
  for (const auto& [i1, i2] : near) {
    if (i1 == i2) {
      EXPECT_LE((first.keypoints.uv[i1] - second.keypoints.uv[i2]).cwiseAbs().maxCoeff(), 5.0f);
    }
  }
}

TEST(MatchBySimilarity, BindsPointsThroughAScaledPose) {
  Scene s;
  // A keyframe of another map whose units are twice ours (a monocular map): S_cw maps our world
  // into its camera, so its camera coordinates are twice the true ones and the pixels the same.
  const Eigen::Isometry3d T = Moved(-0.25, 1.5);
  const KeyFrame query = s.KeyFrameAt(T, 8);
  Similarity3 S_cw = Similarity3::FromIsometry(T);
  S_cw.s = 2;
  S_cw.t *= 2;
  std::vector<PointHandle> matched(query.size(), PointHandle::null());
  const int n = MatchBySimilarity(query, S_cw, s.points, s.map, s.g, 10.0f, MatcherOptions{}, &matched);
  int right = 0;
  for (int j = 0; j < kPoints; ++j) right += matched[j] == s.points[j];
  EXPECT_EQ(n, right);
  EXPECT_GE(right, 100);
  // Entries already set are kept.
  std::vector<PointHandle> preset(query.size(), PointHandle::null());
  preset[0] = s.points[5];
  MatchBySimilarity(query, S_cw, s.points, s.map, s.g, 10.0f, MatcherOptions{}, &preset);
  EXPECT_EQ(preset[0], s.points[5]);
}

TEST(FusePoints, MergesDuplicatesAndAddsMissedObservations) {
  Scene s;
  // A second keyframe sees every point; half of them it took as new duplicate points, the other
  // half it did not match at all.
  const KeyFrameHandle kf2 = s.map.AddKeyFrame(s.KeyFrameAt(Moved(-0.3, 1), 0));
  std::vector<PointHandle> duplicates;
  for (int j = 0; j < kPoints; j += 2) {
    const PointHandle d = s.map.AddPoint(s.map.point(s.points[j]).position + Eigen::Vector3d(0.001, 0, 0), kf2);
    s.map.AddObservation(d, kf2, static_cast<uint32_t>(j));
    s.map.UpdatePointStats(d, MapScales{});
    duplicates.push_back(d);
  }
  const size_t before = s.map.points().size();
  const int fused = FusePoints(s.map, kf2, s.points, s.g, MatcherOptions{});
  EXPECT_GE(fused, 100);
  EXPECT_LE(s.map.points().size(), before - 50);  // the duplicates merged away
  int both = 0;
  for (PointHandle p : s.map.keyframe(kf2).points)
    if (const MapPoint* point = s.map.points().try_get(p)) both += point->observations.size() == 2;
  EXPECT_GE(both, 100);
  EXPECT_EQ(s.map.Validate(), "");
}

TEST(FundamentalBetween, ProjectionsSatisfyTheEpipolarConstraint) {
  Scene s;
  KeyFrame other;
  other.T_cam_world = Moved(-0.4, 3);
  const Eigen::Matrix3d F = FundamentalBetween(s.map.keyframe(s.kf), other, s.g.camera);
  for (int j = 0; j < kPoints; ++j) {
    const Eigen::Vector3d X = s.map.point(s.points[j]).position;
    const Eigen::Vector2f p1 = s.Pixel(Eigen::Isometry3d::Identity(), X), p2 = s.Pixel(other.T_cam_world, X);
    const Eigen::Vector3d x1(p1.x(), p1.y(), 1), x2(p2.x(), p2.y(), 1);
    const Eigen::Vector3d line = F * x1;
    EXPECT_LT(std::abs(x2.dot(line)) / line.head<2>().norm(), 1e-3) << "point " << j;  // pixels
  }
}

}  // namespace
}  // namespace flatslam
