#include "place/vocabulary.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/parallel_sort.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cassert>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <random>
#include <utility>
#include <vector>

#include "core/atomic_write.h"
#include "core/error.h"
#include "core/mapped_file.h"
#include "flatslam/schemas/vocabulary_generated.h"

#ifndef FLATSLAM_DEFAULT_VOCABULARY
#define FLATSLAM_DEFAULT_VOCABULARY "data/vocabulary/orb.fsvc"
#endif

namespace flatslam {

namespace fbv = fbs::vocab;

namespace {

constexpr uint32_t kFormatVersion = 1;
constexpr int kMaxBranching = 64;
constexpr int kMaxLevels = 16;
// Keeps the descriptor array (32 bytes a slot) of one file under flatbuffers' 2 GiB limit.
constexpr uint64_t kMaxNodes = 50'000'000;
// Clusters with at least this many members split their assignment step over threads.
constexpr size_t kParallelMembers = 8192;

static_assert(sizeof(fbv::Descriptor256) == sizeof(Descriptor), "descriptor layout");
static_assert(std::endian::native == std::endian::little, "the vocabulary file is read in place (little-endian)");

// ---------------------------------------------------------------------------------------------
// Content checksum: 64-bit multiply-rotate lanes over 1 MiB chunks (hashed in parallel), then
// over the chunk hashes. Fixed chunking keeps the value independent of the thread count.

constexpr uint64_t kPrime1 = 0x9E3779B185EBCA87ull;
constexpr uint64_t kPrime2 = 0xC2B2AE3D27D4EB4Full;
constexpr uint64_t kPrime3 = 0x165667B19E3779F9ull;
constexpr size_t kHashChunk = size_t{1} << 20;

uint64_t Avalanche(uint64_t h) {
  h ^= h >> 33;
  h *= kPrime2;
  h ^= h >> 29;
  h *= kPrime3;
  h ^= h >> 32;
  return h;
}

uint64_t Load64(const uint8_t* p) {
  uint64_t v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

// Eight independent lanes, one multiply per 8 bytes: each step is a bijection of its lane, so a
// change to any single word always changes the result.
uint64_t HashChunk(const uint8_t* data, size_t size, uint64_t seed) {
  uint64_t lane[8];
  for (int j = 0; j < 8; ++j) lane[j] = seed + kPrime1 * static_cast<uint64_t>(j + 1);
  size_t i = 0;
  for (; i + 64 <= size; i += 64) {
    for (int j = 0; j < 8; ++j) lane[j] = std::rotl((lane[j] ^ Load64(data + i + 8 * j)) * kPrime2, 29);
  }
  uint8_t tail[64] = {};
  if (size > i) std::memcpy(tail, data + i, size - i);
  for (int j = 0; j < 8; ++j) lane[j] = std::rotl((lane[j] ^ Load64(tail + 8 * j)) * kPrime2, 29);
  uint64_t h = static_cast<uint64_t>(size) * kPrime3;
  for (int j = 0; j < 8; ++j) h = std::rotl(h, 7) + lane[j];
  return Avalanche(h);
}

uint64_t HashBytes(const void* data, size_t size, uint64_t seed) {
  const auto* bytes = static_cast<const uint8_t*>(data);
  if (size <= kHashChunk) return HashChunk(bytes, size, seed);
  const size_t chunks = (size + kHashChunk - 1) / kHashChunk;
  std::vector<uint64_t> hashes(chunks);
  tbb::parallel_for(size_t{0}, chunks, [&](size_t c) {
    const size_t begin = c * kHashChunk;
    hashes[c] = HashChunk(bytes + begin, std::min(kHashChunk, size - begin), seed + c);
  });
  return HashChunk(reinterpret_cast<const uint8_t*>(hashes.data()), chunks * sizeof(uint64_t), seed ^ size);
}

struct TreeView {
  uint32_t branching = 0, levels = 0, word_count = 0, node_count = 0;
  uint64_t training_descriptors = 0, training_images = 0;
  const Descriptor* descriptors = nullptr;
  const uint8_t* child_count = nullptr;
  const WordId* word = nullptr;
  const float* weight = nullptr;
};

uint64_t ContentChecksum(const TreeView& t) {
  const uint64_t header[5] = {t.branching, t.levels, t.word_count, t.training_descriptors, t.training_images};
  const uint64_t parts[5] = {
      HashBytes(header, sizeof(header), 1),
      HashBytes(t.descriptors, size_t{t.node_count} * sizeof(Descriptor), 2),
      HashBytes(t.child_count, t.node_count, 3),
      HashBytes(t.word, size_t{t.node_count} * sizeof(WordId), 4),
      HashBytes(t.weight, size_t{t.word_count} * sizeof(float), 5),
  };
  return HashChunk(reinterpret_cast<const uint8_t*>(parts), sizeof(parts), 0x46535643ull);
}

// Slots of a full tree, or 0 when it would exceed kMaxNodes (or the arguments are out of range).
uint64_t NodeCount(uint64_t branching, uint64_t levels) {
  if (branching < 2 || levels < 1) return 0;
  uint64_t total = 1, level_size = 1;
  for (uint64_t d = 1; d <= levels; ++d) {
    level_size *= branching;
    total += level_size;
    if (total > kMaxNodes) return 0;
  }
  return total;
}

// A 64-bit mix of two values, for deriving per-cluster generator seeds.
uint64_t MixSeed(uint64_t a, uint64_t b) {
  uint64_t z = a + 0x9E3779B97F4A7C15ull * (b + 1);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// Uniform integer in [0, bound) from a 64-bit generator (multiply-shift; bound > 0).
uint64_t Below(std::mt19937_64& rng, uint64_t bound) {
  return static_cast<uint64_t>((static_cast<unsigned __int128>(rng()) * bound) >> 64);
}

// Word ids (leaves numbered in slot order), kInnerNode or kEmptyNode per slot, from the child
// counts alone. Throws when a slot that no parent claims has children.
std::vector<WordId> NumberWords(uint32_t branching, std::span<const uint8_t> child_count, const std::string& what) {
  const size_t n = child_count.size();
  std::vector<WordId> word(n, Vocabulary::kEmptyNode);
  FLATSLAM_CHECK(n > 0 && child_count[0] > 0, what, ": the root has no children");
  WordId next = 0;
  for (size_t i = 0; i < n; ++i) {
    bool present = i == 0;
    if (i > 0) {
      const size_t parent = (i - 1) / branching;
      present = word[parent] == Vocabulary::kInnerNode && (i - 1) % branching < child_count[parent];
    }
    if (!present) {
      FLATSLAM_CHECK(child_count[i] == 0, what, ": empty slot ", i, " has ", int(child_count[i]), " children");
      continue;
    }
    FLATSLAM_CHECK(child_count[i] <= branching, what, ": node ", i, " has ", int(child_count[i]),
                   " children, more than the branching ", branching);
    FLATSLAM_CHECK(child_count[i] == 0 || uint64_t{i} * branching + child_count[i] < n, what, ": node ", i,
                   " at the deepest level has children");
    word[i] = child_count[i] > 0 ? Vocabulary::kInnerNode : next++;
  }
  return word;
}

// Checks the tree: every slot agrees with its parent's child count, leaves are numbered 0.. in
// slot order, weights are positive. O(node_count), one pass.
void CheckTree(const TreeView& t, const std::string& what) {
  const uint32_t b = t.branching;
  FLATSLAM_CHECK(t.word[0] == Vocabulary::kInnerNode && t.child_count[0] >= 1 && t.child_count[0] <= b, what,
                 ": inconsistent tree: the root is not an inner node with 1..", b, " children");
  WordId next = 0;
  // Parent by parent, so each slot's parent is known without a division; blocks follow each
  // other in slot order, so leaves are met in slot order too.
  for (uint64_t parent = 0;; ++parent) {
    const uint64_t first = parent * b + 1;
    if (first >= t.node_count) break;
    const uint32_t present = t.word[parent] == Vocabulary::kInnerNode ? t.child_count[parent] : 0;
    for (uint32_t j = 0; j < b; ++j) {
      const uint64_t i = first + j;
      const WordId w = t.word[i];
      const uint32_t cc = t.child_count[i];
      if (j >= present) {
        if (w != Vocabulary::kEmptyNode || cc != 0)
          Fail(what, ": inconsistent tree: slot ", i, " is outside its parent's children but not marked empty");
      } else if (w == Vocabulary::kInnerNode) {
        if (cc == 0 || cc > b || i * b + cc >= t.node_count)
          Fail(what, ": inconsistent tree: inner node ", i, " has ", cc, " children");
      } else if (w != next || cc != 0) {
        Fail(what, ": inconsistent tree: leaf slot ", i, " has word ", w, " (expected ", next, ") and ", cc,
             " children");
      } else {
        ++next;
      }
    }
  }
  FLATSLAM_CHECK(next == t.word_count, what, ": inconsistent tree: ", next, " leaves for ", t.word_count, " words");
  for (uint32_t w = 0; w < t.word_count; ++w) {
    if (!(t.weight[w] > 0.f) || !std::isfinite(t.weight[w]))
      Fail(what, ": word ", w, " has weight ", t.weight[w], " (must be positive and finite)");
  }
}

// Index of the child closest to d, the first one on ties (count <= 256). Distance and index are
// packed into one key and the smallest key wins, so there is no data-dependent branch.
inline uint32_t ClosestChild(const Descriptor& d, const Descriptor* child, uint32_t count) {
  uint32_t best = ~0u;
  for (uint32_t j = 0; j < count; ++j) {
    best = std::min(best, (static_cast<uint32_t>(DescriptorDistance(d, child[j])) << 8) | j);
  }
  return best & 0xFF;
}

// Requests every cache line of a child block at once, so a descent pays one memory latency per
// level rather than one per line.
inline void PrefetchBlock(const Descriptor* block, uint32_t count) {
  const char* p = reinterpret_cast<const char*>(block);
  const char* end = reinterpret_cast<const char*>(block + count);
  for (; p < end; p += 64) __builtin_prefetch(p);
}

constexpr int kFrameLanes = 8;

// Descends kLanes descriptors level by level in lockstep (their memory latencies overlap) to
// words[]; nodes (may be null) gets each one's node at depth node_depth (the leaf when shallower).
// After choosing a node, the next level's descriptors, child counts and word ids are requested
// together, so each level costs about one memory latency.
template <int kLanes>
inline void DescendBatch(const TreeView& t, const Descriptor* descriptors, int node_depth, WordId* words,
                         uint32_t* nodes) {
  const uint32_t b = t.branching;
  uint32_t node[kLanes] = {};
  uint32_t active = (1u << kLanes) - 1;
  if (nodes != nullptr) {
    for (int lane = 0; lane < kLanes; ++lane) nodes[lane] = 0;
  }
  for (int depth = 1; active != 0; ++depth) {
    for (int lane = 0; lane < kLanes; ++lane) {
      if (!(active >> lane & 1)) continue;
      const uint32_t count = t.child_count[node[lane]];
      if (count == 0) {
        active &= ~(1u << lane);
        words[lane] = t.word[node[lane]];
        continue;
      }
      const uint32_t first = node[lane] * b + 1;
      node[lane] = first + ClosestChild(descriptors[lane], t.descriptors + first, count);
      if (nodes != nullptr && depth <= node_depth) nodes[lane] = node[lane];
      const uint64_t next = uint64_t{node[lane]} * b + 1;
      if (next < t.node_count) {
        PrefetchBlock(t.descriptors + next, b);
        __builtin_prefetch(t.child_count + next);
        __builtin_prefetch(t.word + next);
      }
    }
  }
}

std::string Printable(const uint8_t* p, size_t n) {
  std::string s;
  for (size_t i = 0; i < n; ++i) {
    char buf[8];
    if (p[i] >= 0x20 && p[i] < 0x7f) {
      s += static_cast<char>(p[i]);
    } else {
      std::snprintf(buf, sizeof(buf), "\\x%02x", p[i]);
      s += buf;
    }
  }
  return s;
}

}  // namespace

// ---------------------------------------------------------------------------------------------

struct Vocabulary::Impl {
  std::vector<uint64_t> owned;  // the buffer of a trained or assembled vocabulary (8-byte aligned)
  MappedFile file;              // or the mapped file
  const uint8_t* bytes = nullptr;
  size_t size = 0;

  TreeView tree;
  uint64_t checksum = 0;

  Impl() = default;
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  ~Impl() = default;

  // Serializes the arrays into a flatbuffer held by a new Impl, then verifies it as a loaded file.
  static std::unique_ptr<Impl> Build(uint32_t branching, uint32_t levels, std::span<const Descriptor> descriptors,
                                     std::span<const uint8_t> child_count, std::span<const WordId> word,
                                     std::span<const float> weight, uint64_t training_descriptors,
                                     uint64_t training_images, const std::string& what) {
    TreeView t;
    t.branching = branching;
    t.levels = levels;
    t.word_count = static_cast<uint32_t>(weight.size());
    t.node_count = static_cast<uint32_t>(descriptors.size());
    t.descriptors = descriptors.data();
    t.child_count = child_count.data();
    t.word = word.data();
    t.weight = weight.data();
    t.training_descriptors = training_descriptors;
    t.training_images = training_images;
    const uint64_t checksum = ContentChecksum(t);

    flatbuffers::FlatBufferBuilder fbb(descriptors.size() * (sizeof(Descriptor) + 5) + weight.size() * 4 + 1024);
    const auto d =
        fbb.CreateVectorOfStructs(reinterpret_cast<const fbv::Descriptor256*>(descriptors.data()), descriptors.size());
    const auto c = fbb.CreateVector(child_count.data(), child_count.size());
    const auto w = fbb.CreateVector(word.data(), word.size());
    const auto g = fbb.CreateVector(weight.data(), weight.size());
    const auto root = fbv::CreateVocabulary(fbb, kFormatVersion, branching, levels, t.word_count, checksum, d, c, w, g,
                                            training_descriptors, training_images);
    fbv::FinishVocabularyBuffer(fbb, root);

    auto impl = std::make_unique<Impl>();
    impl->size = fbb.GetSize();
    impl->owned.resize((impl->size + 7) / 8);
    std::memcpy(impl->owned.data(), fbb.GetBufferPointer(), impl->size);
    impl->bytes = reinterpret_cast<const uint8_t*>(impl->owned.data());
    impl->Attach(what);
    return impl;
  }

  // Verifies bytes[0, size) and points the tree view into it; throws naming `what`.
  void Attach(const std::string& what) {
    FLATSLAM_CHECK(size >= 8, what, ": truncated (", size, " bytes)");
    FLATSLAM_CHECK(size < FLATBUFFERS_MAX_BUFFER_SIZE, what, ": too large (", size, " bytes)");
    if (!flatbuffers::BufferHasIdentifier(bytes, fbv::VocabularyIdentifier())) {
      Fail(what, ": not a flatslam vocabulary (file identifier '", Printable(bytes + 4, 4), "', expected '",
           fbv::VocabularyIdentifier(), "')");
    }
    flatbuffers::Verifier verifier(bytes, size);
    FLATSLAM_CHECK(fbv::VerifyVocabularyBuffer(verifier), what, ": corrupt or truncated (", size,
                   " bytes): flatbuffers verification failed");
    const fbv::Vocabulary* root = fbv::GetVocabulary(bytes);
    FLATSLAM_CHECK(root->format_version() != 0, what, ": no format version");
    FLATSLAM_CHECK(root->format_version() <= kFormatVersion, what, ": format version ", root->format_version(),
                   " is newer than this build reads (", kFormatVersion, ")");
    const uint64_t nodes = NodeCount(root->branching(), root->levels());
    FLATSLAM_CHECK(root->branching() <= kMaxBranching && root->levels() <= kMaxLevels && nodes > 0, what,
                   ": unsupported shape: branching ", root->branching(), ", levels ", root->levels());
    FLATSLAM_CHECK(root->descriptors() && root->child_count() && root->word() && root->weight(), what,
                   ": missing node or weight arrays");
    FLATSLAM_CHECK(
        root->descriptors()->size() == nodes && root->child_count()->size() == nodes && root->word()->size() == nodes,
        what, ": node arrays hold ", root->descriptors()->size(), "/", root->child_count()->size(), "/",
        root->word()->size(), " slots, expected ", nodes);
    FLATSLAM_CHECK(root->word_count() > 0 && root->weight()->size() == root->word_count(), what, ": ",
                   root->weight()->size(), " weights for ", root->word_count(), " words");
    tree.branching = root->branching();
    tree.levels = root->levels();
    tree.word_count = root->word_count();
    tree.node_count = static_cast<uint32_t>(nodes);
    tree.descriptors = reinterpret_cast<const Descriptor*>(root->descriptors()->Data());
    tree.child_count = root->child_count()->data();
    tree.word = root->word()->data();
    tree.weight = root->weight()->data();
    tree.training_descriptors = root->training_descriptors();
    tree.training_images = root->training_images();
    // The tree check and the checksum read different bytes; run them side by side.
    uint64_t actual = 0;
    tbb::parallel_invoke([&] { CheckTree(tree, what); }, [&] { actual = ContentChecksum(tree); });
    checksum = root->checksum();
    if (actual != checksum) {
      char buf[80];
      std::snprintf(buf, sizeof(buf), "stored %016llx, content %016llx", static_cast<unsigned long long>(checksum),
                    static_cast<unsigned long long>(actual));
      Fail(what, ": checksum mismatch (", buf, "): the file is corrupt");
    }
  }
};

namespace {

// ---------------------------------------------------------------------------------------------
// Training: hierarchical k-majority, one task per cluster.

// kSpread[b]: byte b's eight bits as eight 8-bit lanes of a uint64 (bit j -> lane j).
constexpr std::array<uint64_t, 256> MakeSpread() {
  std::array<uint64_t, 256> table{};
  for (int b = 0; b < 256; ++b) {
    for (int j = 0; j < 8; ++j) table[b] |= static_cast<uint64_t>((b >> j) & 1) << (8 * j);
  }
  return table;
}
constexpr std::array<uint64_t, 256> kSpread = MakeSpread();

// Bitwise majority of data[idx[k]] (a bit is set when set in more than half of them).
Descriptor Majority(std::span<const Descriptor> data, std::span<const uint32_t> idx) {
  uint32_t counts[256] = {};
  size_t k = 0;
  while (k < idx.size()) {
    // Eight 8-bit counters per descriptor byte; flushed before any lane can pass 255.
    uint64_t lanes[32] = {};
    const size_t end = std::min(idx.size(), k + 255);
    for (; k < end; ++k) {
      uint8_t bytes[32];
      std::memcpy(bytes, data[idx[k]].data(), 32);
      for (int p = 0; p < 32; ++p) lanes[p] += kSpread[bytes[p]];
    }
    for (int p = 0; p < 32; ++p) {
      for (int j = 0; j < 8; ++j) counts[p * 8 + j] += static_cast<uint32_t>((lanes[p] >> (8 * j)) & 0xFF);
    }
  }
  Descriptor center{};
  for (int bit = 0; bit < 256; ++bit) {
    if (2 * size_t{counts[bit]} > idx.size()) center[bit / 64] |= uint64_t{1} << (bit % 64);
  }
  return center;
}

// Closest center (first on ties), the same choice Vocabulary::Transform makes.
uint32_t Nearest(const Descriptor& d, const std::vector<Descriptor>& centers) {
  return ClosestChild(d, centers.data(), static_cast<uint32_t>(centers.size()));
}

template <class Body>
void ForMembers(size_t n, const Body& body) {
  if (n < kParallelMembers) {
    body(size_t{0}, n);
  } else {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 2048),
                      [&](const tbb::blocked_range<size_t>& r) { body(r.begin(), r.end()); });
  }
}

class Trainer {
 public:
  Trainer(std::span<const Descriptor> data, const VocabularyTrainOptions& options)
      : data_(data),
        options_(options),
        branching_(static_cast<uint32_t>(options.branching)),
        node_count_(NodeCount(options.branching, options.levels)),
        descriptors_(node_count_, Descriptor{}),
        child_count_(node_count_, 0),
        leaf_of_(data.size(), 0) {}

