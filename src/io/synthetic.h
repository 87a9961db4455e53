// Synthetic scene renderer: textured planar worlds (room, corridor, street, town, highway,
// handheld), camera paths with loops and revisits, several agents, moving objects, motion blur
// and exposure changes, exact ground truth of the camera; mono, stereo, RGB-D.
// Concurrency: a SyntheticScene is immutable after construction; Render() is const and
// thread-safe, so frames can be rendered in parallel.
#pragma once

#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>

#include "io/dataset.h"
#include "io/types.h"

namespace flatslam {

// How a quad's procedural texture looks.
enum class TextureStyle : uint8_t {
  kShapes,   // multi-scale random shapes over smooth noise: walls, facades, furniture, vehicles
  kAsphalt,  // road surface: low-contrast grain with patches, cracks and tyre marks
  kPaint,    // road marking: bright, nearly uniform
};

// A textured rectangle: points origin + s*axis_u + t*axis_v for s in [0,size_u], t in [0,size_v].
struct SceneQuad {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis_u = Eigen::Vector3d::UnitX();  // unit length
  Eigen::Vector3d axis_v = Eigen::Vector3d::UnitY();  // unit length, orthogonal to axis_u
  double size_u = 1, size_v = 1;                      // metres
  double texels_per_m = 96;                           // texture resolution on this surface
  float brightness = 1.0f;                            // stands in for lighting
  TextureStyle style = TextureStyle::kShapes;
};

// The quad spanned by u and v from origin (u and v orthogonal; their lengths are the sizes).
[[nodiscard]] SceneQuad MakeQuad(const Eigen::Vector3d& origin, const Eigen::Vector3d& u, const Eigen::Vector3d& v,
                                 double texels_per_m, float brightness);

// A quick look-around on top of the forward-looking path: turns by (yaw, pitch) over turn_s with a
// raised-cosine profile (peak rate = amplitude * pi / (2 turn_s)), holds, then turns back.
struct CameraGlance {
  double start_s = 0;
  double turn_s = 0.5;
  double hold_s = 0.5;
  double yaw_rad = 0;    // positive turns left
  double pitch_rad = 0;  // positive looks up
};

// A closed loop through control points, followed at constant speed, forward-looking.
struct CameraPath {
  std::vector<Eigen::Vector3d> control_points;  // world frame, z up; closed (last joins first)
  double speed_mps = 1.0;
  double start_s = 0;         // arc length at t = 0
  double yaw_wobble_rad = 0;  // small periodic look-around, keeps motion non-degenerate
  double pitch_wobble_rad = 0;
  double height_wobble_m = 0;
  double roll_wobble_rad = 0;         // hand-held tilt about the viewing direction
  std::vector<CameraGlance> glances;  // sorted by start_s, not overlapping
};

// One sample of a mover's motion: where its body frame is at time t_s.
struct MoverKey {
  double t_s = 0;
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // body origin in the world
  double yaw_rad = 0;                                  // body x axis = (cos yaw, sin yaw, 0)
};

// A rigid group of quads (a vehicle, a box) whose world pose is a function of time: the keys
// interpolated linearly. Its quads are in the body frame (x forward, y left, z up).
struct SceneMover {
  std::vector<SceneQuad> quads;
  std::vector<MoverKey> keys;  // increasing t_s, at least one
  double period_s = 0;         // > 0: the motion repeats with this period (keys span one period)
  double active_from_s = -std::numeric_limits<double>::infinity();  // absent outside [from, until]
  double active_until_s = std::numeric_limits<double>::infinity();

