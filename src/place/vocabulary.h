// A bag-of-words vocabulary tree for 256-bit ORB descriptors, stored as an implicit tree:
// nodes in breadth-first order in one contiguous array; for branching B the children of node i
// are nodes i*B+1 .. i*B+B, contiguous (node 0 is the root, so the first level is 1 .. B; slots
// where the tree is not full are marked empty, and a node's present children come first).
// Trained by hierarchical k-majority clustering with k-means++ seeding; words carry IDF
// weights. Saved as a flatbuffers file (schemas/vocabulary.fbs) that is memory-mapped on load
// and read in place.
// Concurrency: a loaded Vocabulary is immutable; Transform and Score may run on many threads.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <span>
#include <string>

#include "ecs/bow.h"
#include "ecs/descriptor.h"

namespace flatslam {

struct VocabularyTrainOptions {
  int branching = 10;
  int levels = 6;           // depth of the leaves below the root
  int max_iterations = 10;  // k-majority iterations per cluster
  uint64_t seed = 1;
  // Called with (descriptors settled in a word, descriptors in all) as training proceeds, from
  // worker threads one call at a time; may be empty.
  std::function<void(size_t, size_t)> progress;
  [[nodiscard]] bool Check() const;
};

class Vocabulary {
 public:
  Vocabulary();
  ~Vocabulary();
  Vocabulary(Vocabulary&&) noexcept;
  Vocabulary& operator=(Vocabulary&&) noexcept;
  Vocabulary(const Vocabulary&) = delete;
  Vocabulary& operator=(const Vocabulary&) = delete;

  // Clusters `descriptors` (left unchanged) into a tree and weights each word by
  // IDF = log(N / n_i) over the `image_count` images the descriptors came from, where
  // `image_of[k]` names the image of descriptor k. Throws flatslam::Error on bad options or
  // too few descriptors. Every word of the result is reachable and has a positive weight.
  [[nodiscard]] static Vocabulary Train(std::span<const Descriptor> descriptors, std::span<const uint32_t> image_of,
                                        size_t image_count, const VocabularyTrainOptions& options);
  // Writes the flatbuffers file atomically (core/atomic_write.h: temporary file, fsync, rename,
  // directory fsync).
  void Save(const std::filesystem::path& path) const;
  // Memory-maps and verifies a vocabulary file; throws flatslam::Error naming the file and the
  // problem (missing, truncated, not a vocabulary, unsupported version, inconsistent tree).
  [[nodiscard]] static Vocabulary Load(const std::filesystem::path& path);
  // A vocabulary from explicit implicit-tree arrays (tests, benchmarks, converters):
  // node_descriptors and child_counts have one entry per node slot (node_count_for(branching,
  // levels)); a node's present children come first in its block; leaves get word ids in slot
  // order; word_weights has one positive weight per leaf. Throws flatslam::Error when the arrays
  // do not describe a consistent tree.
  [[nodiscard]] static Vocabulary FromNodes(int branching, int levels, std::span<const Descriptor> node_descriptors,
                                            std::span<const uint8_t> child_counts, std::span<const float> word_weights);
  // Slots of the implicit array of a tree with this branching and depth: (B^(L+1) - 1) / (B - 1).
  [[nodiscard]] static size_t node_count_for(int branching, int levels);

  [[nodiscard]] bool empty() const;
  [[nodiscard]] int branching() const;
  [[nodiscard]] int levels() const;
  [[nodiscard]] size_t word_count() const;
  [[nodiscard]] size_t node_count() const;  // slots of the implicit array, empty ones included
  // Identity of the vocabulary (a checksum of its content), stored in map snapshots.
  [[nodiscard]] uint64_t checksum() const;
  [[nodiscard]] float weight(WordId word) const;  // IDF
  // Training statistics stored in the file (0 for FromNodes).
  [[nodiscard]] uint64_t training_descriptors() const;
  [[nodiscard]] uint64_t training_images() const;
  // Size in bytes of the flatbuffers file this vocabulary is (or would be saved as).
  [[nodiscard]] size_t byte_size() const;

  // The implicit tree, for tests and tools. Node slots are [0, node_count()).
  static constexpr WordId kInnerNode = 0xFFFFFFFEu;
  static constexpr WordId kEmptyNode = 0xFFFFFFFFu;
  // Word id of a leaf slot, kInnerNode or kEmptyNode.
  [[nodiscard]] WordId node_word(uint32_t node) const;
  [[nodiscard]] const Descriptor& node_descriptor(uint32_t node) const;
  [[nodiscard]] int node_children(uint32_t node) const;  // present children, first in the block

  // Descends the tree (closest child by Hamming distance at each level) to a word.
  [[nodiscard]] WordId Transform(const Descriptor& descriptor) const;
  // Same, also returning the node on the path at depth `node_depth` (1 = a child of the root).
  [[nodiscard]] WordId Transform(const Descriptor& descriptor, int node_depth, uint32_t* node) const;
  // Bag of words (TF-IDF, L1-normalized) of a whole image, descriptors transformed in parallel;
  // *features (may be null) gets the direct index at `node_depth`.
  void Transform(std::span<const Descriptor> descriptors, BowVector* bow, FeatureVector* features,
                 int node_depth = 2) const;

  // DBoW2's L1 score of two L1-normalized vectors: 1 - 0.5 * |a - b|_1, in [0, 1].
  [[nodiscard]] static float Score(const BowVector& a, const BowVector& b);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  explicit Vocabulary(std::unique_ptr<Impl> impl);
};

// The vocabulary shipped with the sources (data/vocabulary/orb.fsvc in the source tree), or the
// file named by the environment variable FLATSLAM_VOCABULARY when it is set and not empty.
[[nodiscard]] std::filesystem::path DefaultVocabularyPath();

}  // namespace flatslam