  void Run() {
    std::vector<uint32_t> all(data_.size());
    for (uint32_t k = 0; k < all.size(); ++k) all[k] = k;
    ClusterNode(0, 0, std::move(all));
  }

  std::vector<Descriptor>& descriptors() { return descriptors_; }
  std::vector<uint8_t>& child_count() { return child_count_; }
  const std::vector<uint32_t>& leaf_of() const { return leaf_of_; }

 private:
  void ClusterNode(uint32_t node, int depth, std::vector<uint32_t> members) {
    std::vector<Descriptor> centers;
    std::vector<std::vector<uint32_t>> groups;
    if (depth < options_.levels) Split(node, members, &centers, &groups);
    if (groups.size() <= 1) {
      for (uint32_t k : members) leaf_of_[k] = node;
      Settled(members.size());
      return;
    }
    std::vector<uint32_t>().swap(members);
    child_count_[node] = static_cast<uint8_t>(groups.size());
    const uint32_t first = node * branching_ + 1;
    for (size_t j = 0; j < centers.size(); ++j) descriptors_[first + j] = centers[j];
    tbb::parallel_for(size_t{0}, groups.size(), [&](size_t j) {
      ClusterNode(first + static_cast<uint32_t>(j), depth + 1, std::move(groups[j]));
    });
  }

