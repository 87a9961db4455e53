#include "storage/snapshot.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <condition_variable>
#include <cstring>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <new>
#include <random>
#include <thread>
#include <utility>

#include <flatbuffers/flatbuffers.h>

#include "core/error.h"
#include "flatslam/schemas/map_generated.h"
#include "storage/schema_records.h"

namespace flatslam {
namespace {

namespace fb = flatbuffers;

// Columns are copied between arenas and files as raw bytes: the layouts must agree.
static_assert(std::endian::native == std::endian::little, "snapshots are read in place: little-endian only");
static_assert(sizeof(schema::ObservationRecord) == 8);
static_assert(sizeof(schema::CovisibilityEdge) == 8);

constexpr size_t kMaxBufferSize = (size_t{1} << 31) - 1;  // flatbuffers uses 32-bit offsets

using records::FromDescriptor;
using records::FromPose;
using records::FromVec;
using records::Size;
using records::Span;
using records::ToPose;

schema::CompactPose ToSchema(const CompactPose& pose) {
  return schema::CompactPose(fb::span<const float, 4>(pose.q), fb::span<const float, 3>(pose.t));
}

CompactPose FromSchema(const schema::CompactPose& pose) {
  CompactPose out;
  for (int k = 0; k < 4; ++k) out.q[k] = pose.q()->Get(k);
  for (int k = 0; k < 3; ++k) out.t[k] = pose.t()->Get(k);
  // A zero quaternion (a crafted record) reads as the identity rather than NaN.
  if (out.q[0] == 0 && out.q[1] == 0 && out.q[2] == 0 && out.q[3] == 0) out.q[3] = 1;
  return out;
}

// Upper bound of the serialized size, to size the builder once and to refuse >2 GiB early. It
// counts only what is written (edges to live keyframes), so a map and its reload estimate alike:
// the estimate sets the file's layout (see SnapshotImage).
size_t EstimateSize(std::span<const SnapshotMapRef> maps, const SnapshotMetadata& metadata) {
  size_t bytes = 4096;
  if (const auto& session = metadata.session) {
    bytes += 256 + session->dataset.size() + session->frames.size() * sizeof(schema::FramePoseRecord);
    for (const std::string& a : session->arguments) bytes += 16 + a.size();
  }
  for (const SnapshotMapRef& ref : maps) {
    const auto& keyframes = ref.map->keyframes();
    bytes += 256;
    for (const KeyFrame& kf : keyframes.values()) {
      // The record table and its vtable, then ten vectors, each with a length and alignment padding.
      bytes += 512 + 10 * 12 + kf.size() * (8 + 4 + 4 + 4 + 1 + 32 + 4);
      for (KeyFrameHandle c : kf.children) bytes += keyframes.contains(c) ? 4 : 0;
      for (KeyFrameHandle l : kf.loop_edges) bytes += keyframes.contains(l) ? 4 : 0;
      for (const auto& edge : kf.covisible) bytes += keyframes.contains(edge.first) ? 8 : 0;
    }
    for (const MapPoint& p : ref.map->points().values()) {
      bytes += sizeof(schema::PointRecord) + 4;
      for (const Observation& o : p.observations) bytes += keyframes.contains(o.keyframe) ? 8 : 0;
    }
  }
  return bytes;
}

// Called with the builder's size whenever everything written so far is final (between records).
using BuildProgress = std::function<void(size_t)>;

fb::Offset<schema::MapSegment> BuildSegment(fb::FlatBufferBuilder& builder, const SnapshotMapRef& ref,
                                            const BuildProgress& progress) {
  const Map& map = *ref.map;
  const auto& keyframes = map.keyframes();
  const auto& points = map.points();
  auto kf_index = [&](KeyFrameHandle h) -> uint32_t {
    return keyframes.contains(h) ? static_cast<uint32_t>(keyframes.dense_index(h)) : kNoIndex;
  };

  std::vector<uint32_t> agents;
  std::vector<fb::Offset<schema::KeyFrameRecord>> kf_offsets;
  kf_offsets.reserve(keyframes.size());
  auto point_index = [&](PointHandle p) -> uint32_t {
    return points.contains(p) ? static_cast<uint32_t>(points.dense_index(p)) : kNoIndex;
  };
  for (const KeyFrame& kf : keyframes.values()) {
    const size_t n = kf.size();
    FLATSLAM_CHECK(kf.right_u.size() == n && kf.depth.size() == n && kf.angle.size() == n && kf.octave.size() == n &&
                       kf.descriptor.size() == n && kf.points.size() == n,
                   "map snapshot: keyframe ", kf.id, " of map ", ref.id, " has keypoint columns of different sizes");
    agents.push_back(kf.agent);
    kf_offsets.push_back(records::BuildKeyFrameRecord(builder, kf, point_index, kf_index, /*graph=*/true));
    if (progress) progress(builder.GetSize());
  }
  const auto keyframe_vector = builder.CreateVector(kf_offsets);

  // Observations first (flat), then the offsets and records that index into them.
  const auto point_values = points.values();
  std::vector<uint32_t> offsets;
  offsets.reserve(point_values.size() + 1);
  offsets.push_back(0);
  size_t total = 0;
  for (const MapPoint& p : point_values) {
    for (const Observation& o : p.observations) total += keyframes.contains(o.keyframe);
    FLATSLAM_CHECK(total < kNoIndex, "map snapshot: map ", ref.id, " has too many observations");
    offsets.push_back(static_cast<uint32_t>(total));
  }
  std::vector<schema::ObservationRecord> observations;
  observations.reserve(total);
  for (const MapPoint& p : point_values)
    for (const Observation& o : p.observations)
      if (keyframes.contains(o.keyframe)) observations.emplace_back(kf_index(o.keyframe), o.keypoint);
  const auto observation_vector = builder.CreateVectorOfStructs(observations);
  const auto offset_vector = builder.CreateVector(offsets);
  if (progress) progress(builder.GetSize());

  std::vector<schema::PointRecord> records;
  records.reserve(point_values.size());
  for (const MapPoint& p : point_values) {
    records.push_back(records::ToPointRecord(p, kf_index(p.reference)));
  }
  const auto point_vector = builder.CreateVectorOfStructs(records);
  if (progress) progress(builder.GetSize());

  std::sort(agents.begin(), agents.end());
  agents.erase(std::unique(agents.begin(), agents.end()), agents.end());
  const auto agent_vector = builder.CreateVector(agents);
  return schema::CreateMapSegment(builder, ref.id, agent_vector, keyframe_vector, point_vector, offset_vector,
                                  observation_vector);
}

// Offset of the content hash's 8 bytes within a verified buffer.
size_t HashOffset(const schema::MapSnapshot* root, const uint8_t* base) {
  const schema::ContentHash* hash = root->content_hash();
  return hash ? static_cast<size_t>(reinterpret_cast<const uint8_t*>(hash) - base) : 0;
}

std::string ErrnoText() {
  return std::strerror(errno);
}

// Closes a file descriptor on scope exit.
struct FdCloser {
  int fd = -1;
  ~FdCloser() {
    if (fd >= 0) ::close(fd);
  }
};

}  // namespace

uint64_t SnapshotHash(std::span<const uint8_t> bytes, size_t skip_offset, size_t skip_size) {
  constexpr uint64_t kP1 = 0x9e3779b185ebca87ull, kP2 = 0xc2b2ae3d27d4eb4full, kP3 = 0x165667b19e3779f9ull;
  constexpr uint64_t kP4 = 0x85ebca77c2b2ae63ull, kP5 = 0x27d4eb2f165667c5ull;
  const size_t skip_end = skip_offset + skip_size;
  const uint8_t* data = bytes.data();
  const size_t n = bytes.size();
  uint64_t lanes[4] = {kP1 + kP2, kP2, 0, 0 - kP1};
  auto blocks = [&lanes](const uint8_t* block, size_t count) {
    uint64_t l0 = lanes[0], l1 = lanes[1], l2 = lanes[2], l3 = lanes[3];
    for (size_t b = 0; b < count; ++b, block += 32) {
      uint64_t w[4];
      std::memcpy(w, block, 32);
      l0 = std::rotl(l0 + w[0] * kP2, 31) * kP1;
      l1 = std::rotl(l1 + w[1] * kP2, 31) * kP1;
      l2 = std::rotl(l2 + w[2] * kP2, 31) * kP1;
      l3 = std::rotl(l3 + w[3] * kP2, 31) * kP1;
    }
    lanes[0] = l0, lanes[1] = l1, lanes[2] = l2, lanes[3] = l3;
  };
  // Whole blocks before the skipped bytes, the blocks they touch (masked), then the rest.
  const size_t whole = n / 32;
  const size_t first_masked = skip_size > 0 ? std::min(skip_offset / 32, whole) : whole;
  const size_t end_masked = skip_size > 0 ? std::min((skip_end + 31) / 32, whole) : whole;
  blocks(data, first_masked);
  for (size_t b = first_masked; b < end_masked; ++b) {
    uint8_t masked[32];
    std::memcpy(masked, data + 32 * b, 32);
    for (size_t i = std::max(32 * b, skip_offset); i < std::min(32 * b + 32, skip_end); ++i) masked[i - 32 * b] = 0;
    blocks(masked, 1);
  }
  blocks(data + 32 * end_masked, whole - end_masked);
  size_t pos = 32 * whole;
  uint64_t h = std::rotl(lanes[0], 1) + std::rotl(lanes[1], 7) + std::rotl(lanes[2], 12) + std::rotl(lanes[3], 18);
  for (; pos < n; ++pos) {
    const uint64_t byte = (pos >= skip_offset && pos < skip_end) ? 0 : data[pos];
    h = std::rotl(h ^ (byte * kP5), 11) * kP1;
  }
  h ^= n * kP4;
  h ^= h >> 33;
  h *= kP2;
  h ^= h >> 29;
  h *= kP3;
  h ^= h >> 32;
  return h;
}

namespace {

// Thrown by BuilderAllocator when the builder would outgrow its reservation (the size estimate
// fell short); the snapshot is then built again with more room.
struct GrowthRefused {};

// The builder's memory: one block of `reserved` bytes mapped up front (so its address is known
// before building starts) and never grown. Straight from mmap, so it goes back to the system when
// the save ends. Transparent huge pages are not asked for: they made repeated saves in one
// process faster, but the first save of a process (the usual case: `run --save-map`) waited on
// compaction, 0.5-1.0 s against 0.27-0.6 s without them for a 180 MB map on the development VM.
class BuilderAllocator : public fb::Allocator {
 public:
  explicit BuilderAllocator(size_t reserved) : reserved_(reserved) {
    void* p = ::mmap(nullptr, reserved_, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) throw std::bad_alloc();
    base_ = static_cast<uint8_t*>(p);
  }
  ~BuilderAllocator() override { ::munmap(base_, reserved_); }
  BuilderAllocator(const BuilderAllocator&) = delete;
  BuilderAllocator& operator=(const BuilderAllocator&) = delete;

