// Batch inputs: manifests in both forms, their errors, folders of datasets and shards.
#include "io/manifest.h"

#include <gtest/gtest.h>

#include <fstream>
#include <set>

#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

std::filesystem::path Write(const std::filesystem::path& path, const std::string& text) {
  std::ofstream(path) << text;
  return path;
}

TEST(Manifest, LinesNameEachSequenceWithItsOptions) {
  const auto dir = testing::FreshTempDir("manifest_lines");
  const auto file = Write(dir / "batch.txt",
                          "# KITTI and a synthetic scene\n"
                          "\n"
                          "seqs/07 --sensor mono --set orb.features=2000,close_depth_baselines=40 --name k07\n"
                          "synth:room:duration=5 --seed 3 --max-frames 50 --keep-camera  # short\n"
                          "other --config cfg.txt --settings 'my camera.yaml' --keep-camera=false\n");
  const std::vector<SequenceSpec> specs = ReadManifest(file);
  ASSERT_EQ(specs.size(), 3u);
  EXPECT_EQ(specs[0].dataset, (dir / "seqs/07").string());
  EXPECT_EQ(specs[0].name, "k07");
  ASSERT_TRUE(specs[0].sensor.has_value());
  EXPECT_EQ(*specs[0].sensor, Sensor::kMonocular);
  EXPECT_EQ(specs[0].set, (std::vector<std::string>{"orb.features=2000", "close_depth_baselines=40"}));
  EXPECT_EQ(specs[1].dataset, "synth:room:duration=5");
  EXPECT_EQ(specs[1].seed, 3u);
  EXPECT_EQ(specs[1].max_frames, 50u);
  EXPECT_FALSE(specs[0].keep_camera.has_value());
  EXPECT_EQ(specs[1].keep_camera, true);
  EXPECT_EQ(specs[2].keep_camera, false);
  EXPECT_EQ(specs[2].config, (dir / "cfg.txt").string());
  EXPECT_EQ(specs[2].where, file.string() + ":5");
}

TEST(Manifest, YamlListOfMappings) {
  const auto dir = testing::FreshTempDir("manifest_yaml");
  const auto file = Write(dir / "batch.yaml",
                          "sequences:\n"
                          "  - path: /data/kitti/sequences/06\n"
                          "    sensor: stereo\n"
                          "    options:\n"
                          "      orb.features: 2000\n"
                          "      close_depth_baselines: 40   # comment\n"
                          "    name: \"k06\"\n"
                          "  - dataset: synth:corridor:duration=5\n"
                          "    options: orb.features=800,min_local_map_inliers=20\n"
                          "    max_frames: 40\n"
                          "    keep_camera: yes\n"
                          "    camera_from: maps/first.fsmap\n");
  const std::vector<SequenceSpec> specs = ReadManifest(file);
  ASSERT_EQ(specs.size(), 2u);
  EXPECT_EQ(specs[0].dataset, "/data/kitti/sequences/06");
  EXPECT_EQ(specs[0].name, "k06");
  EXPECT_EQ(specs[0].set, (std::vector<std::string>{"orb.features=2000", "close_depth_baselines=40"}));
  EXPECT_EQ(specs[1].dataset, "synth:corridor:duration=5");
  EXPECT_EQ(specs[1].set, (std::vector<std::string>{"orb.features=800", "min_local_map_inliers=20"}));
  EXPECT_EQ(specs[1].max_frames, 40u);
  EXPECT_FALSE(specs[0].keep_camera.has_value());
  EXPECT_EQ(specs[1].keep_camera, true);
  EXPECT_EQ(specs[1].camera_from, (dir / "maps/first.fsmap").string());
  EXPECT_TRUE(specs[0].camera_from.empty());
  EXPECT_EQ(specs[1].where, file.string() + ":8");
}