  // Partitions `members` into at most B non-empty groups with their centers (copies, never
  // references into the data), in the order Transform scans them.
  void Split(uint32_t node, const std::vector<uint32_t>& members, std::vector<Descriptor>* centers,
             std::vector<std::vector<uint32_t>>* groups) const {
    const size_t n = members.size();
    const size_t k_max = branching_;
    if (n <= k_max) {
      // Few descriptors: each distinct one is its own cluster.
      for (uint32_t m : members) centers->push_back(data_[m]);
      std::sort(centers->begin(), centers->end());
      centers->erase(std::unique(centers->begin(), centers->end()), centers->end());
      groups->resize(centers->size());
      for (uint32_t m : members) {
        const auto it = std::lower_bound(centers->begin(), centers->end(), data_[m]);
        (*groups)[it - centers->begin()].push_back(m);
      }
      return;
    }

    // k-means++ seeding: each new seed drawn with probability proportional to D^2.
    std::mt19937_64 rng(MixSeed(options_.seed, node));
    centers->push_back(data_[members[Below(rng, n)]]);
    std::vector<uint32_t> d2(n);
    ForMembers(n, [&](size_t begin, size_t end) {
      for (size_t k = begin; k < end; ++k) {
        const uint32_t d = DescriptorDistance(data_[members[k]], centers->front());
        d2[k] = d * d;
      }
    });
    while (centers->size() < k_max) {
      uint64_t total = 0;
      for (uint32_t v : d2) total += v;
      if (total == 0) break;  // every member equals a seed
      uint64_t r = Below(rng, total);
      size_t pick = 0;
      while (r >= d2[pick]) r -= d2[pick++];
      centers->push_back(data_[members[pick]]);
      const Descriptor& seed = centers->back();
      ForMembers(n, [&](size_t begin, size_t end) {
        for (size_t k = begin; k < end; ++k) {
          const uint32_t d = DescriptorDistance(data_[members[k]], seed);
          d2[k] = std::min(d2[k], d * d);
        }
      });
    }
    std::vector<uint32_t>().swap(d2);

    // k-majority: assign to the nearest center, move each center to its members' majority.
    std::vector<uint32_t> assignment(n, 0);
    auto assign = [&] {
      std::atomic<bool> changed{false};
      ForMembers(n, [&](size_t begin, size_t end) {
        bool local = false;
        for (size_t k = begin; k < end; ++k) {
          const uint32_t j = Nearest(data_[members[k]], *centers);
          local |= j != assignment[k];
          assignment[k] = j;
        }
        if (local) changed.store(true, std::memory_order_relaxed);
      });
      return changed.load();
    };
    auto collect = [&] {
      groups->assign(centers->size(), {});
      for (size_t k = 0; k < n; ++k) (*groups)[assignment[k]].push_back(members[k]);
    };
    assign();
    for (int iteration = 0; iteration < options_.max_iterations; ++iteration) {
      collect();
      auto update = [&](size_t j) {
        if (!(*groups)[j].empty()) (*centers)[j] = Majority(data_, (*groups)[j]);  // an empty one keeps its place
      };
      if (n >= kParallelMembers) {
        tbb::parallel_for(size_t{0}, centers->size(), update);
      } else {
        for (size_t j = 0; j < centers->size(); ++j) update(j);
      }
      if (!assign()) break;
    }
    // The final partition is the nearest-center partition of the final centers, so every member
    // descends into its own group; clusters left empty are dropped and create no node.
    collect();
    size_t kept = 0;
    for (size_t j = 0; j < centers->size(); ++j) {
      if ((*groups)[j].empty()) continue;
      if (kept != j) {
        (*centers)[kept] = (*centers)[j];
        (*groups)[kept] = std::move((*groups)[j]);
      }
      ++kept;
    }
    centers->resize(kept);
    groups->resize(kept);
  }