  uint8_t* allocate(size_t size) override {
    if (size > reserved_) throw GrowthRefused{};
    return base_;
  }
  void deallocate(uint8_t*, size_t) override {}
  uint8_t* reallocate_downward(uint8_t*, size_t, size_t, size_t, size_t) override { throw GrowthRefused{}; }

  [[nodiscard]] uint8_t* base() const { return base_; }
  [[nodiscard]] size_t reserved() const { return reserved_; }

 private:
  size_t reserved_;
  uint8_t* base_ = nullptr;
};

// A builder whose buffer holds the maps' estimated size times 2^attempt, plus a page (rounded up).
struct SizedBuilder {
  SizedBuilder(std::span<const SnapshotMapRef> maps, const SnapshotMetadata& metadata, int attempt)
      : allocator(Reserve(maps, metadata, attempt)), builder(allocator.reserved(), &allocator) {}
  static size_t Reserve(std::span<const SnapshotMapRef> maps, const SnapshotMetadata& metadata, int attempt) {
    for (const SnapshotMapRef& ref : maps) FLATSLAM_CHECK(ref.map != nullptr, "map snapshot: map ", ref.id, " is null");
    const size_t estimate = EstimateSize(maps, metadata);
    FLATSLAM_CHECK(estimate < kMaxBufferSize, "map snapshot: about ", estimate >> 20,
                   " MiB exceeds the 2 GiB limit of one snapshot buffer");
    constexpr size_t kPage = 4096;
    const size_t reserved = ((estimate << attempt) + 2 * kPage - 1) / kPage * kPage;
    FLATSLAM_CHECK(reserved < kMaxBufferSize, "map snapshot: the maps outgrew their size estimate (", estimate >> 20,
                   " MiB) past the 2 GiB limit of one snapshot buffer");
    return reserved;
  }
  BuilderAllocator allocator;
  fb::FlatBufferBuilder builder;
};

// Builds the whole snapshot in builder, all but the content hash; progress (if set) hears of
// the builder's size whenever everything written so far is final.
void BuildSnapshot(fb::FlatBufferBuilder& builder, std::span<const SnapshotMapRef> maps,
                   const SnapshotMetadata& metadata, const BuildProgress& progress) {
  std::vector<fb::Offset<schema::MapSegment>> segments;
  for (const SnapshotMapRef& ref : maps) segments.push_back(BuildSegment(builder, ref, progress));
  const auto segment_vector = builder.CreateVector(segments);

  const auto calibration = records::BuildCalibration(builder, metadata.calibration);
  const auto scales = schema::CreateScalePyramid(builder, metadata.scales.scale_factor, metadata.scales.levels);
  fb::Offset<schema::Session> session;
  if (const auto& s = metadata.session) {
    FLATSLAM_CHECK(s->map < maps.size(), "map snapshot: the session's map ", s->map, " is not among the ", maps.size(),
                   " maps saved");
    const auto& keyframes = maps[s->map].map->keyframes();
    std::vector<schema::FramePoseRecord> frames;
    frames.reserve(s->frames.size());
    for (const AnchoredFramePose& f : s->frames) {
      const uint32_t reference =
          keyframes.contains(f.reference) ? static_cast<uint32_t>(keyframes.dense_index(f.reference)) : kNoIndex;
      frames.emplace_back(f.t_ns, reference, ToSchema(f.T_cam_ref), ToSchema(f.T_cam_world));
    }
    const auto frame_vector = builder.CreateVectorOfStructs(frames);
    const auto arguments = builder.CreateVectorOfStrings(s->arguments);
    const auto dataset = builder.CreateString(s->dataset);
    session = schema::CreateSession(builder, s->next_frame, s->map, dataset, arguments, frame_vector,
                                    s->global_adjustment_pending);
  }
  const schema::ContentHash placeholder(0);
  const auto root =
      schema::CreateMapSnapshot(builder, kMapSnapshotFormatVersion, &placeholder, metadata.vocabulary_checksum,
                                calibration, scales, segment_vector, session, metadata.rgbd_virtual_baseline_m,
                                metadata.camera_refit.focal_scale, metadata.camera_refit.k1,
                                metadata.given_camera.fx, metadata.given_camera.fy, metadata.given_camera.cx,
                                metadata.given_camera.cy);
  schema::FinishMapSnapshotBuffer(builder, root);
}

// A snapshot file's bytes. The builder fills its buffer from the end, so the flatbuffer takes the
// last size bytes of the reserved block; the file keeps that layout: the root offset and file
// identifier, zeros (the estimate's slack), then the flatbuffer. Every byte sits at the same
// offset in memory as in the file, so finished parts are written while the rest is built.
// Offsets inside a flatbuffer are relative: only the leading root offset changes.
struct SnapshotImage {
  std::span<uint8_t> bytes;
  size_t hash_offset = 0;  // of the content hash slot (zero until stamped)
};

SnapshotImage LayOut(const SizedBuilder& sized) {
  uint8_t* base = sized.allocator.base();
  const size_t reserved = sized.allocator.reserved();
  const size_t start = reserved - sized.builder.GetSize();
  FLATSLAM_CHECK(sized.builder.GetBufferPointer() == base + start && start >= 8, "map snapshot: unexpected layout");
  const size_t hash_offset = start + HashOffset(schema::GetMapSnapshot(base + start), base + start);
  const fb::uoffset_t root = static_cast<fb::uoffset_t>(start) + fb::ReadScalar<fb::uoffset_t>(base + start);
  char identifier[fb::kFileIdentifierLength];
  std::memcpy(identifier, base + start + sizeof(fb::uoffset_t), sizeof(identifier));
  std::memset(base, 0, start);  // the builder's scratch space and the slack
  fb::WriteScalar(base, root);
  std::memcpy(base + sizeof(fb::uoffset_t), identifier, sizeof(identifier));
  return {{base, reserved}, hash_offset};
}

// Computes the content hash of an image and writes it into its slot.
void StampContentHash(const SnapshotImage& image) {
  const uint64_t hash = SnapshotHash(image.bytes, image.hash_offset, 8);
  std::memcpy(image.bytes.data() + image.hash_offset, &hash, 8);
}

// Writes bytes [begin, end) of base at the same file offsets and hands them to the disk at once;
// false (errno set) on failure. A file opened for direct I/O that refuses a write (alignment)
// falls back to the page cache for the rest of the save.
bool WriteRange(int fd, const uint8_t* base, size_t begin, size_t end) {
  size_t written = begin;
  while (written < end) {
    const ssize_t n = ::pwrite(fd, base + written, end - written, static_cast<off_t>(written));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && errno == EINVAL) {
      const int flags = ::fcntl(fd, F_GETFL);
      if (flags >= 0 && (flags & O_DIRECT) != 0 && ::fcntl(fd, F_SETFL, flags & ~O_DIRECT) == 0) continue;
    }
    if (n <= 0) return false;
    written += static_cast<size_t>(n);
  }
  if (end > begin)
    (void)::sync_file_range(fd, static_cast<off_t>(begin), static_cast<off_t>(end - begin), SYNC_FILE_RANGE_WRITE);
  return true;
}

// Writes the finished tail of an image, [final_from, end), to the file in its own thread while the
// front is still being built: chunks of 8 MiB, last first, each handed to the disk at once, so
// the final fsync waits for little more than the front.
class TailWriter {
 public:
  TailWriter(int fd, const uint8_t* base, size_t end)
      : fd_(fd), base_(base), final_from_(end), written_from_(end), thread_([this] { Run(); }) {}
  ~TailWriter() { Finish(); }
  TailWriter(const TailWriter&) = delete;
  TailWriter& operator=(const TailWriter&) = delete;

