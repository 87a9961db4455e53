// A bag-of-words vocabulary tree for 256-bit ORB descriptors, stored as an implicit tree:
// nodes in breadth-first order in one contiguous array; for branching B the children of node i
// are nodes (i+1)*B .. (i+1)*B+B-1 (node 0 is the root; slots where the tree is not full are
// marked empty). Trained by hierarchical k-majority clustering with k-means++ seeding; words
// carry IDF weights. Saved as a flatbuffers file (schemas/vocabulary.fbs) that is memory-mapped
// on load and read in place.
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
  int levels = 6;            // depth of the leaves below the root
  int max_iterations = 10;   // k-majority iterations per cluster
  uint64_t seed = 1;
  // Called with (clusters done, clusters planned) as training proceeds; may be empty.
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
  // Writes the flatbuffers file atomically (temporary file, flush, rename).
  void Save(const std::filesystem::path& path) const;
  // Memory-maps and verifies a vocabulary file; throws flatslam::Error naming the file and the
  // problem (missing, truncated, not a vocabulary, unsupported version, inconsistent tree).
  [[nodiscard]] static Vocabulary Load(const std::filesystem::path& path);

  [[nodiscard]] bool empty() const;
  [[nodiscard]] int branching() const;
  [[nodiscard]] int levels() const;
  [[nodiscard]] size_t word_count() const;
  [[nodiscard]] size_t node_count() const;  // slots of the implicit array, empty ones included
  // Identity of the vocabulary (a checksum of its content), stored in map snapshots.
  [[nodiscard]] uint64_t checksum() const;
  [[nodiscard]] float weight(WordId word) const;  // IDF

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
};

}  // namespace flatslam
