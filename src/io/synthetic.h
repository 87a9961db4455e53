// Synthetic scene renderer: textured planar worlds (room, corridor, street, town), camera
// paths with loops and revisits, several agents, exact ground truth; mono, stereo, RGB-D.
// Concurrency: a SyntheticScene is immutable after construction; Render() is const and
// thread-safe, so frames can be rendered in parallel.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>

#include "io/dataset.h"
#include "io/types.h"

namespace flatslam {

// A textured rectangle: points origin + s*axis_u + t*axis_v for s in [0,size_u], t in [0,size_v].
struct SceneQuad {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis_u = Eigen::Vector3d::UnitX();  // unit length
  Eigen::Vector3d axis_v = Eigen::Vector3d::UnitY();  // unit length, orthogonal to axis_u
  double size_u = 1, size_v = 1;                      // metres
  double texels_per_m = 96;                           // texture resolution on this surface
  float brightness = 1.0f;                            // stands in for lighting
};

// A closed loop through control points, followed at constant speed, forward-looking.
struct CameraPath {
  std::vector<Eigen::Vector3d> control_points;  // world frame, z up; closed (last joins first)
  double speed_mps = 1.0;
  double start_s = 0;         // arc length at t = 0
  double yaw_wobble_rad = 0;  // small periodic look-around, keeps motion non-degenerate
  double pitch_wobble_rad = 0;
  double height_wobble_m = 0;
};

struct SceneDescription {
  std::string name;
  std::vector<SceneQuad> quads;
  std::vector<CameraPath> agents;  // at least one
  double default_duration_s = 60;
  double default_baseline_m = 0.12;  // stereo rig of the scene: a handheld rig indoors, a car rig outdoors
  uint64_t world_seed = 1;         // textures; fixed per scene so every agent sees one world
};

// Names accepted by MakeScene(): room, corridor, street, town (3 agents).
[[nodiscard]] std::vector<std::string> SyntheticSceneNames();
// Throws flatslam::Error listing the known names on an unknown one.
[[nodiscard]] SceneDescription MakeScene(const std::string& name);

struct SyntheticOptions {
  int width = 640;              // pixels
  int height = 480;
  double fx = 0;                // 0 = 0.75 * width (about 67 degrees horizontal field of view)
  double fy = 0;                // 0 = fx
  double frame_rate_hz = 20;
  double duration_s = 0;        // 0 = the scene's default
  double baseline_m = 0;        // stereo baseline; 0 = the scene's default
  double pixel_noise_sigma = 1.5;  // grey levels, Gaussian
  double depth_noise_k = 0.0015;   // depth sigma = k * z^2 (metres), as a structured-light sensor
  double max_depth_m = 20;         // RGB-D: farther pixels read 0 (no measurement)
  int agent = 0;
  uint64_t seed = 1;            // noise; the world itself is fixed by the scene
  Sensor sensor = Sensor::kStereo;

  [[nodiscard]] bool Check() const;
};

// Parses "NAME[:key=value,...]" (keys: width, height, fx, fps, duration, baseline, noise,
// depth_noise, agent, seed, sensor) into a scene name and options. Throws flatslam::Error.
void ParseSyntheticSpec(const std::string& spec, std::string* scene, SyntheticOptions* options);

class SyntheticScene {
 public:
  SyntheticScene(SceneDescription description, const SyntheticOptions& options);
  ~SyntheticScene();
  SyntheticScene(const SyntheticScene&) = delete;
  SyntheticScene& operator=(const SyntheticScene&) = delete;

  [[nodiscard]] const SceneDescription& description() const { return description_; }
  [[nodiscard]] const SyntheticOptions& options() const { return options_; }
  [[nodiscard]] const Calibration& calibration() const { return calibration_; }
  [[nodiscard]] size_t frame_count() const { return frame_count_; }
  [[nodiscard]] int64_t timestamp_ns(size_t frame) const;
  // Exact pose of the left camera for agent options().agent at time t.
  [[nodiscard]] Eigen::Isometry3d PoseAt(double t_s) const;
  [[nodiscard]] double path_length_m() const;  // travelled in frame_count() frames
  [[nodiscard]] double loop_length_m() const;  // one lap of this agent's loop

  // Renders a grey image (CV_8UC1) seen from T_world_cam; depth_m (optional) receives
  // the noise-free z-depth in metres (0 where nothing is hit). noise_seed 0 = no noise.
  void RenderView(const Eigen::Isometry3d& T_world_cam, uint64_t noise_seed, cv::Mat* gray,
                  cv::Mat* depth_m) const;
  // Renders frame i for the configured sensor.
  [[nodiscard]] Frame Render(size_t i) const;
  [[nodiscard]] Trajectory GroundTruth() const;

 private:
  struct Texture;
  struct PathTable;

  SceneDescription description_;
  SyntheticOptions options_;
  Calibration calibration_;
  size_t frame_count_ = 0;
  std::vector<std::unique_ptr<Texture>> textures_;  // one per quad
  std::unique_ptr<PathTable> path_;
};

// The Dataset view of a synthetic scene ("synth:NAME[:key=value,...]" in OpenDataset).
[[nodiscard]] std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& spec,
                                                            const DatasetOptions& options);

}  // namespace flatslam