  // Everything from offset final_from on is final.
  void Publish(size_t final_from) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      final_from_ = final_from;
    }
    wake_.notify_one();
  }
  // Stops after the chunk in flight. Returns the offset from which everything is written; an
  // errno value in *error if a write failed.
  size_t Finish(int* error = nullptr) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      done_ = true;
    }
    wake_.notify_one();
    if (thread_.joinable()) thread_.join();
    if (error) *error = error_;
    return written_from_;
  }

 private:
  static constexpr size_t kChunk = size_t{8} << 20;
  void Run() {
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      wake_.wait(lock, [this] { return done_ || written_from_ - final_from_ >= kChunk; });
      if (done_) return;
      const size_t from = written_from_ - kChunk;
      lock.unlock();
      const bool ok = WriteRange(fd_, base_, from, written_from_);
      const int error = errno;
      lock.lock();
      if (!ok) {
        error_ = error;
        return;
      }
      written_from_ = from;
    }
  }

  const int fd_;
  const uint8_t* const base_;
  std::mutex mutex_;
  std::condition_variable wake_;
  size_t final_from_;
  size_t written_from_;
  bool done_ = false;
  int error_ = 0;
  std::thread thread_;
};

// A failed write to the snapshot file: what failed and errno.
struct WriteFailed {
  const char* what;
  int error;
};