  [[nodiscard]] bool active(double t_s) const { return t_s >= active_from_s && t_s <= active_until_s; }
  // T_world_body at t_s (keys held before the first and after the last when not periodic).
  [[nodiscard]] Eigen::Isometry3d PoseAt(double t_s) const;
};

// What the camera's exposure adds in Render(); RenderView() renders one instant at unit gain.
struct SceneExposure {
  double exposure_s = 0;         // motion blur: sub-frames averaged over this time around the frame time
  double gain_wobble = 0;        // relative amplitude of a smooth global gain variation
  double gain_step_every_s = 0;  // mean time between auto-exposure steps; 0 = none
  double gain_step_min = 0.2;    // relative size of a step, drawn in [min, max]
  double gain_step_max = 0.4;
};

struct SceneDescription {
  std::string name;
  std::vector<SceneQuad> quads;
  std::vector<SceneMover> movers;  // moving objects; the ground truth stays the camera's pose
  std::vector<CameraPath> agents;  // at least one
  double default_duration_s = 60;
  double default_baseline_m = 0.12;  // stereo rig of the scene: a handheld rig indoors, a car rig outdoors
  // Camera of the scene; 0 = the SyntheticOptions default (640 x 480, fx = 0.75 width, 20 Hz).
  int default_width = 0;
  int default_height = 0;
  double default_fx = 0;  // for default_width; scaled when the width is overridden
  double default_frame_rate_hz = 0;
  SceneExposure exposure;
  double dynamic_distance_m = 0;  // how close dynamic=F objects pass; 0 = twice the camera height
  uint64_t world_seed = 1;        // textures; fixed per scene so every agent sees one world
};

// Names accepted by MakeScene(): room, corridor, street, town (3 agents), highway (KITTI-like
// motorway with traffic), handheld (fast hand-held motion indoors, motion blur, exposure changes).
[[nodiscard]] std::vector<std::string> SyntheticSceneNames();
// Throws flatslam::Error listing the known names on an unknown one.
[[nodiscard]] SceneDescription MakeScene(const std::string& name);

struct SyntheticOptions {
  int width = 0;  // pixels; 0 = the scene's default (640 x 480 unless it has its own)
  int height = 0;
  double fx = 0;                   // 0 = the scene's, scaled to the width; else 0.75 * width (about 67 degrees)
  double fy = 0;                   // 0 = fx
  double frame_rate_hz = 0;        // 0 = the scene's default (20 Hz unless it has its own)
  double duration_s = 0;           // 0 = the scene's default
  double baseline_m = 0;           // stereo baseline; 0 = the scene's default
  double pixel_noise_sigma = 1.5;  // grey levels, Gaussian
  double depth_noise_k = 0.0015;   // depth sigma = k * z^2 (metres), as a structured-light sensor
  double max_depth_m = 20;         // RGB-D: farther pixels read 0 (no measurement)
  int agent = 0;
  uint64_t seed = 1;  // noise; the world itself is fixed by the scene
  Sensor sensor = Sensor::kStereo;
  // Adds moving objects that pass the camera one at a time (overtaking along its path or
  // crossing in front of it), each covering at most this fraction of the image; in [0, 0.3].
  double dynamic_fraction = 0;
  // Stereo: a rectification error of a real rig, in pixels of disparity. The right camera is turned
  // about its y axis by rig_error / fx radians, so the disparities the images show are rig_error
  // larger than the calibration's baseline predicts at the image centre (1 + (x / fx)^2 times that
  // x pixels from it, as a turned camera shifts them). KITTI 06's, measured from its map: about
  // -0.10 px (disparities short, depths long). In [-5, 5]; 0 = the exact rig.
  double rig_error_px = 0;
  // A lens the calibration leaves out: every image shows a radial distortion x_d = x (1 + k1 r^2)
  // of normalized coordinates (OpenCV's k1) that the calibration, pinhole, does not describe, as
  // a rectification that did not fully correct its lens would. In [0, 0.1]: pincushion only, so
  // that every pixel shows something of the undistorted view. 0 = none.
  double lens_k1 = 0;
  // RGB-D: a structured-light sensor's depth image (Kinect v1 / Xtion class, as in TUM RGB-D)
  // instead of exact depth with independent noise: depth from a disparity quantized to 1/8 px of
  // a 580 px, 7.5 cm projector-camera pair (steps of 2.9 mm at 1 m, 4.6 cm at 4 m), the
  // projector's shadow beside every nearer edge read as no depth, foreground edges fattened by
  // the correlation window (a pixel within 2 px of a nearer surface reads that surface), depth
  // registered to the colour image 1 px off, 1% of pixels missing at random, and nothing beyond
  // 4.5 m (max_depth_m does not apply). false: exact depth with depth_noise_k.
  bool structured_light = false;
  // Shades eight pixels at a time with AVX2 where the CPU has it: the same bits as the portable
  // path, 1.8-2.4x the frames per second (bench_synth). false: the portable path (tests compare
  // the two).
  bool use_avx2 = true;

