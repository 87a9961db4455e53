#include "ecs/map.h"

#include <random>

#include <gtest/gtest.h>

#include "core/error.h"

namespace flatslam {
namespace {

KeyFrame MakeKeyFrame(size_t keypoints, double x) {
  KeyFrame kf;
  kf.resize(keypoints);
  kf.T_cam_world.translation() = Eigen::Vector3d(-x, 0, 0);
  for (size_t i = 0; i < keypoints; ++i) kf.descriptor.mutable_data()[i] = {i, i * 3, ~i, i ^ 0xff};
  return kf;
}

// Keyframes 0..n-1 all see points 0..m-1 at keypoint index = point index.
struct Fixture {
  Map map;
  std::vector<KeyFrameHandle> kfs;
  std::vector<PointHandle> pts;
  Fixture(size_t n, size_t m) {
    for (size_t i = 0; i < n; ++i) kfs.push_back(map.AddKeyFrame(MakeKeyFrame(m, static_cast<double>(i))));
    for (size_t j = 0; j < m; ++j) {
      pts.push_back(map.AddPoint(Eigen::Vector3d(0, 0, 5.0 + j), kfs[0]));
      for (size_t i = 0; i < n; ++i) map.AddObservation(pts[j], kfs[i], static_cast<uint32_t>(j));
    }
    for (KeyFrameHandle kf : kfs) map.UpdateCovisibility(kf);
  }
};

// Moving a map into another frame with a scale (a monocular map joining a merged one): every
// point stays where every camera sees it (same direction, depth scaled), camera centres and points
// move by the similarity, distance ranges scale.
TEST(Map, MoveFrameWithAScaleKeepsWhatEveryCameraSees) {
  Fixture f(3, 4);
  f.map.keyframe(f.kfs[1]).T_cam_world.linear() =
      Eigen::AngleAxisd(0.3, Eigen::Vector3d(0, 1, 0.2).normalized()).toRotationMatrix();
  for (PointHandle p : f.pts) f.map.UpdatePointStats(p, MapScales{});
  const Map before = f.map;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(1.1, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(4, 0.5, -7);
  const double s = 2.5;
  f.map.MoveFrame(T, s);
  auto moved = [&](const Eigen::Vector3d& X) -> Eigen::Vector3d { return s * (T.linear() * X) + T.translation(); };
  for (KeyFrameHandle kf : f.kfs) {
    const KeyFrame& a = before.keyframe(kf);
    const KeyFrame& b = f.map.keyframe(kf);
    EXPECT_LT((b.camera_center() - moved(a.camera_center())).norm(), 1e-12);
    for (PointHandle p : f.pts) {
      const Eigen::Vector3d Xa = a.T_cam_world * before.point(p).position;
      const Eigen::Vector3d Xb = b.T_cam_world * f.map.point(p).position;
      EXPECT_LT((Xb - s * Xa).norm(), 1e-12);  // camera-frame coordinates scale
    }
  }
  for (PointHandle p : f.pts) {
    EXPECT_LT((f.map.point(p).position - moved(before.point(p).position)).norm(), 1e-12);
    EXPECT_LT((f.map.point(p).normal - T.linear() * before.point(p).normal).norm(), 1e-12);
    EXPECT_FLOAT_EQ(f.map.point(p).max_distance, static_cast<float>(s * before.point(p).max_distance));
    EXPECT_FLOAT_EQ(f.map.point(p).min_distance, static_cast<float>(s * before.point(p).min_distance));
  }
}

TEST(Map, ObservationsAreMirrored) {
  Fixture f(3, 20);
  EXPECT_EQ(f.map.Validate(), "");
  EXPECT_EQ(f.map.point(f.pts[4]).observations.size(), 3u);
  EXPECT_EQ(f.map.keyframe(f.kfs[2]).points[4], f.pts[4]);
  EXPECT_THROW(f.map.AddObservation(f.pts[4], f.kfs[2], 5), Error);  // keypoint taken
}

TEST(Map, ErasePointClearsSlotsAndStaysStale) {
  Fixture f(3, 20);
  f.map.ErasePoint(f.pts[7]);
  for (KeyFrameHandle kf : f.kfs) EXPECT_TRUE(f.map.keyframe(kf).points[7].is_null());
  EXPECT_FALSE(f.map.points().contains(f.pts[7]));
  EXPECT_THROW((void)f.map.point(f.pts[7]), Error);
  // The slot is reused by the next point, under a new generation.
  const PointHandle fresh = f.map.AddPoint(Eigen::Vector3d::Zero(), f.kfs[0]);
  EXPECT_EQ(fresh.index(), f.pts[7].index());
  EXPECT_NE(fresh, f.pts[7]);
  EXPECT_FALSE(f.map.points().contains(f.pts[7]));
  EXPECT_EQ(f.map.Validate(), "");
}

TEST(Map, EraseObservationErasesPointBelowMinimum) {
  Fixture f(2, 10);
  EXPECT_TRUE(f.map.EraseObservation(f.pts[0], f.kfs[1]));  // one sighting left < 2
  EXPECT_FALSE(f.map.points().contains(f.pts[0]));
  EXPECT_TRUE(f.map.keyframe(f.kfs[0]).points[0].is_null());
  EXPECT_EQ(f.map.Validate(), "");
}

TEST(Map, CovisibilityIsSymmetricAndSorted) {
  Map map;
  const KeyFrameHandle a = map.AddKeyFrame(MakeKeyFrame(60, 0));
  const KeyFrameHandle b = map.AddKeyFrame(MakeKeyFrame(60, 1));
  const KeyFrameHandle c = map.AddKeyFrame(MakeKeyFrame(60, 2));
  for (uint32_t j = 0; j < 60; ++j) {
    const PointHandle p = map.AddPoint(Eigen::Vector3d(0, 0, 4), a);
    map.AddObservation(p, a, j);
    if (j < 40) map.AddObservation(p, b, j);
    if (j < 20) map.AddObservation(p, c, j);
  }
  for (KeyFrameHandle kf : {a, b, c}) map.UpdateCovisibility(kf);
  const KeyFrame& ka = map.keyframe(a);
  ASSERT_EQ(ka.covisible.size(), 2u);
  EXPECT_EQ(ka.covisible[0], std::make_pair(b, 40));
  EXPECT_EQ(ka.covisible[1], std::make_pair(c, 20));
  EXPECT_EQ(map.BestCovisible(c, 1), std::vector<KeyFrameHandle>{a});  // ties broken by handle
  EXPECT_EQ(map.keyframe(b).parent, a);
  EXPECT_EQ(map.Validate(), "");
}

TEST(Map, EraseKeyFrameReparentsChildrenAndFreesItsSlot) {
  Fixture f(4, 30);
  // Chain: each keyframe's parent is the strongest earlier neighbour (kf 0 for all here).
  f.map.EraseKeyFrame(f.kfs[0]);
  EXPECT_FALSE(f.map.keyframes().contains(f.kfs[0]));
  EXPECT_EQ(f.map.Validate(), "");
  for (size_t i = 1; i < 4; ++i) {
    const KeyFrame& kf = f.map.keyframe(f.kfs[i]);
    for (const auto& link : kf.covisible) EXPECT_NE(link.first, f.kfs[0]);
  }
  const size_t slots = f.map.keyframes().slot_count();
  const KeyFrameHandle again = f.map.AddKeyFrame(MakeKeyFrame(5, 9));
  EXPECT_EQ(f.map.keyframes().slot_count(), slots);  // reused, not grown
  EXPECT_NE(again, f.kfs[0]);
}

TEST(Map, ReplacePointMergesObservations) {
  Map map;
  const KeyFrameHandle a = map.AddKeyFrame(MakeKeyFrame(4, 0));
  const KeyFrameHandle b = map.AddKeyFrame(MakeKeyFrame(4, 1));
  const KeyFrameHandle c = map.AddKeyFrame(MakeKeyFrame(4, 2));
  const PointHandle keep = map.AddPoint(Eigen::Vector3d(0, 0, 3), a);
  const PointHandle dup = map.AddPoint(Eigen::Vector3d(0, 0, 3.01), b);
  map.AddObservation(keep, a, 0);
  map.AddObservation(keep, b, 1);
  map.AddObservation(dup, b, 2);  // b sees both: its dup slot is dropped
  map.AddObservation(dup, c, 3);
  map.ReplacePoint(dup, keep);
  EXPECT_FALSE(map.points().contains(dup));
  const MapPoint& p = map.point(keep);
  EXPECT_EQ(p.observations.size(), 3u);
  EXPECT_EQ(map.keyframe(c).points[3], keep);
  EXPECT_TRUE(map.keyframe(b).points[2].is_null());
  EXPECT_EQ(map.Validate(), "");
}

TEST(Map, BindMatchedPointsFusesOrObserves) {
  // Keyframes 0 and 1 see points 0..5 at keypoints 0..5; a third keyframe joins that place.
  Fixture f(2, 6);
  const KeyFrameHandle kf = f.map.AddKeyFrame(MakeKeyFrame(6, 3.0));
  const PointHandle own = f.map.AddPoint(Eigen::Vector3d(1, 0, 5), kf);  // its own copy of point 0
  f.map.AddObservation(own, kf, 0);
  f.map.AddObservation(f.pts[3], kf, 4);  // already sees point 3, at another keypoint
  const PointHandle gone = f.map.AddPoint(Eigen::Vector3d(2, 0, 5), kf);
  f.map.ErasePoint(gone);
  const std::vector<PointHandle> matched = {f.pts[0], f.pts[1], PointHandle::null(), f.pts[3], PointHandle::null(),
                                            gone};
  f.map.BindMatchedPoints(kf, matched);
  const KeyFrame& k = f.map.keyframe(kf);
  EXPECT_FALSE(f.map.points().contains(own));  // fused into point 0
  EXPECT_EQ(k.points[0], f.pts[0]);
  EXPECT_EQ(k.points[1], f.pts[1]);    // a free keypoint now observes point 1
  EXPECT_TRUE(k.points[3].is_null());  // point 3 is seen at keypoint 4 already
  EXPECT_EQ(k.points[4], f.pts[3]);
  EXPECT_TRUE(k.points[5].is_null());  // an erased match binds nothing
  EXPECT_EQ(f.map.point(f.pts[0]).observations.size(), 3u);
  EXPECT_EQ(f.map.Validate(), "");
}

TEST(Map, PointStatsFromObservations) {
  Fixture f(3, 5);
  MapScales scales;
  f.map.UpdatePointStats(f.pts[0], scales);
  const MapPoint& p = f.map.point(f.pts[0]);
  EXPECT_NEAR(p.normal.norm(), 1.0, 1e-12);
  EXPECT_GT(p.normal.z(), 0.9);            // cameras sit at z = 0 looking at z = 5
  EXPECT_NEAR(p.max_distance, 5.0, 1e-5);  // reference kf 0 at the origin, octave 0
  EXPECT_NEAR(p.min_distance, 5.0 / std::pow(1.2, 7), 1e-4);
}

// The observation of p with the least median Hamming distance to all of p's observations (the
// first such, in observation order), every median computed in full.
Descriptor LeastMedianDescriptor(const Map& map, PointHandle p) {
  size_t best = 0;
  int best_median = 1 << 30;
  const auto& seen = map.point(p).observations;
  for (size_t i = 0; i < seen.size(); ++i) {
    std::vector<int> row;
    for (const Observation& o : seen)
      row.push_back(DescriptorDistance(map.keyframe(seen[i].keyframe).descriptor[seen[i].keypoint],
                                       map.keyframe(o.keyframe).descriptor[o.keypoint]));
    std::sort(row.begin(), row.end());
    if (row[(row.size() - 1) / 2] < best_median) {
      best_median = row[(row.size() - 1) / 2];
      best = i;
    }
  }
  return map.keyframe(seen[best].keyframe).descriptor[seen[best].keypoint];
}

// Keyframes 0..n-1 with one keypoint each, its descriptor drawn near a common one (a few bits
// flipped each), as one feature seen again looks.
std::vector<KeyFrameHandle> AddNoisyKeyFrames(Map& map, size_t n, std::mt19937_64& rng) {
  std::vector<KeyFrameHandle> kfs;
  const Descriptor common{rng(), rng(), rng(), rng()};
  for (size_t i = 0; i < n; ++i) {
    KeyFrame kf = MakeKeyFrame(1, static_cast<double>(i));
    Descriptor d = common;
    for (int flip = static_cast<int>(rng() % 60); flip > 0; --flip) d[rng() % 4] ^= 1ull << (rng() % 64);
    kf.descriptor.mutable_data()[0] = d;
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  return kfs;
}

// A point's descriptor is the one of its observations with the least median Hamming distance to
// all of them (the first such, on ties), for points seen by few and by many keyframes.
TEST(Map, APointsDescriptorIsItsObservationWithTheLeastMedianDistance) {
  std::mt19937_64 rng(11);
  for (size_t n : {1u, 2u, 3u, 8u, 31u, 120u}) {
    Map map;
    const std::vector<KeyFrameHandle> kfs = AddNoisyKeyFrames(map, n, rng);
    const PointHandle p = map.AddPoint(Eigen::Vector3d(0, 0, 5), kfs[0]);
    for (KeyFrameHandle kf : kfs) map.AddObservation(p, kf, 0);
    map.UpdatePointStats(p, MapScales{});
    EXPECT_EQ(map.point(p).descriptor, LeastMedianDescriptor(map, p)) << n << " observations";
  }
}

// UpdatePointStats chooses the descriptor again only when the observations changed: after each
// kind of change (an observation added, one erased, a keyframe erased, a point fused into this
// one) it is the one chosen from scratch, and a moved point gets its new viewing direction.
TEST(Map, APointsDescriptorFollowsEveryChangeOfItsObservations) {
  std::mt19937_64 rng(5);
  Map map;
  const std::vector<KeyFrameHandle> kfs = AddNoisyKeyFrames(map, 40, rng);
  const PointHandle p = map.AddPoint(Eigen::Vector3d(0, 0, 5), kfs[0]);
  for (size_t i = 0; i < 20; ++i) map.AddObservation(p, kfs[i], 0);
  map.UpdatePointStats(p, MapScales{});
  ASSERT_EQ(map.point(p).descriptor, LeastMedianDescriptor(map, p));
  const Descriptor before = map.point(p).descriptor;
  size_t changed = 0;
  auto check = [&](const char* what) {
    map.UpdatePointStats(p, MapScales{});
    EXPECT_EQ(map.point(p).descriptor, LeastMedianDescriptor(map, p)) << what;
    changed += map.point(p).descriptor != before;
  };
  // The observations chosen first, then the others: each erase changes the median set.
  for (size_t i = 0; i < 6; ++i) {
    const Descriptor chosen = map.point(p).descriptor;
    for (const Observation& o : map.point(p).observations)
      if (map.keyframe(o.keyframe).descriptor[0] == chosen) {
        map.EraseObservation(p, o.keyframe);
        break;
      }
    check("after erasing the chosen observation");
  }
  for (size_t i = 20; i < 30; ++i) {
    map.AddObservation(p, kfs[i], 0);
    check("after adding an observation");
  }
  map.EraseKeyFrame(map.point(p).observations[3].keyframe);
  check("after erasing an observing keyframe");
  const PointHandle other = map.AddPoint(Eigen::Vector3d(0, 0, 5), kfs[30]);
  for (size_t i = 30; i < 40; ++i) map.AddObservation(other, kfs[i], 0);
  map.UpdatePointStats(other, MapScales{});
  map.ReplacePoint(other, p);
  check("after a point was fused into it");
  EXPECT_GT(changed, 0u) << "the changes never moved the choice: the test exercises nothing";
  // Only the position changes: the viewing direction follows it.
  map.point(p).position = Eigen::Vector3d(0, 40, 5);
  check("after the point moved");
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  for (const Observation& o : map.point(p).observations)
    normal += (map.point(p).position - map.keyframe(o.keyframe).camera_center()).normalized();
  EXPECT_LT((map.point(p).normal - normal.normalized()).norm(), 1e-12);
}

TEST(Map, RandomChurnKeepsReferencesConsistentAndSlotsBounded) {
  std::mt19937_64 rng(7);
  Map map;
  std::vector<KeyFrameHandle> live;
  size_t max_slots = 0;
  for (int step = 0; step < 3000; ++step) {
    if (live.size() < 12 || rng() % 3 != 0) {
      const KeyFrameHandle kf = map.AddKeyFrame(MakeKeyFrame(40, step));
      // Each new keyframe sees some existing points and creates new ones.
      uint32_t k = 0;
      const auto handles = map.points().handles();
      std::vector<PointHandle> existing(handles.begin(), handles.end());
      std::shuffle(existing.begin(), existing.end(), rng);
      for (size_t i = 0; i < existing.size() && k < 20; ++i, ++k) map.AddObservation(existing[i], kf, k);
      for (; k < 40; ++k) {
        const PointHandle p = map.AddPoint(Eigen::Vector3d(1, 2, 3), kf);
        map.AddObservation(p, kf, k);
      }
      map.UpdateCovisibility(kf, 3);
      live.push_back(kf);
    } else {
      const size_t victim = rng() % live.size();
      map.EraseKeyFrame(live[victim]);
      live.erase(live.begin() + static_cast<long>(victim));
    }
    if (live.size() > 30) {  // steady state: a sliding window of keyframes
      map.EraseKeyFrame(live.front());
      live.erase(live.begin());
    }
    // Points seen by nobody are culled, as local mapping does.
    map.points().erase_if([](PointHandle, const MapPoint& p) { return p.observations.empty(); });
    if (step % 100 == 0) {
      ASSERT_EQ(map.Validate(), "") << "step " << step;
    }
    if (step > 1000) max_slots = std::max(max_slots, map.keyframes().slot_count());
  }
  EXPECT_EQ(map.Validate(), "");
  EXPECT_LE(max_slots, 40u);  // bounded by the window, not by the 3000 steps
}

}  // namespace
}  // namespace flatslam