// Builds and lays out the maps, with more room should the estimate fall short, then calls
// use(image, written_from). With a file descriptor, finished parts are written to it while the
// rest is built; from offset written_from on, the file already holds the image.
template <class Use>
void WithSnapshot(std::span<const SnapshotMapRef> maps, const SnapshotMetadata& metadata, int fd, Use use) {
  for (int attempt = 0;; ++attempt) {
    try {
      SizedBuilder sized(maps, metadata, attempt);
      const size_t reserved = sized.allocator.reserved();
      std::optional<TailWriter> tail;  // declared after sized: stopped before its memory goes
      BuildProgress progress;
      if (fd >= 0) {
        tail.emplace(fd, sized.allocator.base(), reserved);
        progress = [&tail, reserved](size_t built) { tail->Publish(reserved - built); };
      }
      BuildSnapshot(sized.builder, maps, metadata, progress);
      size_t written_from = reserved;
      if (tail) {
        int error = 0;
        written_from = tail->Finish(&error);
        if (error != 0) throw WriteFailed{"write failed", error};
      }
      use(LayOut(sized), written_from);
      return;
    } catch (const GrowthRefused&) {
      FLATSLAM_CHECK(attempt < 3, "map snapshot: the size estimate fell short three times");
      if (fd >= 0 && ::ftruncate(fd, 0) != 0) throw WriteFailed{"truncate failed", errno};
    }
  }
}

}  // namespace

std::vector<uint8_t> SerializeMapSnapshot(std::span<const SnapshotMapRef> maps, const SnapshotMetadata& metadata) {
  std::vector<uint8_t> out;
  WithSnapshot(maps, metadata, -1, [&](const SnapshotImage& image, size_t) {
    StampContentHash(image);
    out.assign(image.bytes.begin(), image.bytes.end());
  });
  return out;
}

