// Vocabulary: implicit-tree descent against a brute-force reference, training invariants
// (input untouched, every word reachable and weighted), IDF and L1 score by hand, file round trip
// and rejection of bad files, the shipped default vocabulary, and place separation on KITTI 07.
#include "place/vocabulary.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <numeric>
#include <random>
#include <string>
#include <tuple>
#include <vector>

#include "core/error.h"
#include "flatslam/schemas/vocabulary_generated.h"
#include "io/image_io.h"
#include "frontend/orb_extractor.h"
#include "test_data.h"

namespace flatslam {
namespace {

Descriptor RandomDescriptor(std::mt19937_64& rng) {
  return {rng(), rng(), rng(), rng()};
}

Descriptor FlipBits(Descriptor d, int bits, std::mt19937_64& rng) {
  for (int i = 0; i < bits; ++i) {
    const int bit = static_cast<int>(rng() % 256);
    d[bit / 64] ^= uint64_t{1} << (bit % 64);
  }
  return d;
}

// Descriptors around `prototypes` random centres (up to `noise` flipped bits each), as ORB
// descriptors of repeated structures; image k % images.
struct TrainingSet {
  std::vector<Descriptor> descriptors;
  std::vector<uint32_t> image_of;
  size_t images = 0;
};

TrainingSet MakeTrainingSet(size_t count, int prototypes, int noise, size_t images, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::vector<Descriptor> centres(prototypes);
  for (auto& c : centres) c = RandomDescriptor(rng);
  TrainingSet set;
  set.images = images;
  for (size_t k = 0; k < count; ++k) {
    set.descriptors.push_back(FlipBits(centres[rng() % centres.size()], static_cast<int>(rng() % (noise + 1)), rng));
    set.image_of.push_back(static_cast<uint32_t>(k % images));
  }
  return set;
}

Vocabulary TrainSmall(const TrainingSet& set, int branching, int levels, uint64_t seed = 1) {
  VocabularyTrainOptions options;
  options.branching = branching;
  options.levels = levels;
  options.seed = seed;
  return Vocabulary::Train(set.descriptors, set.image_of, set.images, options);
}

// Reference descent: look at every slot of the child block, skip the ones marked empty, recurse
// into the closest (first on ties).
WordId ReferenceWord(const Vocabulary& v, uint32_t node, const Descriptor& d) {
  const uint64_t first = uint64_t{node} * v.branching() + 1;
  int best_distance = 1000;
  uint32_t best = 0;
  for (int j = 0; j < v.branching() && first + j < v.node_count(); ++j) {
    const auto slot = static_cast<uint32_t>(first + j);
    if (v.node_word(slot) == Vocabulary::kEmptyNode) continue;
    const int distance = DescriptorDistance(d, v.node_descriptor(slot));
    if (distance < best_distance) {
      best_distance = distance;
      best = slot;
    }
  }
  if (best_distance == 1000) return v.node_word(node);
  return ReferenceWord(v, best, d);
}

std::vector<uint8_t> ReadBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

void WriteBytes(const std::filesystem::path& path, const uint8_t* data, size_t size) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
}

// The message of the flatslam::Error that loading `path` throws ("" when it loads).
std::string LoadError(const std::filesystem::path& path) {
  try {
    (void)Vocabulary::Load(path);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

bool Contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

TEST(Vocabulary, TransformMatchesBruteForceDescent) {
  const TrainingSet set = MakeTrainingSet(30000, 400, 40, 60, 7);
  const Vocabulary v = TrainSmall(set, 6, 4);
  ASSERT_GT(v.word_count(), 300u);
  std::mt19937_64 rng(11);
  for (int i = 0; i < 4000; ++i) {
    // Half from the training distribution, half uniformly random.
    const Descriptor d =
        i % 2 ? FlipBits(set.descriptors[rng() % set.descriptors.size()], 30, rng) : RandomDescriptor(rng);
    const WordId word = v.Transform(d);
    ASSERT_EQ(word, ReferenceWord(v, 0, d)) << "descriptor " << i;
    // The node at depth 2 is an ancestor of the word's leaf.
    uint32_t node = 0;
    ASSERT_EQ(v.Transform(d, 2, &node), word);
    uint32_t leaf = 0;
    while (v.node_word(leaf) != word) ++leaf;
    uint32_t ancestor = leaf;
    while (ancestor > node) ancestor = (ancestor - 1) / v.branching();
    EXPECT_EQ(ancestor, node);
  }
}

TEST(Vocabulary, HandBuiltTreeDescends) {
  // B = 2, L = 2: root -> {A, B}; A -> {A0, A1}; B is a leaf. Slots: 0 root, 1 A, 2 B, 3 A0, 4 A1,
  // 5-6 empty children of B. Words in slot order: B = 0, A0 = 1, A1 = 2.
  const Descriptor a{0, 0, 0, 0}, b{~0ull, ~0ull, ~0ull, ~0ull};
  const Descriptor a0{0x0F, 0, 0, 0}, a1{0xF0, 0, 0, 0};
  const std::vector<Descriptor> nodes = {Descriptor{}, a, b, a0, a1, Descriptor{}, Descriptor{}};
  const std::vector<uint8_t> children = {2, 2, 0, 0, 0, 0, 0};
  const std::vector<float> weights = {0.5f, 1.0f, 2.0f};
  const Vocabulary v = Vocabulary::FromNodes(2, 2, nodes, children, weights);
  EXPECT_EQ(v.word_count(), 3u);
  EXPECT_EQ(v.node_count(), 7u);
  EXPECT_EQ(v.node_word(2), 0u);
  EXPECT_EQ(v.node_word(3), 1u);
  EXPECT_EQ(v.node_word(4), 2u);
  EXPECT_EQ(v.node_word(5), Vocabulary::kEmptyNode);
  EXPECT_EQ(v.node_word(1), Vocabulary::kInnerNode);
  EXPECT_EQ(v.Transform(Descriptor{0x07, 0, 0, 0}), 1u);           // near a, then a0
  EXPECT_EQ(v.Transform(Descriptor{0x70, 0, 0, 0}), 2u);           // near a, then a1
  EXPECT_EQ(v.Transform(Descriptor{0xFF, 0, 0, 0}), 1u);           // tie between a0 and a1: the first
  EXPECT_EQ(v.Transform(Descriptor{~0ull, ~0ull, ~0ull, 0}), 0u);  // near b, a leaf at depth 1
  uint32_t node = 99;
  EXPECT_EQ(v.Transform(Descriptor{~0ull, ~0ull, ~0ull, 0}, 2, &node), 0u);
  EXPECT_EQ(node, 2u);  // the leaf itself when it is shallower than the asked depth
  EXPECT_EQ(v.Transform(Descriptor{0x70, 0, 0, 0}, 1, &node), 2u);
  EXPECT_EQ(node, 1u);
  EXPECT_FLOAT_EQ(v.weight(2), 2.0f);

  // Inconsistent arrays are refused with a message.
  std::vector<uint8_t> bad = children;
  bad[5] = 1;  // an empty slot with a child
  EXPECT_THROW((void)Vocabulary::FromNodes(2, 2, nodes, bad, weights), Error);
  bad = children;
  bad[2] = 3;  // more children than the branching
  EXPECT_THROW((void)Vocabulary::FromNodes(2, 2, nodes, bad, weights), Error);
  EXPECT_THROW((void)Vocabulary::FromNodes(2, 2, nodes, children, std::vector<float>{1, 1}), Error);
  EXPECT_THROW((void)Vocabulary::FromNodes(2, 2, nodes, children, std::vector<float>{1, 0, 1}), Error);
}

TEST(Vocabulary, TrainingLeavesInputUnchanged) {
  const TrainingSet set = MakeTrainingSet(20000, 300, 30, 40, 3);
  const std::vector<Descriptor> before = set.descriptors;
  const std::vector<uint32_t> images_before = set.image_of;
  const Vocabulary v = TrainSmall(set, 8, 3);
  EXPECT_EQ(set.descriptors, before);
  EXPECT_EQ(set.image_of, images_before);
  // Deterministic for a seed.
  EXPECT_EQ(TrainSmall(set, 8, 3).checksum(), v.checksum());
  EXPECT_NE(TrainSmall(set, 8, 3, 2).checksum(), v.checksum());
}

TEST(Vocabulary, EveryWordReachableWithPositiveWeight) {
  for (const auto& [noise, branching, levels] : {std::tuple{30, 10, 3}, std::tuple{5, 6, 5}, std::tuple{80, 4, 6}}) {
    const TrainingSet set = MakeTrainingSet(25000, 500, noise, 50, 5 + noise);
    const Vocabulary v = TrainSmall(set, branching, levels);
    std::vector<int> hits(v.word_count(), 0);
    for (const Descriptor& d : set.descriptors) ++hits[v.Transform(d)];
    // A word no training descriptor reaches must at least be reached by its own centroid.
    size_t unreachable = 0, zero_weight = 0;
    for (uint32_t node = 0; node < v.node_count(); ++node) {
      const WordId w = v.node_word(node);
      if (w >= Vocabulary::kInnerNode) continue;
      if (hits[w] == 0 && v.Transform(v.node_descriptor(node)) != w) ++unreachable;
      if (!(v.weight(w) > 0.f)) ++zero_weight;
    }
    EXPECT_EQ(unreachable, 0u) << "noise " << noise;
    EXPECT_EQ(zero_weight, 0u) << "noise " << noise;
    // Every word holds training descriptors (no empty cluster made a word).
    EXPECT_EQ(std::count(hits.begin(), hits.end(), 0), 0) << "noise " << noise;
  }
}

TEST(Vocabulary, DegenerateTrainingData) {
  // Many copies of three descriptors: three words, whatever the requested depth.
  std::mt19937_64 rng(1);
  const std::vector<Descriptor> distinct = {RandomDescriptor(rng), RandomDescriptor(rng), RandomDescriptor(rng)};
  TrainingSet set;
  set.images = 10;
  for (int k = 0; k < 3000; ++k) {
    set.descriptors.push_back(distinct[k % 3]);
    set.image_of.push_back(k % 10);
  }
  const Vocabulary v = TrainSmall(set, 10, 6);
  EXPECT_EQ(v.word_count(), 3u);
  std::vector<WordId> words;
  for (const Descriptor& d : distinct) words.push_back(v.Transform(d));
  std::sort(words.begin(), words.end());
  EXPECT_EQ(words, (std::vector<WordId>{0, 1, 2}));

  // One distinct descriptor cannot make a tree; bad options and bad image indices are refused.
  TrainingSet one = set;
  std::fill(one.descriptors.begin(), one.descriptors.end(), distinct[0]);
  EXPECT_THROW((void)TrainSmall(one, 10, 3), Error);
  EXPECT_THROW((void)TrainSmall(set, 1, 3), Error);
  EXPECT_THROW((void)TrainSmall(set, 10, 0), Error);
  EXPECT_THROW((void)TrainSmall(set, 10, 9), Error);  // 1.1e9 nodes
  TrainingSet bad_image = set;
  bad_image.image_of[5] = 10;
  EXPECT_THROW((void)TrainSmall(bad_image, 10, 3), Error);
}

TEST(Vocabulary, IdfByHand) {
  // Four far-apart descriptors, one level: each is its own word. Word of d0 appears in images
  // {0, 1}, d1 in {0}, d2 in {0, 1, 2, 3} (every image), d3 in {3}; N = 4.
  const std::vector<Descriptor> d = {Descriptor{0, 0, 0, 0}, Descriptor{~0ull, 0, 0, 0}, Descriptor{0, ~0ull, 0, 0},
                                     Descriptor{0, 0, ~0ull, 0}};
  const std::vector<Descriptor> descriptors = {d[0], d[0], d[1], d[2], d[2], d[2], d[2], d[3], d[0]};
  const std::vector<uint32_t> image_of = {0, 1, 0, 0, 1, 2, 3, 3, 1};
  VocabularyTrainOptions options;
  options.branching = 4;
  options.levels = 1;
  const Vocabulary v = Vocabulary::Train(descriptors, image_of, 4, options);
  ASSERT_EQ(v.word_count(), 4u);
  EXPECT_NEAR(v.weight(v.Transform(d[0])), std::log(4.0 / 2.0), 1e-6);
  EXPECT_NEAR(v.weight(v.Transform(d[1])), std::log(4.0 / 1.0), 1e-6);
  EXPECT_NEAR(v.weight(v.Transform(d[3])), std::log(4.0 / 1.0), 1e-6);
  // In every image: counted as in N - 1/2 images, positive and below every rarer word.
  EXPECT_NEAR(v.weight(v.Transform(d[2])), std::log(4.0 / 3.5), 1e-6);

  // TF-IDF of an image: counts times IDF, L1-normalized.
  BowVector bow;
  FeatureVector features;
  v.Transform(std::vector<Descriptor>{d[0], d[1], d[0]}, &bow, &features, 1);
  ASSERT_EQ(bow.size(), 2u);
  const double w0 = 2 * std::log(2.0), w1 = std::log(4.0);
  const WordId word0 = v.Transform(d[0]), word1 = v.Transform(d[1]);
  for (const auto& [word, value] : bow) {
    EXPECT_NEAR(value, (word == word0 ? w0 : w1) / (w0 + w1), 1e-6);
    EXPECT_TRUE(word == word0 || word == word1);
  }
  EXPECT_TRUE(std::is_sorted(bow.begin(), bow.end()));
  ASSERT_EQ(features.size(), 3u);
  EXPECT_TRUE(std::is_sorted(features.begin(), features.end()));
}

TEST(Vocabulary, ScoreByHand) {
  const BowVector a = {{1, 0.5f}, {2, 0.5f}};
  const BowVector b = {{2, 0.25f}, {3, 0.75f}};
  // 1 - 0.5 * (|0.5 - 0| + |0.5 - 0.25| + |0 - 0.75|) = 1 - 0.5 * 1.5 = 0.25.
  EXPECT_NEAR(Vocabulary::Score(a, b), 0.25, 1e-6);
  EXPECT_NEAR(Vocabulary::Score(b, a), 0.25, 1e-6);
  EXPECT_NEAR(Vocabulary::Score(a, a), 1.0, 1e-6);
  EXPECT_NEAR(Vocabulary::Score(a, BowVector{{7, 1.0f}}), 0.0, 1e-6);
  EXPECT_NEAR(Vocabulary::Score(a, BowVector{}), 0.0, 1e-6);
  EXPECT_NEAR(Vocabulary::Score(BowVector{}, BowVector{}), 0.0, 1e-6);
  const BowVector c = {{1, 0.1f}, {2, 0.2f}, {4, 0.3f}, {9, 0.4f}};
  const BowVector d = {{2, 0.6f}, {4, 0.1f}, {5, 0.3f}};
  // 1 - 0.5 * (0.1 + 0.4 + 0.2 + 0.3 + 0.4) = 0.3.
  EXPECT_NEAR(Vocabulary::Score(c, d), 0.3, 1e-6);
}

class VocabularyFile : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTempDir("vocabulary");
    set_ = MakeTrainingSet(8000, 150, 30, 20, 9);
    vocabulary_ = TrainSmall(set_, 5, 3);
    path_ = dir_ / "small.fsvc";
    vocabulary_.Save(path_);
    bytes_ = ReadBytes(path_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::filesystem::path dir_, path_;
  TrainingSet set_;
  Vocabulary vocabulary_;
  std::vector<uint8_t> bytes_;
};

TEST_F(VocabularyFile, SaveLoadRoundTrip) {
  ASSERT_EQ(bytes_.size(), vocabulary_.byte_size());
  EXPECT_FALSE(std::filesystem::exists(path_.string() + ".tmp." + std::to_string(::getpid())));
  const Vocabulary loaded = Vocabulary::Load(path_);
  EXPECT_EQ(loaded.checksum(), vocabulary_.checksum());
  EXPECT_EQ(loaded.branching(), vocabulary_.branching());
  EXPECT_EQ(loaded.levels(), vocabulary_.levels());
  EXPECT_EQ(loaded.word_count(), vocabulary_.word_count());
  EXPECT_EQ(loaded.node_count(), vocabulary_.node_count());
  EXPECT_EQ(loaded.training_descriptors(), set_.descriptors.size());
  EXPECT_EQ(loaded.training_images(), set_.images);
  for (WordId w = 0; w < loaded.word_count(); ++w) ASSERT_EQ(loaded.weight(w), vocabulary_.weight(w));
  std::mt19937_64 rng(2);
  for (int i = 0; i < 5000; ++i) {
    const Descriptor d = i % 2 ? RandomDescriptor(rng) : set_.descriptors[rng() % set_.descriptors.size()];
    ASSERT_EQ(loaded.Transform(d), vocabulary_.Transform(d));
  }
  // Saving the loaded one gives the same bytes; saving over an existing file replaces it.
  loaded.Save(path_);
  EXPECT_EQ(ReadBytes(path_), bytes_);
  // Moving keeps the mapping alive.
  Vocabulary reloaded = Vocabulary::Load(path_);
  const Vocabulary moved = std::move(reloaded);
  EXPECT_TRUE(reloaded.empty());
  EXPECT_EQ(moved.checksum(), vocabulary_.checksum());
  EXPECT_EQ(moved.Transform(set_.descriptors[0]), vocabulary_.Transform(set_.descriptors[0]));
}

TEST_F(VocabularyFile, MissingFileAndDirectory) {
  const std::string missing = LoadError(dir_ / "nowhere.fsvc");
  EXPECT_TRUE(Contains(missing, "nowhere.fsvc")) << missing;
  EXPECT_TRUE(Contains(missing, "cannot open")) << missing;
  const std::string directory = LoadError(dir_);
  EXPECT_TRUE(Contains(directory, "not a regular file")) << directory;
  EXPECT_THROW(vocabulary_.Save(dir_ / "no" / "such" / "dir.fsvc"), Error);
}

TEST_F(VocabularyFile, TruncatedFilesAreRefused) {
  const auto bad = dir_ / "truncated.fsvc";
  for (size_t length : {size_t{0}, size_t{3}, size_t{7}, size_t{8}, size_t{16}, size_t{64}, bytes_.size() / 4,
                        bytes_.size() / 2, bytes_.size() - 100, bytes_.size() - 1}) {
    WriteBytes(bad, bytes_.data(), length);
    const std::string message = LoadError(bad);
    EXPECT_TRUE(Contains(message, "truncated.fsvc")) << length << ": " << message;
    EXPECT_TRUE(Contains(message, "truncated") || Contains(message, "corrupt")) << length << ": " << message;
  }
}

TEST_F(VocabularyFile, WrongIdentifierAndNewerVersion) {
  const auto bad = dir_ / "bad.fsvc";
  std::vector<uint8_t> copy = bytes_;
  std::memcpy(copy.data() + 4, "FSMP", 4);
  WriteBytes(bad, copy.data(), copy.size());
  std::string message = LoadError(bad);
  EXPECT_TRUE(Contains(message, "not a flatslam vocabulary")) << message;
  EXPECT_TRUE(Contains(message, "FSMP")) << message;

  // Same content, a newer format version.
  const auto* root = fbs::vocab::GetVocabulary(bytes_.data());
  flatbuffers::FlatBufferBuilder fbb;
  const auto d = fbb.CreateVectorOfStructs(
      reinterpret_cast<const fbs::vocab::Descriptor256*>(root->descriptors()->Data()), root->descriptors()->size());
  const auto c = fbb.CreateVector(root->child_count()->data(), root->child_count()->size());
  const auto w = fbb.CreateVector(root->word()->data(), root->word()->size());
  const auto g = fbb.CreateVector(root->weight()->data(), root->weight()->size());
  fbs::vocab::FinishVocabularyBuffer(
      fbb, fbs::vocab::CreateVocabulary(fbb, root->format_version() + 1, root->branching(), root->levels(),
                                        root->word_count(), root->checksum(), d, c, w, g));
  WriteBytes(bad, fbb.GetBufferPointer(), fbb.GetSize());
  message = LoadError(bad);
  EXPECT_TRUE(Contains(message, "newer")) << message;
  EXPECT_TRUE(Contains(message, "bad.fsvc")) << message;
}

TEST_F(VocabularyFile, FlippedBytesAreRefused) {
  const auto bad = dir_ / "flipped.fsvc";
  // Every byte of the file flipped in turn: loading either fails with a flatslam::Error or, for
  // bytes the format ignores (alignment padding), gives the same vocabulary. Never a crash.
  size_t refused = 0, ignored = 0;
  const size_t step = std::max<size_t>(1, bytes_.size() / 1500);
  for (size_t at = 0; at < bytes_.size(); at += step) {
    std::vector<uint8_t> copy = bytes_;
    copy[at] ^= 0x5A;
    WriteBytes(bad, copy.data(), copy.size());
    try {
      const Vocabulary v = Vocabulary::Load(bad);
      EXPECT_EQ(v.checksum(), vocabulary_.checksum()) << "byte " << at;
      ++ignored;
    } catch (const Error& e) {
      EXPECT_TRUE(Contains(e.what(), "flipped.fsvc")) << e.what();
      ++refused;
    }
  }
  EXPECT_GT(refused, 10 * ignored);
  // Bytes of each array's content are always caught.
  const auto* root = fbs::vocab::GetVocabulary(bytes_.data());
  const std::vector<const uint8_t*> inside = {reinterpret_cast<const uint8_t*>(root->descriptors()->data()) + 100,
                                              root->child_count()->data() + 3,
                                              reinterpret_cast<const uint8_t*>(root->word()->data()) + 41,
                                              reinterpret_cast<const uint8_t*>(root->weight()->data()) + 2};
  for (const uint8_t* p : inside) {
    std::vector<uint8_t> copy = bytes_;
    copy[p - bytes_.data()] ^= 0x01;
    WriteBytes(bad, copy.data(), copy.size());
    const std::string message = LoadError(bad);
    EXPECT_FALSE(message.empty()) << "byte " << (p - bytes_.data());
  }
}

TEST(Vocabulary, DefaultVocabularyLoads) {
  const std::filesystem::path path = DefaultVocabularyPath();
  ASSERT_TRUE(std::filesystem::exists(path)) << path;
  const Vocabulary v = Vocabulary::Load(path);
  EXPECT_GE(v.word_count(), 10000u);
  EXPECT_LE(v.byte_size(), 5u << 20);
  std::printf("default vocabulary %s: branching %d, levels %d, %zu words, %.2f MiB\n", path.c_str(), v.branching(),
              v.levels(), v.word_count(), v.byte_size() / 1048576.0);
}

double Mean(const std::vector<double>& v) {
  return std::accumulate(v.begin(), v.end(), 0.0) / v.size();
}
double Median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// Real-data check of the default vocabulary (KITTI 07 was not used to train it): consecutive
// frames (about 1 m apart) must score clearly above frames of different places (>= 50 frames,
// about 30 m, apart).
TEST(Vocabulary, SeparatesPlacesOnKitti07) {
  const auto dir = testing::DatasetsDir() / "kitti/sequences/07/image_0";
  if (!std::filesystem::exists(dir)) GTEST_SKIP() << "no KITTI snippet at " << dir;
  const Vocabulary v = Vocabulary::Load(DefaultVocabularyPath());
  OrbOptions orb_options;
  orb_options.features = 2000;
  const OrbExtractor orb(orb_options);
  std::vector<BowVector> bows;
  for (int i = 0; i < 160; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06d.png", i);
    Keypoints keypoints;
    orb.Extract(ReadGrayImage(dir / name), &keypoints);
    bows.emplace_back();
    v.Transform(keypoints.descriptor, &bows.back(), nullptr);
  }
  std::vector<double> consecutive, apart;
  for (size_t i = 0; i + 1 < bows.size(); ++i) consecutive.push_back(Vocabulary::Score(bows[i], bows[i + 1]));
  for (size_t i = 0; i < bows.size(); ++i) {
    for (size_t j = i + 50; j < bows.size(); ++j) apart.push_back(Vocabulary::Score(bows[i], bows[j]));
  }
  const double worst_consecutive = *std::min_element(consecutive.begin(), consecutive.end());
  const double best_apart = *std::max_element(apart.begin(), apart.end());
  size_t above = 0;  // consecutive pairs scoring above the 99th percentile of different places
  std::vector<double> sorted_apart = apart;
  std::sort(sorted_apart.begin(), sorted_apart.end());
  const double p99 = sorted_apart[sorted_apart.size() * 99 / 100];
  for (double s : consecutive) above += s > p99;
  std::printf(
      "KITTI 07, 160 frames, 2000 ORB features, default vocabulary:\n"
      "  consecutive frames   (%zu pairs): mean %.4f, median %.4f, min %.4f\n"
      "  >= 50 frames apart (%zu pairs): mean %.4f, median %.4f, 99th percentile %.4f, max %.4f\n"
      "  consecutive pairs above that 99th percentile: %zu of %zu\n",
      consecutive.size(), Mean(consecutive), Median(consecutive), worst_consecutive, apart.size(), Mean(apart),
      Median(apart), p99, best_apart, above, consecutive.size());
  EXPECT_GT(Median(consecutive), 1.7 * Median(apart));
  EXPECT_GT(Mean(consecutive), Mean(apart) + 0.05);
  EXPECT_GE(above, consecutive.size() * 9 / 10);
}

}  // namespace
}  // namespace flatslam