  void Settled(size_t count) {
    const size_t done = settled_.fetch_add(count) + count;
    if (options_.progress) {
      std::lock_guard<std::mutex> lock(progress_mutex_);
      options_.progress(done, data_.size());
    }
  }

  std::span<const Descriptor> data_;
  const VocabularyTrainOptions& options_;
  uint32_t branching_;
  uint64_t node_count_;
  std::vector<Descriptor> descriptors_;
  std::vector<uint8_t> child_count_;
  std::vector<uint32_t> leaf_of_;  // per training descriptor: the leaf slot it settled in
  std::atomic<size_t> settled_{0};
  std::mutex progress_mutex_;
};

}  // namespace

// ---------------------------------------------------------------------------------------------

bool VocabularyTrainOptions::Check() const {
  return branching >= 2 && branching <= kMaxBranching && levels >= 1 && levels <= kMaxLevels &&
         NodeCount(branching, levels) > 0 && max_iterations >= 0;
}

Vocabulary::Vocabulary() = default;
Vocabulary::~Vocabulary() = default;
Vocabulary::Vocabulary(Vocabulary&&) noexcept = default;
Vocabulary& Vocabulary::operator=(Vocabulary&&) noexcept = default;
Vocabulary::Vocabulary(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

size_t Vocabulary::node_count_for(int branching, int levels) {
  return branching < 2 || levels < 1 ? 0 : NodeCount(branching, levels);
}

Vocabulary Vocabulary::Train(std::span<const Descriptor> descriptors, std::span<const uint32_t> image_of,
                             size_t image_count, const VocabularyTrainOptions& options) {
  FLATSLAM_CHECK(options.Check(), "Vocabulary::Train: bad options (branching ", options.branching, ", levels ",
                 options.levels, ", max_iterations ", options.max_iterations, "; at most ", kMaxNodes, " nodes)");
  FLATSLAM_CHECK(image_of.size() == descriptors.size(), "Vocabulary::Train: ", image_of.size(), " image indices for ",
                 descriptors.size(), " descriptors");
  FLATSLAM_CHECK(descriptors.size() < (uint64_t{1} << 32), "Vocabulary::Train: too many descriptors");
  FLATSLAM_CHECK(image_count >= 1, "Vocabulary::Train: image_count must be at least 1");
  for (size_t k = 0; k < image_of.size(); ++k) {
    FLATSLAM_CHECK(image_of[k] < image_count, "Vocabulary::Train: descriptor ", k, " names image ", image_of[k], " of ",
                   image_count);
  }

  Trainer trainer(descriptors, options);
  trainer.Run();
  FLATSLAM_CHECK(trainer.child_count()[0] >= 2, "Vocabulary::Train: need at least 2 distinct descriptors, got ",
                 descriptors.size(), " descriptor(s) with fewer");

  const std::vector<WordId> word = NumberWords(options.branching, trainer.child_count(), "Vocabulary::Train");
  size_t word_count = 0;
  for (WordId w : word) word_count += w < kInnerNode;

  // IDF: n_i = images with at least one descriptor in word i (at least one, since every word
  // holds training descriptors). A word in every image would weigh log(1) = 0; it is counted as
  // in N - 1/2 images instead, which keeps it positive and below every rarer word.
  std::vector<uint64_t> pairs(descriptors.size());
  const std::vector<uint32_t>& leaf_of = trainer.leaf_of();
  tbb::parallel_for(size_t{0}, pairs.size(),
                    [&](size_t k) { pairs[k] = (uint64_t{word[leaf_of[k]]} << 32) | image_of[k]; });
  tbb::parallel_sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  std::vector<uint32_t> images_with(word_count, 0);
  for (uint64_t p : pairs) ++images_with[p >> 32];
  std::vector<float> weight(word_count);
  const double n_images = static_cast<double>(image_count);
  for (size_t w = 0; w < word_count; ++w) {
    FLATSLAM_CHECK(images_with[w] > 0, "Vocabulary::Train: internal error: word ", w, " holds no descriptor");
    const double n_i = images_with[w] < image_count ? images_with[w] : n_images - 0.5;
    weight[w] = static_cast<float>(std::log(n_images / n_i));
  }

  return Vocabulary(Impl::Build(options.branching, options.levels, trainer.descriptors(), trainer.child_count(), word,
                                weight, descriptors.size(), image_count, "Vocabulary::Train"));
}

Vocabulary Vocabulary::FromNodes(int branching, int levels, std::span<const Descriptor> node_descriptors,
                                 std::span<const uint8_t> child_counts, std::span<const float> word_weights) {
  const uint64_t nodes = node_count_for(branching, levels);
  FLATSLAM_CHECK(nodes > 0 && branching <= kMaxBranching && levels <= kMaxLevels,
                 "Vocabulary::FromNodes: unsupported shape: branching ", branching, ", levels ", levels);
  FLATSLAM_CHECK(node_descriptors.size() == nodes && child_counts.size() == nodes,
                 "Vocabulary::FromNodes: ", node_descriptors.size(), " descriptors and ", child_counts.size(),
                 " child counts for ", nodes, " slots");
  const std::vector<WordId> word = NumberWords(branching, child_counts, "Vocabulary::FromNodes");
  size_t word_count = 0;
  for (WordId w : word) word_count += w < kInnerNode;
  FLATSLAM_CHECK(word_weights.size() == word_count, "Vocabulary::FromNodes: ", word_weights.size(), " weights for ",
                 word_count, " leaves");
  return Vocabulary(Impl::Build(branching, levels, node_descriptors, child_counts, word, word_weights, 0, 0,
                                "Vocabulary::FromNodes"));
}

void Vocabulary::Save(const std::filesystem::path& path) const {
  FLATSLAM_CHECK(impl_ != nullptr, "Vocabulary::Save: empty vocabulary, nothing to write to '", path.string(), "'");
  try {
    WriteFileAtomically(path, [&](std::FILE* file) { std::fwrite(impl_->bytes, 1, impl_->size, file); });
  } catch (const Error& e) {
    Fail("vocabulary file: ", e.what());
  }
}

Vocabulary Vocabulary::Load(const std::filesystem::path& path) {
  const std::string what = "vocabulary file '" + path.string() + "'";
  auto impl = std::make_unique<Impl>();
  impl->file = MappedFile::Open(path, what, /*min_size=*/8, /*populate=*/true);
  impl->bytes = impl->file.bytes().data();
  impl->size = impl->file.bytes().size();
  impl->Attach(what);
  return Vocabulary(std::move(impl));
}

bool Vocabulary::empty() const {
  return impl_ == nullptr;
}
int Vocabulary::branching() const {
  return impl_ ? static_cast<int>(impl_->tree.branching) : 0;
}
int Vocabulary::levels() const {
  return impl_ ? static_cast<int>(impl_->tree.levels) : 0;
}
size_t Vocabulary::word_count() const {
  return impl_ ? impl_->tree.word_count : 0;
}
size_t Vocabulary::node_count() const {
  return impl_ ? impl_->tree.node_count : 0;
}
uint64_t Vocabulary::checksum() const {
  return impl_ ? impl_->checksum : 0;
}
uint64_t Vocabulary::training_descriptors() const {
  return impl_ ? impl_->tree.training_descriptors : 0;
}
uint64_t Vocabulary::training_images() const {
  return impl_ ? impl_->tree.training_images : 0;
}
size_t Vocabulary::byte_size() const {
  return impl_ ? impl_->size : 0;
}

float Vocabulary::weight(WordId word) const {
  FLATSLAM_CHECK(impl_ && word < impl_->tree.word_count, "Vocabulary::weight: word ", word, " out of range (",
                 word_count(), " words)");
  return impl_->tree.weight[word];
}

WordId Vocabulary::node_word(uint32_t node) const {
  FLATSLAM_CHECK(impl_ && node < impl_->tree.node_count, "Vocabulary::node_word: slot ", node, " out of range");
  return impl_->tree.word[node];
}

const Descriptor& Vocabulary::node_descriptor(uint32_t node) const {
  FLATSLAM_CHECK(impl_ && node < impl_->tree.node_count, "Vocabulary::node_descriptor: slot ", node, " out of range");
  return impl_->tree.descriptors[node];
}

int Vocabulary::node_children(uint32_t node) const {
  FLATSLAM_CHECK(impl_ && node < impl_->tree.node_count, "Vocabulary::node_children: slot ", node, " out of range");
  return impl_->tree.child_count[node];
}

WordId Vocabulary::Transform(const Descriptor& descriptor) const {
  assert(impl_ != nullptr);
  WordId word;
  DescendBatch<1>(impl_->tree, &descriptor, 0, &word, nullptr);
  return word;
}

WordId Vocabulary::Transform(const Descriptor& descriptor, int node_depth, uint32_t* node_at_depth) const {
  assert(impl_ != nullptr);
  WordId word;
  DescendBatch<1>(impl_->tree, &descriptor, node_depth, &word, node_at_depth);
  return word;
}

void Vocabulary::Transform(std::span<const Descriptor> descriptors, BowVector* bow, FeatureVector* features,
                           int node_depth) const {
  FLATSLAM_CHECK(impl_ != nullptr, "Vocabulary::Transform: empty vocabulary");
  FLATSLAM_CHECK(bow != nullptr, "Vocabulary::Transform: no output vector");
  const size_t n = descriptors.size();
  std::vector<WordId> words(n);
  std::vector<uint32_t> nodes(features != nullptr ? n : 0);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 128), [&](const tbb::blocked_range<size_t>& r) {
    // Eight descents in lockstep, so their memory latencies overlap.
    size_t k = r.begin();
    for (; k + kFrameLanes <= r.end(); k += kFrameLanes) {
      DescendBatch<kFrameLanes>(impl_->tree, &descriptors[k], node_depth, &words[k],
                                features != nullptr ? &nodes[k] : nullptr);
    }
    for (; k < r.end(); ++k) {
      DescendBatch<1>(impl_->tree, &descriptors[k], node_depth, &words[k], features != nullptr ? &nodes[k] : nullptr);
    }
  });