void SaveMapSnapshot(const std::filesystem::path& path, std::span<const SnapshotMapRef> maps,
                     const SnapshotMetadata& metadata) {
  const std::filesystem::path dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  std::mt19937_64 rng(std::random_device{}());
  std::string temp_name = ".";
  temp_name += path.filename().string();
  temp_name += ".tmp" + std::to_string(::getpid()) + "_" + std::to_string(rng() % 1000000);
  const std::filesystem::path temp = dir / temp_name;
  FdCloser file{::open(temp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644)};
  FLATSLAM_CHECK(file.fd >= 0, "cannot save map snapshot ", path, ": cannot create ", temp, ": ", ErrnoText());
  // Direct I/O: the disk reads the built bytes straight from the builder's page-aligned memory, at
  // aligned offsets, while the rest is built. Through the page cache, writing 180 MB ran at about
  // 360 MB/s on the development VM on many runs (the tail writer fell behind the build, and a first
  // save took 0.5-0.6 s); direct, the writer keeps up and the first save took 0.22-0.27 s.
  // Filesystems without direct I/O (tmpfs) keep the page cache.
  if (const int flags = ::fcntl(file.fd, F_GETFL); flags >= 0) (void)::fcntl(file.fd, F_SETFL, flags | O_DIRECT);
  auto fail = [&](const std::string& what, int error) {
    ::close(file.fd);
    file.fd = -1;
    ::unlink(temp.c_str());
    Fail("cannot save map snapshot ", path, ": ", what, ": ", std::strerror(error));
  };
  try {
    WithSnapshot(maps, metadata, file.fd, [&](const SnapshotImage& image, size_t written_from) {
      // The front holds the root table and its content hash: it goes last.
      StampContentHash(image);
      if (!WriteRange(file.fd, image.bytes.data(), 0, written_from)) throw WriteFailed{"write failed", errno};
    });
    if (::fsync(file.fd) != 0) throw WriteFailed{"fsync failed", errno};
  } catch (const WriteFailed& e) {
    fail(e.what, e.error);
  } catch (...) {
    // Nothing half-written is left behind (a build error, memory refused).
    ::close(file.fd);
    file.fd = -1;
    ::unlink(temp.c_str());
    throw;
  }
  if (::close(file.fd) != 0) {
    file.fd = -1;
    fail("close failed", errno);
  }
  file.fd = -1;
  // Replacing a map frees the old file's blocks and cached pages in the rename (about 70 ms for
  // 180 MB): in a session that is the checkpoint job's time, not tracking's.
  if (::rename(temp.c_str(), path.c_str()) != 0) {
    const int error = errno;
    ::unlink(temp.c_str());
    Fail("cannot save map snapshot ", path, ": rename failed: ", std::strerror(error));
  }
  // Makes the rename itself durable; failure here leaves a complete file, so it is not an error.
  FdCloser directory{::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC)};
  if (directory.fd >= 0) (void)::fsync(directory.fd);
}

// ---------------------------------------------------------------------------------------------
// Read-only view

MapSnapshotView::MapSnapshotView(MapSnapshotView&& other) noexcept
    : name_(std::move(other.name_)),
      bytes_(std::exchange(other.bytes_, {})),
      file_(std::move(other.file_)),
      root_(std::exchange(other.root_, nullptr)) {}

MapSnapshotView& MapSnapshotView::operator=(MapSnapshotView&& other) noexcept {
  if (this != &other) {
    name_ = std::move(other.name_);
    bytes_ = std::exchange(other.bytes_, {});
    file_ = std::move(other.file_);
    root_ = std::exchange(other.root_, nullptr);
  }
  return *this;
}

MapSnapshotView::~MapSnapshotView() = default;

MapSnapshotView MapSnapshotView::Open(const std::filesystem::path& path, const SnapshotReadOptions& options) {
  MapSnapshotView view;
  view.name_ = path.string();
  view.file_ = MappedFile::Open(path, "map snapshot \"" + view.name_ + "\"", /*min_size=*/8);
  view.bytes_ = view.file_.bytes();
  FLATSLAM_CHECK(view.bytes_.size() < kMaxBufferSize, "map snapshot ", path, ": ", view.bytes_.size(),
                 " bytes exceeds the 2 GiB format limit");
  view.Verify(options);  // on throw, the view's destructor unmaps
  return view;
}

MapSnapshotView MapSnapshotView::FromBytes(std::span<const uint8_t> bytes, const std::string& name,
                                           const SnapshotReadOptions& options) {
  MapSnapshotView view;
  view.name_ = name;
  view.bytes_ = bytes;
  FLATSLAM_CHECK(bytes.size() >= 8, "map snapshot ", name, ": truncated or not a map snapshot (", bytes.size(),
                 " bytes)");
  FLATSLAM_CHECK(bytes.size() < kMaxBufferSize, "map snapshot ", name, ": exceeds the 2 GiB format limit");
  view.Verify(options);
  return view;
}

