// Synthetic renderer: z-buffered planar quads with mip-mapped procedural textures.
#include "io/synthetic.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <random>
#include <sstream>

#include <opencv2/imgproc.hpp>
#include <tbb/parallel_for.h>

#include "core/error.h"

namespace flatslam {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr int kMaxTextureSide = 4096;
constexpr float kNearPlane = 0.05f;

uint64_t SplitMix(uint64_t* state) {
  uint64_t z = (*state += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Approximately standard normal from four uniform bytes (Irwin-Hall); cheap and deterministic.
float GaussFromBits(uint64_t bits) {
  const int sum = static_cast<int>(bits & 0xff) + static_cast<int>((bits >> 8) & 0xff) +
                  static_cast<int>((bits >> 16) & 0xff) + static_cast<int>((bits >> 24) & 0xff);
  return (static_cast<float>(sum) - 510.0f) * (1.0f / 147.8f);
}

// Multi-scale random shapes over smooth noise: corners and blobs at every pyramid scale.
cv::Mat GenerateTexture(int width, int height, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> grey(0, 255), mid(60, 200);
  cv::Mat coarse(std::max(2, height / 40), std::max(2, width / 40), CV_8UC1);
  for (int r = 0; r < coarse.rows; ++r)
    for (int c = 0; c < coarse.cols; ++c) coarse.at<uint8_t>(r, c) = static_cast<uint8_t>(mid(rng));
  cv::Mat img;
  cv::resize(coarse, img, cv::Size(width, height), 0, 0, cv::INTER_CUBIC);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double log_min = std::log(2.0), log_max = std::log(48.0);
  const long shapes = static_cast<long>(width) * height / 300;
  for (long k = 0; k < shapes; ++k) {
    const cv::Point c(static_cast<int>(unit(rng) * width), static_cast<int>(unit(rng) * height));
    const int size = static_cast<int>(std::exp(log_min + unit(rng) * (log_max - log_min)));
    const cv::Scalar colour(grey(rng));
    switch (rng() % 6) {
      case 0:
        cv::rectangle(img, c, c + cv::Point(size, static_cast<int>(size * (0.3 + unit(rng)))), colour,
                      cv::FILLED);
        break;
      case 1:
        cv::circle(img, c, std::max(1, size / 2), colour, cv::FILLED);
        break;
      case 2:
        cv::line(img, c, c + cv::Point(size, static_cast<int>((unit(rng) - 0.5) * 2 * size)), colour,
                 1 + static_cast<int>(rng() % 3));
        break;
      case 3:
        cv::ellipse(img, c, cv::Size(std::max(1, size / 2), std::max(1, size / 4)), unit(rng) * 180, 0,
                    360, colour, cv::FILLED);
        break;
      case 4: {
        const cv::Point pts[3] = {c, c + cv::Point(size, static_cast<int>(unit(rng) * size)),
                                  c + cv::Point(static_cast<int>(unit(rng) * size), size)};
        cv::fillConvexPoly(img, pts, 3, colour);
        break;
      }
      default:
        cv::rectangle(img, c, c + cv::Point(size, size), colour, 1 + static_cast<int>(rng() % 2));
        break;
    }
  }
  return img;
}

// Catmull-Rom point on the closed loop through pts, segment i, parameter u in [0,1].
Eigen::Vector3d CatmullRom(const std::vector<Eigen::Vector3d>& pts, size_t i, double u) {
  const size_t n = pts.size();
  const Eigen::Vector3d& p0 = pts[(i + n - 1) % n];
  const Eigen::Vector3d& p1 = pts[i % n];
  const Eigen::Vector3d& p2 = pts[(i + 1) % n];
  const Eigen::Vector3d& p3 = pts[(i + 2) % n];
  const double u2 = u * u, u3 = u2 * u;
  return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 +
                (-p0 + 3 * p1 - 3 * p2 + p3) * u3);
}

}  // namespace

struct SyntheticScene::Texture {
  // Raw view of one mip level, so the per-pixel sampler touches no cv::Mat internals.
  struct Level {
    const uint8_t* data = nullptr;
    int width = 0, height = 0;
    size_t stride = 0;
    float scale = 1;  // level texels per level-0 texel
  };
  std::vector<cv::Mat> images;  // CV_8UC1 mip pyramid, level 0 finest (owns the pixels)
  std::vector<Level> levels;
  float texels_per_m = 1;
};

// Arc-length table of one agent's loop.
struct SyntheticScene::PathTable {
  std::vector<Eigen::Vector3d> points;
  std::vector<double> arc;  // cumulative length at each point; arc.back() = loop length
  double length = 0;

