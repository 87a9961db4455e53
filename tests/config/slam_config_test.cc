#include "config/slam_config.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "core/error.h"
#include "geometry/geometry_fixtures.h"
#include "merge/map_merge.h"
#include "slam/session.h"

namespace flatslam {
namespace {

std::filesystem::path WriteFile(const std::string& name, const std::string& text) {
  const auto path = std::filesystem::temp_directory_path() / ("flatslam_config_test_" + name);
  std::ofstream(path) << text;
  return path;
}

std::string ErrorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(SlamConfig, SetsEveryKindOfOptionByName) {
  SlamOptions o;
  SetSlamOption(&o, "orb.features", "2500");
  SetSlamOption(&o, " stereo.outlier_factor ", " 1.5 ");
  SetSlamOption(&o, "close_depth_baselines", "30");
  SetSlamOption(&o, "matcher.check_orientation", "false");
  SetSlamOption(&o, "local_keyframes", "12");
  SetSlamOption(&o, "seed", "18446744073709551615");
  SetSlamOption(&o, "bundle_adjustment.solver", "ceres");
  EXPECT_EQ(o.orb.features, 2500);
  EXPECT_FLOAT_EQ(o.stereo.outlier_factor, 1.5f);
  EXPECT_DOUBLE_EQ(o.close_depth_baselines, 30);
  EXPECT_FALSE(o.matcher.check_orientation);
  EXPECT_EQ(o.local_keyframes, 12u);
  EXPECT_EQ(o.seed, 18446744073709551615ull);
  EXPECT_EQ(o.bundle_adjustment.solver, BundleAdjustmentOptions::Solver::kCeres);
  ApplySlamSetting(&o, "bundle_adjustment.solver=schur_lm");
  EXPECT_EQ(o.bundle_adjustment.solver, BundleAdjustmentOptions::Solver::kSchurLm);
}

// Related values change together: --set checks the ranges after its last setting, so lowering
// both FAST thresholds works with the main one first (a check after each value refused it: 6
// under the default floor of 7).
TEST(SlamConfig, SetChecksRangesOnceEverySettingIsIn) {
  SlamOptions o;
  ApplySlamOptionSources(&o, nullptr, Sensor::kStereo, 0, "", {"orb.fast_threshold=6,orb.min_fast_threshold=2"});
  EXPECT_EQ(o.orb.fast_threshold, 6);
  EXPECT_EQ(o.orb.min_fast_threshold, 2);
  SlamOptions p;
  ApplySlamOptionSources(&p, nullptr, Sensor::kStereo, 0, "", {"orb.fast_threshold=6", "orb.min_fast_threshold=2"});
  EXPECT_EQ(p.orb.min_fast_threshold, 2);
  // What stays out of range when all are in is refused, naming every setting and the requirement.
  SlamOptions q;
  const std::string error = ErrorOf(
      [&] { ApplySlamOptionSources(&q, nullptr, Sensor::kStereo, 0, "", {"orb.fast_threshold=6,local_keyframes=3"}); });
  EXPECT_NE(error.find("--set orb.fast_threshold=6,local_keyframes=3: out of range (orb: min_fast_threshold"),
            std::string::npos)
      << error;
}

TEST(SlamConfig, ErrorsNameTheKeyAndWhatWasExpected) {
  SlamOptions o;
  EXPECT_NE(ErrorOf([&] { SetSlamOption(&o, "orb.featurez", "1"); }).find("unknown option 'orb.featurez'"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { SetSlamOption(&o, "orb.features", "12x"); }).find("orb.features needs an integer, got '12x'"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { SetSlamOption(&o, "local_keyframes", "-3"); }).find("non-negative integer"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { SetSlamOption(&o, "loop_closing", "maybe"); }).find("true or false"), std::string::npos);
  EXPECT_NE(ErrorOf([&] { SetSlamOption(&o, "pose.chi2_mono", "nan"); }).find("a real number"), std::string::npos);
  EXPECT_NE(ErrorOf([&] { ApplySlamSetting(&o, "orb.features"); }).find("expected KEY=VALUE"), std::string::npos);
  // A value that parses but breaks an option's range is refused, naming the requirement it breaks.
  EXPECT_NE(
      ErrorOf([&] { ApplySlamSetting(&o, "orb.features=-5"); }).find("out of range (orb: features >= 1 does not hold)"),
      std::string::npos);
  EXPECT_EQ(o.orb.features, -5);  // the caller's options are not used after a throw
}

// Every options struct names the first field it finds out of range; nested ones by their prefix.
TEST(SlamConfig, OptionProblemsNameTheField) {
  SlamOptions o;
  EXPECT_EQ(o.Problem(), "");
  o.orb.features = 0;  // derived from the camera: valid
  EXPECT_EQ(o.Problem(), "");
  o.stereo.sad_half_window = 40;
  EXPECT_EQ(o.Problem(), "stereo: sad_half_window >= 1 && sad_half_window <= 15");
  o.stereo = StereoOptions{};
  o.bundle_adjustment.num_threads = 0;
  EXPECT_EQ(o.Problem(), "bundle_adjustment: num_threads >= 1");
  o.bundle_adjustment = BundleAdjustmentOptions{};
  o.min_loop_matches = 2;
  EXPECT_EQ(o.Problem(), "min_loop_matches >= 3");
  EXPECT_FALSE(o.Check());
  o.matcher.nn_ratio = 1.5f;  // the first broken requirement is reported
  EXPECT_EQ(o.Problem(), "matcher: nn_ratio > 0 && nn_ratio <= 1");
  Calibration calibration;
  calibration.camera = testing::TestCamera();
  EXPECT_NE(ErrorOf([&] {
              SlamSession slam(calibration, o);
            }).find("invalid SLAM options: matcher: nn_ratio > 0 && nn_ratio <= 1 does not hold"),
            std::string::npos);
  MapMergeOptions merge;
  merge.min_consistent_pairs = 0;
  EXPECT_EQ(merge.Problem(), "min_consistent_pairs >= 1");
}

TEST(SlamConfig, FileErrorsNameTheFileAndLine) {
  const auto path = WriteFile("bad.conf", "# tuned for KITTI\norb.features = 2000\n\nmatcher.nn_ratio 0.7\n");
  SlamOptions o;
  const std::string error = ErrorOf([&] { LoadSlamConfig(path, &o); });
  EXPECT_NE(error.find(path.string() + ":4"), std::string::npos) << error;
  EXPECT_NE(error.find("expected 'key = value'"), std::string::npos) << error;
  const auto unknown = WriteFile("unknown.conf", "orb.features = 2000\nno_such_option = 1\n");
  EXPECT_NE(ErrorOf([&] { LoadSlamConfig(unknown, &o); }).find(unknown.string() + ":2: unknown option"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { LoadSlamConfig("/nonexistent/flatslam.conf", &o); }).find("cannot read config file"),
            std::string::npos);
  const auto range = WriteFile("range.conf", "redundant_keyframe_ratio = 1.5\n");
  EXPECT_NE(ErrorOf([&] { LoadSlamConfig(range, &o); })
                .find(range.string() + ": a value is out of range (redundant_keyframe_ratio > 0 && "
                                       "redundant_keyframe_ratio <= 1 does not hold)"),
            std::string::npos);
  std::filesystem::remove(path);
  std::filesystem::remove(unknown);
  std::filesystem::remove(range);
}

// The option lists are the one source of every key: each key listed is settable by name and
// explains itself with a description, no key appears twice, and a field's requirement is checked
// under its key's struct.
TEST(SlamConfig, EveryListedOptionIsDescribedAndSettable) {
  const std::vector<std::string> lines = DescribeSlamOptions(SlamOptions{});
  std::vector<std::string> keys;
  for (size_t i = 0; i < lines.size(); ++i) {
    const size_t eq = lines[i].find(" = ");
    if (lines[i].empty() || lines[i][0] == '#') continue;
    ASSERT_NE(eq, std::string::npos) << lines[i];
    ASSERT_GT(i, 0u);
    EXPECT_EQ(lines[i - 1].rfind("# ", 0), 0u) << "no description before " << lines[i];
    EXPECT_GT(lines[i - 1].size(), 4u) << lines[i];
    keys.push_back(lines[i].substr(0, eq));
  }
  // Every struct's list is walked, nested ones under their prefix.
  for (const char* key : {"orb.levels", "stereo.outlier_factor", "matcher.nn_ratio", "pose.min_observations",
                          "bundle_adjustment.num_threads", "min_loop_matches"})
    EXPECT_NE(std::find(keys.begin(), keys.end(), key), keys.end()) << key;
  std::vector<std::string> sorted = keys;
  std::sort(sorted.begin(), sorted.end());
  EXPECT_EQ(std::adjacent_find(sorted.begin(), sorted.end()), sorted.end());
  // Setting each key to its own listed value is accepted and changes nothing.
  SlamOptions o;
  for (size_t i = 0; i < lines.size(); ++i) {
    const size_t eq = lines[i].find(" = ");
    if (lines[i].empty() || lines[i][0] == '#') continue;
    SetSlamOption(&o, lines[i].substr(0, eq), lines[i].substr(eq + 3));
  }
  EXPECT_EQ(DescribeSlamOptions(o), lines);
  // Thresholds that were literals in tracking and mapping, by name and range.
  for (const char* key : {"init_search_px", "keyframe_weak_ratio", "keyframe_fading_ratio", "keyframe_fading_inliers",
                          "revisit_healthy_ratio", "revisit_healthy_close", "new_point_depth_factor"})
    EXPECT_NE(std::find(keys.begin(), keys.end(), key), keys.end()) << key;
  EXPECT_NE(ErrorOf([&] { ApplySlamSetting(&o, "new_point_depth_factor=0.5"); }).find("new_point_depth_factor >= 1"),
            std::string::npos);
  o.new_point_depth_factor = 4;
  EXPECT_NE(ErrorOf([&] { ApplySlamSetting(&o, "matcher.fusion_radius=0"); }).find("matcher: fusion_radius > 0"),
            std::string::npos);
}

// What --list-options prints reads back as the same options.
TEST(SlamConfig, DescriptionRoundTripsThroughAConfigFile) {
  SlamOptions changed;
  changed.orb.features = 1234;
  changed.stereo.outlier_factor = 1.75f;
  changed.pose.huber_mono = 2.5;
  changed.far_stereo_baselines = 0;
  changed.bundle_adjustment.solver = BundleAdjustmentOptions::Solver::kCeres;
  std::string text;
  for (const std::string& line : DescribeSlamOptions(changed)) text += line + "\n";
  const auto path = WriteFile("roundtrip.conf", text);
  SlamOptions loaded;
  LoadSlamConfig(path, &loaded);
  EXPECT_EQ(DescribeSlamOptions(loaded), DescribeSlamOptions(changed));
  EXPECT_EQ(loaded.orb.features, 1234);
  EXPECT_FLOAT_EQ(loaded.stereo.outlier_factor, 1.75f);
  EXPECT_DOUBLE_EQ(loaded.pose.huber_mono, 2.5);
  EXPECT_EQ(loaded.far_stereo_baselines, 0);
  EXPECT_EQ(loaded.bundle_adjustment.solver, BundleAdjustmentOptions::Solver::kCeres);
  std::filesystem::remove(path);
}

Calibration CameraOf(int width, int height, double fx, double rate_hz, Sensor sensor, double baseline_m = 0) {
  Calibration c;
  c.sensor = sensor;
  c.camera = PinholeCamera{fx, fx, (width - 1) * 0.5, (height - 1) * 0.5, width, height};
  c.frame_rate_hz = rate_hz;
  c.baseline_m = baseline_m;
  return c;
}

// Defaults left to the camera: a TUM-like 640x480 at 30 Hz, a KITTI-like 1241x376 at 10 Hz and
// a EuRoC-like 752x480 at 20 Hz each get the documented value.
TEST(SlamOptions, FeatureBudgetFollowsTheCamera) {
  const SlamOptions defaults;
  EXPECT_EQ(defaults.orb.features, 0);
  EXPECT_TRUE(defaults.Check());
  // 1.9 x sqrt(307,200) = 1053 -> 1000.
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(640, 480, 525, 30, Sensor::kRgbd)).orb.features, 1000);
  // 1.9 x sqrt(466,616) = 1298, x sqrt(2) at 10 Hz = 1835 -> 2000.
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(1241, 376, 718.9, 10, Sensor::kStereo, 0.537)).orb.features, 2000);
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(1241, 376, 718.9, 10, Sensor::kMonocular)).orb.features, 2000);
  // 1.9 x sqrt(360,960) = 1142 -> 1200.
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(752, 480, 458.6, 20, Sensor::kStereo, 0.11)).orb.features, 1200);
  // The same camera at three quarters and half its size (920x277, 613x185 at 10 Hz): 1.9 x
  // sqrt(254,840) x sqrt(2) = 1356 -> 1500, 1.9 x sqrt(113,405) x sqrt(2) = 905 -> 1000. Monocular
  // KITTI 06 at those sizes loses no frame with these budgets and loses frames with the
  // area-proportional 1200 and 500 (docs/STATUS.md).
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(920, 277, 530.3, 10, Sensor::kMonocular)).orb.features, 1500);
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(613, 185, 353.5, 10, Sensor::kMonocular)).orb.features, 1000);
  // Tiny and huge images stay within [500, 8000]; an unknown rate counts as 20 Hz.
  EXPECT_EQ(DerivedFeatureBudget(PinholeCamera{100, 100, 80, 60, 160, 120}, 0), 500);
  EXPECT_EQ(DerivedFeatureBudget(PinholeCamera{3000, 3000, 2000, 1500, 4000, 3000}, 5), 8000);
  // An explicit budget is kept.
  SlamOptions explicit_budget;
  explicit_budget.orb.features = 1500;
  EXPECT_EQ(ResolvedOptions(explicit_budget, CameraOf(1241, 376, 718.9, 10, Sensor::kMonocular)).orb.features, 1500);
}