void MapSnapshotView::Verify(const SnapshotReadOptions& options) {
  const uint8_t* buf = bytes_.data();
  const size_t size = bytes_.size();
  const std::string& file = name_;
  if (!schema::MapSnapshotBufferHasIdentifier(buf)) {
    std::string found;
    for (int i = 4; i < 8; ++i) found += (buf[i] >= 32 && buf[i] < 127) ? static_cast<char>(buf[i]) : '?';
    Fail("map snapshot ", file, ": not a flatslam map snapshot (file identifier '", found, "', expected '",
         schema::MapSnapshotIdentifier(), "')");
  }
  // The version is read on its own first, so a newer file is named as such even where its
  // layout no longer verifies against this schema.
  fb::Verifier version_verifier(buf, size);
  const fb::uoffset_t root_offset = version_verifier.VerifyOffset(0);
  FLATSLAM_CHECK(root_offset != 0, "map snapshot ", file, ": truncated or corrupt (bad root offset)");
  const auto* table = reinterpret_cast<const fb::Table*>(buf + root_offset);
  FLATSLAM_CHECK(table->VerifyTableStart(version_verifier) &&
                     table->VerifyField<uint32_t>(version_verifier, schema::MapSnapshot::VT_FORMAT_VERSION, 4),
                 "map snapshot ", file, ": truncated or corrupt (bad root table)");
  const uint32_t version = table->GetField<uint32_t>(schema::MapSnapshot::VT_FORMAT_VERSION, 0);
  FLATSLAM_CHECK(version <= kMapSnapshotFormatVersion, "map snapshot ", file, ": format version ", version,
                 " is newer than this build reads (version ", kMapSnapshotFormatVersion, "); update flatslam");
  FLATSLAM_CHECK(version >= 1, "map snapshot ", file, ": invalid format version 0");

  fb::Verifier verifier(buf, size);
  FLATSLAM_CHECK(schema::VerifyMapSnapshotBuffer(verifier), "map snapshot ", file,
                 ": truncated or corrupt (flatbuffers verification failed)");
  root_ = schema::GetMapSnapshot(buf);
  const schema::MapSnapshot& root = *root_;
  FLATSLAM_CHECK(root.content_hash() != nullptr, "map snapshot ", file, ": no content hash");
  if (options.verify_content_hash) {
    const size_t offset = HashOffset(root_, buf);
    const uint64_t computed = SnapshotHash(bytes_, offset, 8);
    FLATSLAM_CHECK(computed == root.content_hash()->value(), "map snapshot ", file,
                   ": corrupt (content hash mismatch: some bytes changed after it was written)");
  }
  if (options.vocabulary_checksum && *options.vocabulary_checksum != root.vocabulary_checksum()) {
    Fail("map snapshot ", file, ": built with vocabulary checksum ", root.vocabulary_checksum(),
         ", but the vocabulary in use has checksum ", *options.vocabulary_checksum,
         " (a map only works with the vocabulary it was built with)");
  }
  FLATSLAM_CHECK(root.calibration() != nullptr, "map snapshot ", file, ": missing calibration");
  FLATSLAM_CHECK(root.scales() != nullptr, "map snapshot ", file, ": missing scale pyramid");
  const auto sensor = static_cast<uint8_t>(root.calibration()->sensor());
  FLATSLAM_CHECK(sensor <= static_cast<uint8_t>(schema::Sensor::MAX), "map snapshot ", file, ": unknown sensor ",
                 int{sensor});

  const size_t maps = Size(root.maps());
  for (size_t m = 0; m < maps; ++m) {
    const schema::MapSegment& seg = *root.maps()->Get(static_cast<fb::uoffset_t>(m));
    const size_t nk = Size(seg.keyframes());
    const size_t np = Size(seg.points());
    const size_t no = Size(seg.observations());
    auto bad = [&](auto&&... what) { Fail("map snapshot ", file, ": map ", m, ": ", what...); };
    const uint32_t* agents = Span(seg.agents()).data();
    const size_t agent_count = Size(seg.agents());
    for (size_t a = 1; a < agent_count; ++a)
      if (agents[a - 1] >= agents[a]) bad("agent list not sorted and unique");

    // Point records and observations.
    if (Size(seg.observation_offsets()) != np + 1)
      bad("observation offsets: ", Size(seg.observation_offsets()), " entries for ", np, " points (expected ", np + 1,
          ")");
    const uint32_t* offsets = Span(seg.observation_offsets()).data();
    if (offsets[0] != 0) bad("first observation offset is ", offsets[0], ", not 0");
    for (size_t i = 0; i < np; ++i)
      if (offsets[i + 1] < offsets[i]) bad("observation offsets decrease at point ", i);
    if (offsets[np] != no) bad("observation offsets end at ", offsets[np], " but there are ", no, " observations");
    // The scans below reduce without branches (vectorized) and look for the culprit only on failure.
    // Index i is valid when i < count or i == kNoIndex, i.e. when i + 1 (wrapping) <= count.
    const uint32_t nk32 = static_cast<uint32_t>(nk), np32 = static_cast<uint32_t>(np);
    const schema::PointRecord* points = Span(seg.points()).data();
    uint32_t failed = 0;
    for (size_t i = 0; i < np; ++i) failed |= static_cast<uint32_t>(points[i].reference() + 1u > nk32);
    for (size_t i = 0; failed && i < np; ++i) {
      const uint32_t ref = points[i].reference();
      if (ref != kNoIndex && ref >= nk)
        bad("point ", i, ": reference keyframe index ", ref, " out of range (", nk, " keyframes)");
    }

    // Keyframes: column sizes, indices.
    std::vector<uint32_t> keypoints(nk);
    for (size_t k = 0; k < nk; ++k) {
      const schema::KeyFrameRecord& kf = *seg.keyframes()->Get(static_cast<fb::uoffset_t>(k));
      const size_t n = Size(kf.uv());
      if (Size(kf.right_u()) != n || Size(kf.depth()) != n || Size(kf.angle()) != n || Size(kf.octave()) != n ||
          Size(kf.descriptors()) != n || Size(kf.points()) != n)
        bad("keyframe ", k, ": keypoint columns differ in size");
      keypoints[k] = static_cast<uint32_t>(n);
      if (!std::binary_search(agents, agents + agent_count, kf.agent()))
        bad("keyframe ", k, ": agent ", kf.agent(), " missing from the map's agent list");
      if (kf.parent() != kNoIndex && kf.parent() >= nk)
        bad("keyframe ", k, ": parent index ", kf.parent(), " out of range (", nk, " keyframes)");
      if (kf.parent() == k) bad("keyframe ", k, " is its own parent");
      const uint32_t* point_index = Span(kf.points()).data();
      failed = 0;
      for (size_t j = 0; j < n; ++j) failed |= static_cast<uint32_t>(point_index[j] + 1u > np32);
      for (size_t j = 0; failed && j < n; ++j)
        if (point_index[j] != kNoIndex && point_index[j] >= np)
          bad("keyframe ", k, " keypoint ", j, ": point index ", point_index[j], " out of range (", np, " points)");
      for (uint32_t c : Span(kf.children()))
        if (c >= nk) bad("keyframe ", k, ": child index ", c, " out of range (", nk, " keyframes)");
      for (uint32_t l : Span(kf.loop_edges()))
        if (l >= nk || l == k) bad("keyframe ", k, ": loop edge index ", l, " out of range or to itself");
      for (const schema::CovisibilityEdge& e : Span(kf.covisible()))
        if (e.keyframe() >= nk || e.keyframe() == k)
          bad("keyframe ", k, ": covisible keyframe index ", e.keyframe(), " out of range or itself (", nk,
              " keyframes)");
    }
    const schema::ObservationRecord* observations = Span(seg.observations()).data();
    if (no > 0 && nk == 0) bad("observations without keyframes");
    failed = 0;
    for (size_t o = 0; o < no; ++o) {
      const uint32_t kf = observations[o].keyframe();
      const uint32_t safe = kf < nk32 ? kf : 0;
      failed |=
          static_cast<uint32_t>(kf >= nk32) | static_cast<uint32_t>(observations[o].keypoint() >= keypoints[safe]);
    }
    for (size_t o = 0; failed && o < no; ++o) {
      const uint32_t kf = observations[o].keyframe();
      if (kf >= nk) bad("observation ", o, ": keyframe index ", kf, " out of range (", nk, " keyframes)");
      if (observations[o].keypoint() >= keypoints[kf])
        bad("observation ", o, ": keypoint ", observations[o].keypoint(), " out of range (keyframe ", kf, " has ",
            keypoints[kf], ")");
    }
  }
  if (const schema::Session* session = root.session()) {
    FLATSLAM_CHECK(session->map() < maps, "map snapshot ", file, ": session: map ", session->map(), " of ", maps);
    const size_t nk = Size(root.maps()->Get(session->map())->keyframes());
    const auto frames = Span(session->frames());
    for (size_t f = 0; f < frames.size(); ++f)
      FLATSLAM_CHECK(frames[f].reference() == kNoIndex || frames[f].reference() < nk, "map snapshot ", file,
                     ": session: frame ", f, " refers to keyframe ", frames[f].reference(), " of ", nk);
  }
}