  explicit PathTable(const std::vector<Eigen::Vector3d>& control) {
    FLATSLAM_CHECK(control.size() >= 4, "camera path needs at least 4 control points");
    constexpr int kSamples = 64;
    for (size_t i = 0; i < control.size(); ++i)
      for (int k = 0; k < kSamples; ++k) points.push_back(CatmullRom(control, i, double(k) / kSamples));
    points.push_back(points.front());
    arc.resize(points.size(), 0.0);
    for (size_t i = 1; i < points.size(); ++i) arc[i] = arc[i - 1] + (points[i] - points[i - 1]).norm();
    length = arc.back();
  }

  [[nodiscard]] Eigen::Vector3d At(double s) const {
    s = std::fmod(s, length);
    if (s < 0) s += length;
    const size_t hi = static_cast<size_t>(std::upper_bound(arc.begin(), arc.end(), s) - arc.begin());
    const size_t i = std::min(hi, arc.size() - 1);
    const size_t j = i == 0 ? 0 : i - 1;
    const double span = arc[i] - arc[j];
    const double f = span > 0 ? (s - arc[j]) / span : 0.0;
    return points[j] + f * (points[i] - points[j]);
  }
};

bool SyntheticOptions::Check() const {
  return width >= 32 && height >= 32 && fx >= 0 && fy >= 0 && frame_rate_hz > 0 && duration_s >= 0 &&
         baseline_m >= 0 && pixel_noise_sigma >= 0 && depth_noise_k >= 0 && max_depth_m > 0 && agent >= 0;
}

void ParseSyntheticSpec(const std::string& spec, std::string* scene, SyntheticOptions* options) {
  const size_t colon = spec.find(':');
  *scene = spec.substr(0, colon);
  if (colon == std::string::npos) return;
  std::stringstream list(spec.substr(colon + 1));
  std::string item;
  while (std::getline(list, item, ',')) {
    const size_t eq = item.find('=');
    FLATSLAM_CHECK(eq != std::string::npos, "synthetic spec '", spec, "': expected key=value, got '", item, "'");
    const std::string key = item.substr(0, eq), value = item.substr(eq + 1);
    double v = 0;
    if (key != "sensor") {
      try {
        size_t used = 0;
        v = std::stod(value, &used);
        if (used != value.size()) throw std::invalid_argument(value);
      } catch (const std::exception&) {
        Fail("synthetic spec '", spec, "': ", key, "='", value, "' is not a number");
      }
    }
    if (key == "width") options->width = static_cast<int>(v);
    else if (key == "height") options->height = static_cast<int>(v);
    else if (key == "fx") options->fx = v;
    else if (key == "fps") options->frame_rate_hz = v;
    else if (key == "duration") options->duration_s = v;
    else if (key == "baseline") options->baseline_m = v;
    else if (key == "noise") options->pixel_noise_sigma = v;
    else if (key == "depth_noise") options->depth_noise_k = v;
    else if (key == "agent") options->agent = static_cast<int>(v);
    else if (key == "seed") options->seed = static_cast<uint64_t>(v);
    else if (key == "sensor") options->sensor = ParseSensor(value);
    else Fail("synthetic spec '", spec, "': unknown key '", key,
              "' (known: width, height, fx, fps, duration, baseline, noise, depth_noise, agent, seed, sensor)");
  }
}

SyntheticScene::SyntheticScene(SceneDescription description, const SyntheticOptions& options)
    : description_(std::move(description)), options_(options) {
  FLATSLAM_CHECK(options_.Check(), "synthetic options out of range (scene '", description_.name, "')");
  FLATSLAM_CHECK(options_.agent < static_cast<int>(description_.agents.size()), "scene '",
                 description_.name, "' has ", description_.agents.size(), " agent(s); agent ",
                 options_.agent, " does not exist");
  if (options_.fx == 0) options_.fx = 0.75 * options_.width;
  if (options_.fy == 0) options_.fy = options_.fx;
  if (options_.duration_s == 0) options_.duration_s = description_.default_duration_s;
  if (options_.baseline_m == 0) options_.baseline_m = description_.default_baseline_m;

  calibration_.sensor = options_.sensor;
  calibration_.camera = PinholeCamera{options_.fx, options_.fy, (options_.width - 1) * 0.5,
                                      (options_.height - 1) * 0.5, options_.width, options_.height};
  calibration_.baseline_m = options_.sensor == Sensor::kStereo ? options_.baseline_m : 0.0;
  calibration_.frame_rate_hz = options_.frame_rate_hz;
  frame_count_ = static_cast<size_t>(std::llround(options_.duration_s * options_.frame_rate_hz));
  FLATSLAM_CHECK(frame_count_ > 0, "synthetic scene '", description_.name, "' has no frames");

  path_ = std::make_unique<PathTable>(description_.agents[options_.agent].control_points);

  textures_.resize(description_.quads.size());
  tbb::parallel_for(size_t{0}, description_.quads.size(), [&](size_t i) {
    const SceneQuad& q = description_.quads[i];
    auto tex = std::make_unique<Texture>();
    const double longest = std::max(q.size_u, q.size_v);
    tex->texels_per_m = static_cast<float>(std::min(q.texels_per_m, kMaxTextureSide / longest));
    const int w = std::max(4, static_cast<int>(std::ceil(q.size_u * tex->texels_per_m)));
    const int h = std::max(4, static_cast<int>(std::ceil(q.size_v * tex->texels_per_m)));
    tex->images.push_back(GenerateTexture(w, h, description_.world_seed * 1000003ull + i));
    while (tex->images.back().cols > 8 && tex->images.back().rows > 8) {
      cv::Mat down;
      cv::pyrDown(tex->images.back(), down);
      tex->images.push_back(down);
    }
    for (size_t l = 0; l < tex->images.size(); ++l) {
      const cv::Mat& m = tex->images[l];
      tex->levels.push_back({m.ptr<uint8_t>(0), m.cols, m.rows, m.step[0], 1.0f / static_cast<float>(1u << l)});
    }
    textures_[i] = std::move(tex);
  });
}

SyntheticScene::~SyntheticScene() = default;

int64_t SyntheticScene::timestamp_ns(size_t frame) const {
  return static_cast<int64_t>(std::llround(static_cast<double>(frame) * 1e9 / options_.frame_rate_hz));
}

double SyntheticScene::path_length_m() const {
  return description_.agents[options_.agent].speed_mps * (frame_count_ - 1) / options_.frame_rate_hz;
}

double SyntheticScene::loop_length_m() const { return path_->length; }

Eigen::Isometry3d SyntheticScene::PoseAt(double t) const {
  const CameraPath& agent = description_.agents[options_.agent];
  const double s = agent.start_s + agent.speed_mps * t;
  Eigen::Vector3d position = path_->At(s);
  position.z() += agent.height_wobble_m * std::sin(2 * kPi * t / 4.1);
  Eigen::Vector3d tangent = path_->At(s + 0.05) - path_->At(s - 0.05);
  tangent.z() = 0;
  tangent.normalize();
  const double yaw = agent.yaw_wobble_rad * std::sin(2 * kPi * t / 7.3);
  const double pitch = agent.pitch_wobble_rad * std::sin(2 * kPi * t / 5.1);
  const Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d forward = Eigen::AngleAxisd(yaw, up) * tangent;
  forward = (std::cos(pitch) * forward + std::sin(pitch) * up).normalized();
  const Eigen::Vector3d right = forward.cross(up).normalized();
  const Eigen::Vector3d down = forward.cross(right);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear().col(0) = right;
  T.linear().col(1) = down;
  T.linear().col(2) = forward;
  T.translation() = position;
  return T;
}

namespace {

// Per-thread render buffers, reused across frames.
struct RenderScratch {
  std::vector<float> inv_depth, s, t;
  std::vector<int32_t> quad;
  void Resize(size_t n) {
    inv_depth.assign(n, 0.0f);
    quad.assign(n, -1);
    s.resize(n);
    t.resize(n);
  }
};

// log2 to within 0.09: exponent plus linear mantissa; enough to choose a mip level.
inline float FastLog2(float x) {
  const uint32_t bits = std::bit_cast<uint32_t>(x);
  const float mantissa = std::bit_cast<float>((bits & 0x007fffffu) | 0x3f800000u);
  return static_cast<float>(static_cast<int>(bits >> 23) - 127) + (mantissa - 1.0f);
}

template <class Level>
[[gnu::always_inline]] inline float SampleBilinear(const Level& img, float x, float y) {
  x = std::clamp(x, 0.0f, static_cast<float>(img.width - 1));
  y = std::clamp(y, 0.0f, static_cast<float>(img.height - 1));
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const int x1 = std::min(x0 + 1, img.width - 1), y1 = std::min(y0 + 1, img.height - 1);
  const float fx = x - x0, fy = y - y0;
  const uint8_t* r0 = img.data + img.stride * y0;
  const uint8_t* r1 = img.data + img.stride * y1;
  const float top = r0[x0] + fx * (r0[x1] - r0[x0]);
  const float bottom = r1[x0] + fx * (r1[x1] - r1[x0]);
  return top + fy * (bottom - top);
}

}  // namespace

void SyntheticScene::RenderView(const Eigen::Isometry3d& T_world_cam, uint64_t noise_seed, cv::Mat* gray,
                                cv::Mat* depth_m) const {
  const int W = options_.width, H = options_.height;
  const float fx = static_cast<float>(calibration_.camera.fx), fy = static_cast<float>(calibration_.camera.fy);
  const float cx = static_cast<float>(calibration_.camera.cx), cy = static_cast<float>(calibration_.camera.cy);
  thread_local RenderScratch scratch;
  scratch.Resize(static_cast<size_t>(W) * H);

  const Eigen::Matrix3d R_cam_world = T_world_cam.linear().transpose();
  const Eigen::Vector3d t_cam_world = -R_cam_world * T_world_cam.translation();
  const float inv_fx = 1.0f / fx, inv_fy = 1.0f / fy;
  // Per-quad constants of the shading pass for this view.
  struct QuadShading {
    Eigen::Vector3f normal = Eigen::Vector3f::Zero();  // camera frame
    float footprint_scale2 = 0;                        // (texels_per_m / fx)^2
    float last_level = 0;                              // highest level l with l + 1 present
    float brightness = 1;
  };
  std::vector<QuadShading> shading(description_.quads.size());

  for (size_t qi = 0; qi < description_.quads.size(); ++qi) {
    const SceneQuad& quad = description_.quads[qi];
    const Eigen::Vector3d o = R_cam_world * quad.origin + t_cam_world;
    const Eigen::Vector3d a = R_cam_world * quad.axis_u;
    const Eigen::Vector3d b = R_cam_world * quad.axis_v;
    // Clip the quad against the near plane, then bound its projection.
    const std::array<Eigen::Vector3d, 4> corners = {o, o + quad.size_u * a, o + quad.size_u * a + quad.size_v * b,
                                                    o + quad.size_v * b};
    double u_min = W, u_max = -1, v_min = H, v_max = -1;
    bool any = false;
    auto extend = [&](const Eigen::Vector3d& p) {
      const double u = fx * p.x() / p.z() + cx, v = fy * p.y() / p.z() + cy;
      u_min = std::min(u_min, u);
      u_max = std::max(u_max, u);
      v_min = std::min(v_min, v);
      v_max = std::max(v_max, v);
      any = true;
    };
    for (int k = 0; k < 4; ++k) {
      const Eigen::Vector3d& p = corners[k];
      const Eigen::Vector3d& q = corners[(k + 1) % 4];
      const bool p_in = p.z() >= kNearPlane, q_in = q.z() >= kNearPlane;
      if (p_in) extend(p);
      if (p_in != q_in) extend(p + (q - p) * ((kNearPlane - p.z()) / (q.z() - p.z())));
    }
    if (!any) continue;
    const int u0 = std::max(0, static_cast<int>(std::floor(u_min)) - 1);
    const int u1 = std::min(W - 1, static_cast<int>(std::ceil(u_max)) + 1);
    const int v0 = std::max(0, static_cast<int>(std::floor(v_min)) - 1);
    const int v1 = std::min(H - 1, static_cast<int>(std::ceil(v_max)) + 1);
    if (u0 > u1 || v0 > v1) continue;

    // Plane homography: camera point X = [a b o] (s, t, 1)^T; M maps a ray to (s, t, 1) / z.
    Eigen::Matrix3d Hm;
    Hm << a, b, o;
    if (std::abs(Hm.determinant()) < 1e-9) continue;  // plane through the optical centre
    const Eigen::Matrix3f M = Hm.inverse().cast<float>();
    QuadShading& shade = shading[qi];
    shade.normal = a.cross(b).normalized().cast<float>();
    shade.footprint_scale2 = std::pow(textures_[qi]->texels_per_m / fx, 2.0f);
    shade.last_level = static_cast<float>(textures_[qi]->levels.size()) - 1.001f;
    shade.brightness = quad.brightness;
    const float size_u = static_cast<float>(quad.size_u), size_v = static_cast<float>(quad.size_v);
    // Along a row, q(u) = q_row + u * du is linear, and the quad is exactly where
    // q.z > 0, 0 <= q.x <= size_u q.z and 0 <= q.y <= size_v q.z: five half-lines in u.
    const Eigen::Vector3d du = M.col(0).cast<double>() / fx;
    for (int v = v0; v <= v1; ++v) {
      const Eigen::Vector3d q_row = M.col(0).cast<double>() * (-cx / fx) +
                                    M.col(1).cast<double>() * ((v - cy) / fy) + M.col(2).cast<double>();
      double lo = u0, hi = u1;
      auto keep = [&](double c0, double c1) {  // c0 + c1 u >= 0
        if (c1 > 0) lo = std::max(lo, -c0 / c1);
        else if (c1 < 0) hi = std::min(hi, -c0 / c1);
        else if (c0 < 0) hi = -1;
      };
      keep(q_row.z(), du.z());
      keep(q_row.x(), du.x());
      keep(quad.size_u * q_row.z() - q_row.x(), quad.size_u * du.z() - du.x());
      keep(q_row.y(), du.y());
      keep(quad.size_v * q_row.z() - q_row.y(), quad.size_v * du.z() - du.y());
      if (!(lo <= hi)) continue;  // empty (lo, hi stay within [u0, u1] otherwise)
      const int ua = static_cast<int>(std::ceil(lo)), ub = static_cast<int>(std::floor(hi));
      if (ua > ub) continue;
      Eigen::Vector3f q = (q_row + du * ua).cast<float>();
      const Eigen::Vector3f duf = du.cast<float>();
      const size_t row = static_cast<size_t>(v) * W;
      for (int u = ua; u <= ub; ++u, q += duf) {
        const float w = q.z();
        const size_t p = row + u;
        if (w <= scratch.inv_depth[p]) continue;
        const float inv = 1.0f / w;
        scratch.inv_depth[p] = w;
        scratch.quad[p] = static_cast<int32_t>(qi);
        scratch.s[p] = std::clamp(q.x() * inv, 0.0f, size_u);
        scratch.t[p] = std::clamp(q.y() * inv, 0.0f, size_v);
      }
    }
  }

  gray->create(H, W, CV_8UC1);
  if (depth_m) depth_m->create(H, W, CV_32FC1);
  uint64_t rng = noise_seed;
  const float sigma = noise_seed ? static_cast<float>(options_.pixel_noise_sigma) : 0.0f;
  for (int v = 0; v < H; ++v) {
    uint8_t* out = gray->ptr<uint8_t>(v);
    float* dout = depth_m ? depth_m->ptr<float>(v) : nullptr;
    for (int u = 0; u < W; ++u) {
      const size_t p = static_cast<size_t>(v) * W + u;
      const int32_t qi = scratch.quad[p];
      float value;
      if (qi < 0) {
        value = 150.0f + 60.0f * static_cast<float>(v) / H;  // featureless sky / void
        if (dout) dout[u] = 0.0f;
      } else {
        const float w = scratch.inv_depth[p];
        const QuadShading& shade = shading[qi];
        const Texture& tex = *textures_[qi];
        // Squared texel footprint of one pixel, widened on slanted surfaces (cosine floor
        // 0.2), picks the mip level: footprint^2 = (tpm/fx)^2 |ray|^2 / (w^2 max(cos^2 |ray|^2)).
        const float rx = (u - cx) * inv_fx, ry = (v - cy) * inv_fy;
        const float ray2 = rx * rx + ry * ry + 1.0f;
        const float dot = shade.normal.x() * rx + shade.normal.y() * ry + shade.normal.z();
        const float footprint2 = shade.footprint_scale2 * ray2 / (w * w * std::max(dot * dot, 0.04f * ray2));
        float level = footprint2 > 1.0f ? 0.5f * FastLog2(footprint2) : 0.0f;
        level = std::min(level, shade.last_level);
        const int l0 = static_cast<int>(level);
        // Blend two levels only around the middle of a level ("brilinear"): fewer samples.
        const float blend = std::clamp((level - l0 - 0.3f) * 2.5f, 0.0f, 1.0f);
        const float x0 = scratch.s[p] * tex.texels_per_m, y0 = scratch.t[p] * tex.texels_per_m;
        const auto& level0 = tex.levels[l0];
        const float a = SampleBilinear(level0, x0 * level0.scale - 0.5f, y0 * level0.scale - 0.5f);
        float b = a;
        if (blend > 0.0f) {
          const auto& level1 = tex.levels[l0 + 1];
          b = SampleBilinear(level1, x0 * level1.scale - 0.5f, y0 * level1.scale - 0.5f);
        }
        value = (a + blend * (b - a)) * shade.brightness;
        if (dout) dout[u] = 1.0f / w;
      }
      if (sigma > 0) value += sigma * GaussFromBits(SplitMix(&rng));
      out[u] = static_cast<uint8_t>(std::clamp(value + 0.5f, 0.0f, 255.0f));
    }
  }
}

Frame SyntheticScene::Render(size_t i) const {
  FLATSLAM_CHECK(i < frame_count_, "synthetic frame ", i, " out of range (", frame_count_, " frames)");
  Frame frame;
  frame.index = i;
  frame.t_ns = timestamp_ns(i);
  const Eigen::Isometry3d T_world_cam = PoseAt(static_cast<double>(frame.t_ns) * 1e-9);
  // Noise seeds depend only on (seed, agent, frame, view): any thread order gives the same pixels.
  uint64_t mix = options_.seed * 0x9e3779b97f4a7c15ull + (static_cast<uint64_t>(options_.agent) << 40) + i * 4;
  const uint64_t seed_left = SplitMix(&mix) | 1, seed_right = SplitMix(&mix) | 1, seed_depth = SplitMix(&mix);
  const bool noisy = options_.pixel_noise_sigma > 0;
  if (options_.sensor == Sensor::kRgbd) {
    cv::Mat depth;
    RenderView(T_world_cam, noisy ? seed_left : 0, &frame.left, &depth);
    uint64_t rng = seed_depth;
    const float k = static_cast<float>(options_.depth_noise_k), max_depth = static_cast<float>(options_.max_depth_m);
    for (int v = 0; v < depth.rows; ++v) {
      float* d = depth.ptr<float>(v);
      for (int u = 0; u < depth.cols; ++u) {
        const float z = d[u];
        if (z <= 0 || z > max_depth) {
          d[u] = 0;
          continue;
        }
        d[u] = std::max(0.0f, z + k * z * z * GaussFromBits(SplitMix(&rng)));
      }
    }
    frame.depth = depth;
  } else {
    RenderView(T_world_cam, noisy ? seed_left : 0, &frame.left, nullptr);
    if (options_.sensor == Sensor::kStereo) {
      const Eigen::Isometry3d T_world_right = T_world_cam * Eigen::Translation3d(options_.baseline_m, 0, 0);
      RenderView(T_world_right, noisy ? seed_right : 0, &frame.right, nullptr);
    }
  }
  return frame;
}

Trajectory SyntheticScene::GroundTruth() const {
  Trajectory gt(frame_count_);
  for (size_t i = 0; i < frame_count_; ++i) {
    gt[i].t_ns = timestamp_ns(i);
    gt[i].T_world_cam = PoseAt(static_cast<double>(gt[i].t_ns) * 1e-9);
  }
  return gt;
}

namespace {

class SyntheticDataset final : public Dataset {
 public:
  SyntheticDataset(SceneDescription scene, const SyntheticOptions& options)
      : scene_(std::move(scene), options) {}

  std::string name() const override {
    std::ostringstream out;
    out << "synthetic " << scene_.description().name << " (agent " << scene_.options().agent << ", "
        << SensorName(scene_.options().sensor) << ")";
    return out.str();
  }
  const Calibration& calibration() const override { return scene_.calibration(); }
  size_t size() const override { return scene_.frame_count(); }
  Frame read(size_t i) const override { return scene_.Render(i); }
  std::optional<Trajectory> ground_truth() const override { return scene_.GroundTruth(); }

 private:
  SyntheticScene scene_;
};

}  // namespace

std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& spec, const DatasetOptions& options) {
  std::string scene;
  SyntheticOptions synth;
  synth.seed = options.seed;
  if (options.sensor) synth.sensor = *options.sensor;
  ParseSyntheticSpec(spec, &scene, &synth);
  return std::make_unique<SyntheticDataset>(MakeScene(scene), synth);
}

}  // namespace flatslam