// Monocular keyframe spacing: 2 frames at KITTI's rate (its times.txt gives 9.65 Hz) and above,
// 1 where 2 frames span more than about 0.2 s (KITTI with every 2nd frame, 4.8 Hz); depth
// cameras have none; an explicit value is kept.
TEST(SlamOptions, MonocularKeyFrameSpacingFollowsTheFrameRate) {
  const SlamOptions defaults;
  EXPECT_EQ(defaults.min_frames_between_keyframes, -1);
  auto spacing = [&](double rate_hz, Sensor sensor) {
    return ResolvedOptions(defaults, CameraOf(1241, 376, 718.9, rate_hz, sensor, 0.537)).min_frames_between_keyframes;
  };
  EXPECT_EQ(spacing(9.65, Sensor::kMonocular), 2);
  EXPECT_EQ(spacing(20, Sensor::kMonocular), 2);
  EXPECT_EQ(spacing(30, Sensor::kMonocular), 2);
  EXPECT_EQ(spacing(7.5, Sensor::kMonocular), 2);
  EXPECT_EQ(spacing(7.4, Sensor::kMonocular), 1);
  EXPECT_EQ(spacing(4.8, Sensor::kMonocular), 1);
  EXPECT_EQ(spacing(1, Sensor::kMonocular), 1);
  EXPECT_EQ(spacing(0, Sensor::kMonocular), 2);  // rate unknown
  EXPECT_EQ(spacing(4.8, Sensor::kStereo), 0);
  SlamOptions explicit_spacing;
  explicit_spacing.min_frames_between_keyframes = 3;
  EXPECT_EQ(ResolvedOptions(explicit_spacing, CameraOf(1241, 376, 718.9, 4.8, Sensor::kMonocular))
                .min_frames_between_keyframes,
            3);
}