std::optional<SnapshotSession> MapSnapshotView::session_summary() const {
  const schema::Session* s = root_->session();
  if (!s) return std::nullopt;
  SnapshotSession session;
  session.next_frame = s->next_frame();
  session.map = s->map();
  session.global_adjustment_pending = s->global_adjustment_pending();
  if (s->dataset()) session.dataset = s->dataset()->str();
  if (s->arguments())
    for (const fb::String* a : *s->arguments()) session.arguments.push_back(a->str());
  return session;
}

size_t MapSnapshotView::session_frame_count() const {
  return root_->session() ? Size(root_->session()->frames()) : 0;
}

uint32_t MapSnapshotView::format_version() const {
  return root_->format_version();
}
double MapSnapshotView::rgbd_virtual_baseline_m() const {
  return root_->rgbd_virtual_baseline_m();
}
CameraRefit MapSnapshotView::camera_refit() const {
  return CameraRefit{root_->camera_refit_focal_scale(), root_->camera_refit_k1()};
}
PinholeCamera MapSnapshotView::given_camera() const {
  PinholeCamera camera;
  if (root_->camera_given_fx() <= 0) return camera;
  const PinholeCamera made_with = calibration().camera;
  camera.fx = root_->camera_given_fx();
  camera.fy = root_->camera_given_fy();
  camera.cx = root_->camera_given_cx();
  camera.cy = root_->camera_given_cy();
  camera.width = made_with.width;
  camera.height = made_with.height;
  return camera;
}
uint64_t MapSnapshotView::vocabulary_checksum() const {
  return root_->vocabulary_checksum();
}
uint64_t MapSnapshotView::content_hash() const {
  return root_->content_hash()->value();
}

Calibration MapSnapshotView::calibration() const {
  return records::CalibrationFromRecord(*root_->calibration());
}

MapScales MapSnapshotView::scales() const {
  return MapScales{root_->scales()->scale_factor(), root_->scales()->levels()};
}

size_t MapSnapshotView::map_count() const {
  return Size(root_->maps());
}

const schema::MapSegment& MapSnapshotView::segment(size_t m) const {
  FLATSLAM_CHECK(m < map_count(), "map snapshot ", name_, ": no map ", m);
  return *root_->maps()->Get(static_cast<fb::uoffset_t>(m));
}

uint32_t MapSnapshotView::map_id(size_t m) const {
  return segment(m).id();
}
std::span<const uint32_t> MapSnapshotView::agents(size_t m) const {
  const auto* a = segment(m).agents();
  return a ? std::span<const uint32_t>(a->data(), a->size()) : std::span<const uint32_t>();
}
size_t MapSnapshotView::keyframe_count(size_t m) const {
  return Size(segment(m).keyframes());
}
size_t MapSnapshotView::point_count(size_t m) const {
  return Size(segment(m).points());
}
size_t MapSnapshotView::observation_count(size_t m) const {
  return Size(segment(m).observations());
}

size_t MapSnapshotView::keypoint_count(size_t m) const {
  size_t total = 0;
  if (const auto* kfs = segment(m).keyframes())
    for (const schema::KeyFrameRecord* kf : *kfs) total += Size(kf->uv());
  return total;
}

Eigen::Vector3d MapSnapshotView::point_position(size_t m, size_t i) const {
  const auto* points = segment(m).points();
  FLATSLAM_CHECK(i < Size(points), "map snapshot ", name_, ": map ", m, " has no point ", i);
  return FromVec(points->Get(static_cast<fb::uoffset_t>(i))->position());
}

BoundingBox MapSnapshotView::bounds(size_t m) const {
  BoundingBox box;
  const auto* points = segment(m).points();
  for (const schema::PointRecord& record : Span(points)) {
    const Eigen::Vector3d p = FromVec(record.position());
    if (box.empty) {
      box.min = box.max = p;
      box.empty = false;
    } else {
      box.min = box.min.cwiseMin(p);
      box.max = box.max.cwiseMax(p);
    }
  }
  return box;
}

