// flatslam vocab: train a bag-of-words vocabulary from images; describe a vocabulary file.
#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <vector>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "io/dataset.h"
#include "io/image_io.h"
#include "frontend/orb_extractor.h"
#include "place/vocabulary.h"

namespace flatslam::app {

const char* const kVocabUsage =
    "usage: flatslam vocab train --images SRC [SRC...] --out FILE [--branching 10] [--levels 6]\n"
    "                            [--features N] [--every N] [--max-descriptors N] [--iterations N]\n"
    "                            [--seed N]\n"
    "       flatslam vocab info FILE\n\n"
    "train  extracts ORB descriptors with flatslam's extractor from every N-th image of each source,\n"
    "       clusters them into a vocabulary tree (hierarchical k-majority with k-means++ seeds),\n"
    "       weights the words by IDF over the images and writes FILE atomically.\n"
    "  --images SRC...      image sources, one or more: a dataset folder (KITTI sequence, EuRoC or\n"
    "                       TUM RGB-D; the left/RGB images), synth:NAME[:key=value,...] (see\n"
    "                       flatslam synth --help) or a folder of .png/.jpg images\n"
    "  --out FILE           vocabulary file to write (.fsvc)\n"
    "  --branching B        children per node (default 10)\n"
    "  --levels L           depth of the tree (default 6); at most B^L words\n"
    "  --features N         ORB keypoints per image (default 1000)\n"
    "  --every N            use every N-th image of each source (default 1)\n"
    "  --max-descriptors N  cluster a random subset of at most N descriptors (default 0: all)\n"
    "  --iterations N       k-majority iterations per cluster (default 10)\n"
    "  --seed N             seed of the clustering and the subset (default 1)\n"
    "info   loads FILE (verifying it) and prints its shape, word count, weights, checksum and size.\n";

namespace {

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

// A list of gray images: a dataset's left/RGB frames or the image files of a folder.
struct ImageSource {
  std::string name;
  size_t size = 0;
  std::function<cv::Mat(size_t)> read;
};

bool IsImageFile(const std::filesystem::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext == ".png" || ext == ".jpg" || ext == ".jpeg";
}

ImageSource OpenImageSource(const std::string& spec) {
  std::error_code ec;
  if (spec.rfind("synth:", 0) != 0 && std::filesystem::is_directory(spec, ec)) {
    std::vector<std::filesystem::path> files;
    for (const auto& entry : std::filesystem::directory_iterator(spec)) {
      if (entry.is_regular_file() && IsImageFile(entry.path())) files.push_back(entry.path());
    }
    if (!files.empty()) {
      std::sort(files.begin(), files.end());
      auto shared = std::make_shared<std::vector<std::filesystem::path>>(std::move(files));
      return {"image folder " + spec, shared->size(), [shared](size_t i) { return ReadGrayImage((*shared)[i]); }};
    }
  }
  DatasetOptions options;
  options.sensor = Sensor::kMonocular;  // only the left/RGB images are used
  std::shared_ptr<Dataset> dataset = OpenDataset(spec, options);
  return {dataset->name(), dataset->size(), [dataset](size_t i) { return dataset->read(i).left; }};
}

// Draws `keep` of `n` indices without replacement (own generator: the same subset everywhere), sorted.
std::vector<size_t> Subset(size_t n, size_t keep, uint64_t seed) {
  std::vector<size_t> index(n);
  for (size_t i = 0; i < n; ++i) index[i] = i;
  std::mt19937_64 rng(seed ^ 0x5ab5e7ull);
  for (size_t i = 0; i < keep; ++i) {
    const size_t j = i + static_cast<size_t>((static_cast<unsigned __int128>(rng()) * (n - i)) >> 64);
    std::swap(index[i], index[j]);
  }
  index.resize(keep);
  std::sort(index.begin(), index.end());
  return index;
}

int Train(const Args& args) {
  std::vector<std::string> specs;
  if (auto first = args.get("images")) specs.push_back(*first);
  specs.insert(specs.end(), args.positional().begin() + 1, args.positional().end());
  if (specs.empty()) throw UsageError{"train needs --images SRC [SRC...]"};
  if (!args.has("out")) throw UsageError{"train needs --out FILE"};
  const std::filesystem::path out = *args.get("out");
  const int64_t every = args.get_int("every", 1);
  const int64_t features = args.get_int("features", 1000);
  const int64_t max_descriptors = args.get_int("max-descriptors", 0);
  if (every < 1) throw UsageError{"--every must be at least 1"};
  if (features < 1) throw UsageError{"--features must be at least 1"};
  if (max_descriptors < 0) throw UsageError{"--max-descriptors must not be negative"};
  VocabularyTrainOptions options;
  options.branching = static_cast<int>(args.get_int("branching", 10));
  options.levels = static_cast<int>(args.get_int("levels", 6));
  options.max_iterations = static_cast<int>(args.get_int("iterations", 10));
  options.seed = static_cast<uint64_t>(args.get_int("seed", 1));
  if (!options.Check()) {
    throw UsageError{
        "--branching must be in [2, 64], --levels in [1, 16], --iterations >= 0, and the tree at most "
        "50 million nodes"};
  }

  // Which images: every N-th frame of each source.
  std::vector<ImageSource> sources;
  struct Item {
    size_t source, frame;
  };
  std::vector<Item> items;
  for (const std::string& spec : specs) {
    sources.push_back(OpenImageSource(spec));
    const ImageSource& s = sources.back();
    size_t used = 0;
    for (size_t i = 0; i < s.size; i += static_cast<size_t>(every), ++used) items.push_back({sources.size() - 1, i});
    std::printf("source     %s: %zu images, using %zu\n", s.name.c_str(), s.size, used);
  }
  if (items.empty()) throw Error("the image sources hold no images");

  OrbOptions orb_options;
  orb_options.features = static_cast<int>(features);
  const OrbExtractor orb(orb_options);
  std::vector<std::vector<Descriptor>> per_image(items.size());
  std::atomic<size_t> done{0};
  std::mutex print_mutex;
  auto start = std::chrono::steady_clock::now();
  tbb::parallel_for(size_t{0}, items.size(), [&](size_t k) {
    const cv::Mat gray = sources[items[k].source].read(items[k].frame);
    Keypoints keypoints;
    orb.Extract(gray, &keypoints);
    per_image[k] = std::move(keypoints.descriptor);
    const size_t n = ++done;
    if (n % 20 == 0 || n == items.size()) {
      std::lock_guard<std::mutex> lock(print_mutex);
      std::fprintf(stderr, "\rextracting %zu / %zu images", n, items.size());
    }
  });
  std::fprintf(stderr, "\n");

  // Flatten; images without descriptors do not count towards the IDF's N.
  size_t total = 0;
  for (const auto& d : per_image) total += d.size();
  std::vector<size_t> keep;
  if (max_descriptors > 0 && total > static_cast<size_t>(max_descriptors)) {
    keep = Subset(total, static_cast<size_t>(max_descriptors), options.seed);
  }
  std::vector<Descriptor> descriptors;
  std::vector<uint32_t> image_of;
  descriptors.reserve(keep.empty() ? total : keep.size());
  image_of.reserve(descriptors.capacity());
  {
    size_t flat = 0, next_keep = 0;
    uint32_t images = 0;
    for (const auto& d : per_image) {
      bool any = false;
      for (const Descriptor& x : d) {
        if (keep.empty() || (next_keep < keep.size() && keep[next_keep] == flat)) {
          descriptors.push_back(x);
          image_of.push_back(images);
          any = true;
          if (!keep.empty()) ++next_keep;
        }
        ++flat;
      }
      images += any;
    }
    std::vector<std::vector<Descriptor>>().swap(per_image);
    std::printf("extracted  %zu descriptors from %zu images in %.1f s; clustering %zu from %u images\n", total,
                items.size(), Seconds(start), descriptors.size(), images);
    start = std::chrono::steady_clock::now();
    int last_percent = -1;
    options.progress = [&](size_t settled, size_t all) {
      const int percent = static_cast<int>(100 * settled / std::max<size_t>(all, 1));
      if (percent != last_percent) {
        last_percent = percent;
        std::fprintf(stderr, "\rclustering %3d%% of descriptors placed in words", percent);
      }
    };
    const Vocabulary vocabulary = Vocabulary::Train(descriptors, image_of, images, options);
    std::fprintf(stderr, "\n");
    const double train_s = Seconds(start);
    vocabulary.Save(out);
    std::printf("trained    %zu words (branching %d, levels %d, %zu node slots) in %.1f s\n", vocabulary.word_count(),
                vocabulary.branching(), vocabulary.levels(), vocabulary.node_count(), train_s);
    std::printf("wrote      %s (%.2f MiB, checksum %016llx)\n", out.c_str(), vocabulary.byte_size() / 1048576.0,
                static_cast<unsigned long long>(vocabulary.checksum()));
  }
  return 0;
}

int Info(const Args& args) {
  if (args.positional().size() != 2) throw UsageError{"info needs exactly one FILE"};
  const std::filesystem::path path = args.positional()[1];
  const auto start = std::chrono::steady_clock::now();
  const Vocabulary vocabulary = Vocabulary::Load(path);
  const double load_ms = 1e3 * Seconds(start);

  size_t inner = 0, present = 0;
  std::vector<size_t> leaves_at(vocabulary.levels() + 1, 0);
  for (uint32_t node = 0, depth = 0, depth_end = 1; node < vocabulary.node_count(); ++node) {
    if (node == depth_end) {
      ++depth;
      depth_end = depth_end * vocabulary.branching() + 1;
    }
    const WordId w = vocabulary.node_word(node);
    if (w == Vocabulary::kEmptyNode) continue;
    ++present;
    if (w == Vocabulary::kInnerNode) {
      ++inner;
    } else {
      ++leaves_at[depth];
    }
  }
  std::vector<float> weights(vocabulary.word_count());
  for (WordId w = 0; w < weights.size(); ++w) weights[w] = vocabulary.weight(w);
  std::sort(weights.begin(), weights.end());

  std::printf("file       %s (%.2f MiB, %zu bytes)\n", path.c_str(), vocabulary.byte_size() / 1048576.0,
              vocabulary.byte_size());
  std::printf("tree       branching %d, levels %d, %zu node slots (%zu present: %zu inner, %zu words)\n",
              vocabulary.branching(), vocabulary.levels(), vocabulary.node_count(), present, inner,
              vocabulary.word_count());
  std::printf("words      %zu; by depth:", vocabulary.word_count());
  for (size_t d = 1; d < leaves_at.size(); ++d) std::printf(" %zu", leaves_at[d]);
  std::printf("\n");
  std::printf("weights    IDF min %.3f, median %.3f, max %.3f\n", weights.front(), weights[weights.size() / 2],
              weights.back());
  if (vocabulary.training_images() > 0) {
    std::printf("trained on %llu descriptors from %llu images\n",
                static_cast<unsigned long long>(vocabulary.training_descriptors()),
                static_cast<unsigned long long>(vocabulary.training_images()));
  }
  std::printf("checksum   %016llx\n", static_cast<unsigned long long>(vocabulary.checksum()));
  std::printf("loaded in  %.2f ms (mmap, verified)\n", load_ms);
  return 0;
}

}  // namespace

int RunVocab(const std::vector<std::string>& argv) {
  const Args args(
      argv, {"images", "out", "branching", "levels", "features", "every", "max-descriptors", "iterations", "seed"}, {});
  if (args.help()) {
    std::fputs(kVocabUsage, stdout);
    return 0;
  }
  if (args.positional().empty()) throw UsageError{"expected 'train' or 'info'"};
  const std::string& action = args.positional()[0];
  if (action == "train") return Train(args);
  if (action == "info") {
    if (args.has("images") || args.has("out")) throw UsageError{"info takes only FILE"};
    return Info(args);
  }
  throw UsageError{"unknown vocab action '" + action + "': expected 'train' or 'info'"};
}

}  // namespace flatslam::app