  [[nodiscard]] bool Check() const;
};

// Parses "NAME[:key=value,...]" (keys: width, height, fx, fps, duration, baseline, noise,
// depth_noise, agent, seed, sensor, dynamic, rig_error, structured_light, k1) into a scene name and
// options. Throws flatslam::Error.
void ParseSyntheticSpec(const std::string& spec, std::string* scene, SyntheticOptions* options);

class SyntheticScene {
 public:
  SyntheticScene(SceneDescription description, const SyntheticOptions& options);
  ~SyntheticScene();
  SyntheticScene(const SyntheticScene&) = delete;
  SyntheticScene& operator=(const SyntheticScene&) = delete;

  // The scene as rendered: with dynamic=F, movers also holds the objects added for this agent.
  [[nodiscard]] const SceneDescription& description() const { return description_; }
  [[nodiscard]] const SyntheticOptions& options() const { return options_; }
  [[nodiscard]] const Calibration& calibration() const { return calibration_; }
  [[nodiscard]] size_t frame_count() const { return frame_count_; }
  [[nodiscard]] int64_t timestamp_ns(size_t frame) const;
  // Exact pose of the left camera for agent options().agent at time t.
  [[nodiscard]] Eigen::Isometry3d PoseAt(double t_s) const;
  [[nodiscard]] double path_length_m() const;  // travelled in frame_count() frames
  [[nodiscard]] double loop_length_m() const;  // one lap of this agent's loop

  // Global gain of the image at time t (1 unless the scene has exposure changes).
  [[nodiscard]] double GainAt(double t_s) const;

  // Renders a grey image (CV_8UC1) of one instant t_s (movers where they are then) seen from
  // T_world_cam, at unit gain and without motion blur; depth_m (optional) receives the
  // noise-free z-depth in metres (0 where nothing is hit). noise_seed 0 = no noise.
  void RenderView(const Eigen::Isometry3d& T_world_cam, double t_s, uint64_t noise_seed, cv::Mat* gray,
                  cv::Mat* depth_m) const;
  // The same at t_s = 0.
  void RenderView(const Eigen::Isometry3d& T_world_cam, uint64_t noise_seed, cv::Mat* gray, cv::Mat* depth_m) const {
    RenderView(T_world_cam, 0.0, noise_seed, gray, depth_m);
  }
  // Renders frame i for the configured sensor at the frame's time, with the scene's exposure.
  [[nodiscard]] Frame Render(size_t i) const;
  [[nodiscard]] Trajectory GroundTruth() const;

 private:
  struct Texture;
  struct PathTable;

  void AddDynamicObjects();
  [[nodiscard]] std::vector<double> ExposureTimes(double t_s) const;
  // Noise-free intensities before gain (row-major floats) and z-depth (optional) of one instant.
  void RenderLinear(const Eigen::Isometry3d& T_world_cam, double t_s, float* value, cv::Mat* depth_m) const;
  // Averages the sub-frames at times of the view offset by offset_x along the camera's x axis,
  // then applies gain and noise; depth_m (optional) is the exact depth at the frame time.
  void RenderExposure(const std::vector<double>& times, double offset_x, float gain, uint64_t noise_seed, cv::Mat* gray,
                      cv::Mat* depth_m) const;
  // lens_k1: warps a rendered view (and its depth, when given) as the lens shows it; else nothing.
  void ApplyLens(float* value, cv::Mat* depth_m) const;

  SceneDescription description_;
  SyntheticOptions options_;
  Calibration calibration_;
  size_t frame_count_ = 0;
  std::vector<std::unique_ptr<Texture>> textures_;     // one per static quad, then one per mover quad
  std::vector<Eigen::Vector4d> bounds_;                // per quad as textures_: bounding sphere centre, radius
  std::vector<size_t> mover_texture_;                  // index in textures_ of each mover's first quad
  std::vector<std::pair<double, double>> gain_steps_;  // (time, gain factor from then on)
  cv::Mat lens_map_x_, lens_map_y_;                    // lens_k1: the undistorted pixel each pixel shows
  std::unique_ptr<PathTable> path_;
};

// The Dataset view of a synthetic scene ("synth:NAME[:key=value,...]" in OpenDataset).
[[nodiscard]] std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& spec, const DatasetOptions& options);

}  // namespace flatslam