Trajectory MapSnapshotView::KeyFrameTrajectory(size_t m, std::optional<uint32_t> agent) const {
  Trajectory out;
  if (const auto* kfs = segment(m).keyframes()) {
    out.reserve(kfs->size());
    for (const schema::KeyFrameRecord* kf : *kfs)
      if (!agent || kf->agent() == *agent) out.push_back({kf->t_ns(), FromPose(kf->cam_from_world()).inverse()});
  }
  std::stable_sort(out.begin(), out.end(), [](const TimedPose& a, const TimedPose& b) { return a.t_ns < b.t_ns; });
  return out;
}

// ---------------------------------------------------------------------------------------------
// Bulk load

LoadedSnapshot LoadMapSnapshot(const MapSnapshotView& view) {
  LoadedSnapshot out;
  out.format_version = view.format_version();
  out.metadata.calibration = view.calibration();
  out.metadata.scales = view.scales();
  out.metadata.vocabulary_checksum = view.vocabulary_checksum();
  out.metadata.rgbd_virtual_baseline_m = view.rgbd_virtual_baseline_m();
  out.metadata.camera_refit = view.camera_refit();
  out.metadata.given_camera = view.given_camera();
  out.maps.resize(view.map_count());
  std::vector<std::vector<KeyFrameHandle>> kf_handles_of(view.map_count());
  for (size_t m = 0; m < view.map_count(); ++m) {
    const schema::MapSegment& seg = view.segment(m);
    LoadedMap& loaded = out.maps[m];
    loaded.id = seg.id();
    const auto agents = view.agents(m);
    loaded.agents.assign(agents.begin(), agents.end());
    Map& map = loaded.map;
    const size_t nk = Size(seg.keyframes());
    const size_t np = Size(seg.points());
    map.keyframes().reserve(nk);
    map.points().reserve(np);

    // Keyframes and points first (fresh arenas: the i-th created entity has handle (i, 0)), then
    // the references between them, once every handle exists.
    std::vector<KeyFrameHandle> kf_handles(nk);
    for (size_t k = 0; k < nk; ++k) {
      const schema::KeyFrameRecord& r = *seg.keyframes()->Get(static_cast<fb::uoffset_t>(k));
      KeyFrame kf = records::KeyFrameFromRecord(r);
      kf_handles[k] = map.RestoreKeyFrame(std::move(kf));
    }
    kf_handles_of[m] = kf_handles;
    std::vector<PointHandle> point_handles(np);
    const schema::PointRecord* records = Span(seg.points()).data();
    const uint32_t* offsets = Span(seg.observation_offsets()).data();
    const schema::ObservationRecord* observations = Span(seg.observations()).data();
    for (size_t i = 0; i < np; ++i) {
      const schema::PointRecord& r = records[i];
      MapPoint p = records::FromPointRecord(r);
      p.reference = r.reference() == kNoIndex ? KeyFrameHandle::null() : kf_handles[r.reference()];
      p.observations.reserve(offsets[i + 1] - offsets[i]);
      for (uint32_t o = offsets[i]; o < offsets[i + 1]; ++o)
        p.observations.push_back({kf_handles[observations[o].keyframe()], observations[o].keypoint()});
      point_handles[i] = map.points().create(std::move(p));
    }
    for (size_t k = 0; k < nk; ++k) {
      const schema::KeyFrameRecord& r = *seg.keyframes()->Get(static_cast<fb::uoffset_t>(k));
      KeyFrame& kf = map.keyframe(kf_handles[k]);
      const uint32_t* point_index = Span(r.points()).data();
      for (size_t j = 0; j < kf.points.size(); ++j)
        kf.points[j] = point_index[j] == kNoIndex ? PointHandle::null() : point_handles[point_index[j]];
      kf.parent = r.parent() == kNoIndex ? KeyFrameHandle::null() : kf_handles[r.parent()];
      for (uint32_t c : Span(r.children())) kf.children.push_back(kf_handles[c]);
      for (uint32_t l : Span(r.loop_edges())) kf.loop_edges.push_back(kf_handles[l]);
      kf.covisible.reserve(Size(r.covisible()));
      for (const schema::CovisibilityEdge& e : Span(r.covisible()))
        kf.covisible.emplace_back(kf_handles[e.keyframe()], e.weight());
    }
    const std::string problem = map.Validate();
    FLATSLAM_CHECK(problem.empty(), "map snapshot ", view.name(), ": map ", m, " is inconsistent: ", problem);
  }
  if (const schema::Session* s = view.root().session()) {
    SnapshotSession session = *view.session_summary();
    const std::vector<KeyFrameHandle>& handles = kf_handles_of[s->map()];
    for (const schema::FramePoseRecord& r : Span(s->frames())) {
      AnchoredFramePose f;
      f.t_ns = r.t_ns();
      f.reference = r.reference() == kNoIndex ? KeyFrameHandle::null() : handles[r.reference()];
      f.T_cam_ref = FromSchema(r.cam_from_ref());
      f.T_cam_world = FromSchema(r.cam_from_world());
      session.frames.push_back(f);
    }
    out.metadata.session = std::move(session);
  }
  return out;
}

LoadedSnapshot LoadMapSnapshot(const std::filesystem::path& path, const SnapshotReadOptions& options) {
  return LoadMapSnapshot(MapSnapshotView::Open(path, options));
}

LoadedSnapshot LoadMapSnapshotFromBytes(std::span<const uint8_t> bytes, const std::string& name,
                                        const SnapshotReadOptions& options) {
  return LoadMapSnapshot(MapSnapshotView::FromBytes(bytes, name, options));
}

}  // namespace flatslam