// The narrow rays a thin monocular keyframe takes: down to the angle of 4 pixels, 4 / fx rad
// (TUM-like fx 525: 0.4365 degrees, KITTI-like 718.9: 0.3188, EuRoC-like 458.6: 0.4998), never
// over the monocular floor; until it holds twice the fading count (200). With depth the rule is
// off (the floor itself); explicit values are kept.
TEST(SlamOptions, ThinKeyFrameRaysFollowTheFocalLength) {
  const SlamOptions defaults;
  EXPECT_EQ(defaults.thin_keyframe_parallax_deg, 0);
  EXPECT_EQ(defaults.thin_keyframe_points, 0);
  const SlamOptions tum = ResolvedOptions(defaults, CameraOf(640, 480, 525, 30, Sensor::kMonocular));
  const SlamOptions kitti = ResolvedOptions(defaults, CameraOf(1241, 376, 718.9, 10, Sensor::kMonocular));
  const SlamOptions euroc = ResolvedOptions(defaults, CameraOf(752, 480, 458.6, 20, Sensor::kMonocular));
  EXPECT_NEAR(tum.thin_keyframe_parallax_deg, 0.4365, 1e-4);
  EXPECT_NEAR(kitti.thin_keyframe_parallax_deg, 0.3188, 1e-4);
  EXPECT_NEAR(euroc.thin_keyframe_parallax_deg, 0.4998, 1e-4);
  for (const SlamOptions* o : {&tum, &kitti, &euroc}) {
    EXPECT_EQ(o->thin_keyframe_points, 200);
    EXPECT_EQ(o->min_parallax_deg, 2.0);
  }
  // A camera so short-sighted that 4 pixels span more than the floor: the floor.
  EXPECT_EQ(ResolvedOptions(defaults, CameraOf(160, 120, 100, 30, Sensor::kMonocular)).thin_keyframe_parallax_deg,
            2.0);
  const SlamOptions stereo = ResolvedOptions(defaults, CameraOf(752, 480, 458.6, 20, Sensor::kStereo, 0.11));
  EXPECT_EQ(stereo.thin_keyframe_parallax_deg, stereo.min_parallax_deg);
  SlamOptions explicit_thin;
  explicit_thin.thin_keyframe_parallax_deg = 1.146;
  explicit_thin.thin_keyframe_points = 100;
  const SlamOptions kept = ResolvedOptions(explicit_thin, CameraOf(1241, 376, 718.9, 10, Sensor::kMonocular));
  EXPECT_EQ(kept.thin_keyframe_parallax_deg, 1.146);
  EXPECT_EQ(kept.thin_keyframe_points, 100);
}

// --list-options: each value chosen from the camera comes with its rule, and the whole listing
// still reads back as a config file.
TEST(SlamOptions, DerivedValuesAreExplained) {
  std::vector<DerivedOption> derived;
  const SlamOptions resolved =
      ResolvedOptions(SlamOptions{}, CameraOf(1241, 376, 718.9, 10, Sensor::kStereo, 0.537), &derived);
  const std::vector<std::string> lines = DescribeSlamOptions(resolved, derived);
  const auto features = std::find(lines.begin(), lines.end(), "orb.features = 2000");
  ASSERT_NE(features, lines.end());
  ASSERT_NE(features, lines.begin());
  EXPECT_EQ(std::prev(features)->rfind("# derived: 1.9 x sqrt(1241 x 376) (the image's linear size)", 0), 0u)
      << *std::prev(features);
  std::string text;
  for (const std::string& line : lines) text += line + "\n";
  const auto path = WriteFile("derived.conf", text);
  SlamOptions loaded;
  LoadSlamConfig(path, &loaded);
  EXPECT_EQ(loaded.orb.features, 2000);
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace flatslam