  // TF-IDF: each occurrence adds the word's IDF; the 1/n of the term frequency cancels in the
  // L1 normalization.
  bow->clear();
  std::sort(words.begin(), words.end());
  double total = 0;
  for (size_t k = 0; k < n;) {
    size_t end = k + 1;
    while (end < n && words[end] == words[k]) ++end;
    const double value = static_cast<double>(impl_->tree.weight[words[k]]) * static_cast<double>(end - k);
    bow->emplace_back(words[k], static_cast<float>(value));
    total += value;
    k = end;
  }
  if (total > 0) {
    for (auto& entry : *bow) entry.second = static_cast<float>(entry.second / total);
  }

  if (features != nullptr) {
    features->resize(n);
    for (size_t k = 0; k < n; ++k) (*features)[k] = {nodes[k], static_cast<uint32_t>(k)};
    std::sort(features->begin(), features->end());
  }
}

float Vocabulary::Score(const BowVector& a, const BowVector& b) {
  // For L1-normalized vectors 1 - 0.5 |a - b|_1 equals the sum over shared words of min(a_i, b_i)
  // (|a_i| + |b_i| - |a_i - b_i| = 2 min(a_i, b_i)); vectors with no shared word score 0.
  double score = 0;
  auto i = a.begin();
  auto j = b.begin();
  while (i != a.end() && j != b.end()) {
    if (i->first < j->first) {
      ++i;
    } else if (j->first < i->first) {
      ++j;
    } else {
      score += std::min(i->second, j->second);
      ++i;
      ++j;
    }
  }
  return static_cast<float>(std::clamp(score, 0.0, 1.0));
}

std::filesystem::path DefaultVocabularyPath() {
  if (const char* env = std::getenv("FLATSLAM_VOCABULARY"); env != nullptr && *env != '\0') return env;
  return FLATSLAM_DEFAULT_VOCABULARY;
}

}  // namespace flatslam