TEST(Manifest, ErrorsNameTheFileAndLine) {
  const auto dir = testing::FreshTempDir("manifest_errors");
  using testing::ExpectErrorMentions;
  const auto lines = Write(dir / "a.txt", "synth:room\nsynth:room --frobnicate 3\n");
  ExpectErrorMentions([&] { (void)ReadManifest(lines); }, {"a.txt:2", "unknown key 'frobnicate'"});
  const auto two = Write(dir / "b.txt", "synth:room synth:corridor\n");
  ExpectErrorMentions([&] { (void)ReadManifest(two); }, {"b.txt:1", "second dataset"});
  const auto seed = Write(dir / "c.txt", "\nsynth:room --seed x1\n");
  ExpectErrorMentions([&] { (void)ReadManifest(seed); }, {"c.txt:2", "seed 'x1'"});
  const auto sensor = Write(dir / "d.yaml", "- path: synth:room\n  sensor: lidar\n");
  ExpectErrorMentions([&] { (void)ReadManifest(sensor); }, {"d.yaml:2", "lidar"});
  const auto no_path = Write(dir / "e.yaml", "- name: x\n  sensor: mono\n- path: synth:room\n");
  ExpectErrorMentions([&] { (void)ReadManifest(no_path); }, {"e.yaml:1", "names no dataset"});
  const auto indent = Write(dir / "f.yaml", "- path: synth:room\n      name: x\n");
  ExpectErrorMentions([&] { (void)ReadManifest(indent); }, {"f.yaml:2", "indentation"});
  const auto option = Write(dir / "g.yaml", "- path: synth:room\n  options: orb.features\n");
  ExpectErrorMentions([&] { (void)ReadManifest(option); }, {"g.yaml:2", "KEY=VALUE"});
  const auto keep = Write(dir / "i.yaml", "- path: synth:room\n  keep_camera: maybe\n");
  ExpectErrorMentions([&] { (void)ReadManifest(keep); }, {"i.yaml:2", "keep_camera 'maybe'"});
  const auto empty = Write(dir / "h.txt", "# nothing\n\n");
  ExpectErrorMentions([&] { (void)ReadManifest(empty); }, {"h.txt", "no sequence"});
  ExpectErrorMentions([&] { (void)ReadManifest(dir / "missing.txt"); }, {"missing.txt", "cannot open"});
}

TEST(BatchInputs, FoldersOfDatasetsSynthAndUniqueNames) {
  const auto kitti = testing::DatasetsDir() / "kitti";
  if (!std::filesystem::exists(kitti / "sequences")) GTEST_SKIP() << "no KITTI snippets in " << kitti;
  SequenceSpec defaults;
  defaults.sensor = Sensor::kMonocular;
  defaults.set = {"orb.features=1500"};
  const auto specs = ExpandBatchInputs(
      {kitti.string(), (kitti / "sequences" / "06").string(), "synth:room:duration=5", "synth:room:duration=5"},
      defaults);
  std::vector<std::string> sequences;
  for (const auto& entry : std::filesystem::directory_iterator(kitti / "sequences")) sequences.push_back(entry.path());
  ASSERT_GE(sequences.size(), 2u);
  ASSERT_EQ(specs.size(), sequences.size() + 3);
  EXPECT_EQ(specs[0].name, "kitti_06");  // a KITTI root: every sequence, in name order
  EXPECT_EQ(specs[1].name, "kitti_07");
  EXPECT_EQ(specs[sequences.size()].name, "kitti_06-2");
  EXPECT_EQ(specs[sequences.size() + 1].name, "synth_room_duration=5");
  EXPECT_EQ(specs[sequences.size() + 2].name, "synth_room_duration=5-2");
  for (const SequenceSpec& s : specs) {
    EXPECT_EQ(s.sensor, Sensor::kMonocular);
    EXPECT_EQ(s.set, std::vector<std::string>{"orb.features=1500"});
  }
  testing::ExpectErrorMentions([&] { (void)ExpandBatchInputs({"/no/such/place"}, {}); }, {"/no/such/place"});
}

TEST(BatchInputs, ManifestOptionsComeAfterTheBatchDefaults) {
  const auto dir = testing::FreshTempDir("manifest_defaults");
  const auto file = Write(dir / "m.txt",
                          "synth:room --set orb.features=900\nsynth:corridor --seed 4 --keep-camera=false\n");
  SequenceSpec defaults;
  defaults.set = {"orb.features=1500"};
  defaults.seed = 7;
  defaults.keep_camera = true;
  const auto specs = ExpandBatchInputs({file.string()}, defaults);
  ASSERT_EQ(specs.size(), 2u);
  EXPECT_EQ(specs[0].set, (std::vector<std::string>{"orb.features=1500", "orb.features=900"}));
  EXPECT_EQ(specs[0].seed, 7u);
  EXPECT_EQ(specs[1].seed, 4u);
  EXPECT_EQ(specs[0].keep_camera, true);  // the batch's --keep-camera
  EXPECT_EQ(specs[1].keep_camera, false);
}

TEST(BatchInputs, ShardsCoverEverySequenceOnce) {
  for (size_t n : {1u, 2u, 3u, 7u}) {
    std::multiset<size_t> seen;
    for (size_t i = 0; i < n; ++i)
      for (size_t p : ShardPositions(10, i, n)) seen.insert(p);
    EXPECT_EQ(seen.size(), 10u);
    for (size_t p = 0; p < 10; ++p) EXPECT_EQ(seen.count(p), 1u);
  }
  EXPECT_EQ(ShardPositions(5, 1, 2), (std::vector<size_t>{1, 3}));
  testing::ExpectErrorMentions([] { (void)ShardPositions(5, 2, 2); }, {"shard 2/2"});
}

}  // namespace
}  // namespace flatslam
