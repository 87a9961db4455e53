// The built-in synthetic worlds and the agents' loops through them.
#include <algorithm>
#include <cmath>
#include <random>

#include "core/error.h"
#include "io/synthetic.h"

namespace flatslam {
namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

constexpr double kPi = 3.14159265358979323846;

SceneQuad Quad(const Vector3d& origin, const Vector3d& u, const Vector3d& v, double texels_per_m, float brightness) {
  return MakeQuad(origin, u, v, texels_per_m, brightness);
}

// Six faces of an axis-aligned box seen from inside (a room).
void AddRoom(const Vector3d& lo, const Vector3d& hi, double tpm, std::vector<SceneQuad>* quads) {
  const Vector3d d = hi - lo;
  const Vector3d X(d.x(), 0, 0), Y(0, d.y(), 0), Z(0, 0, d.z());
  quads->push_back(Quad(lo, X, Y, tpm, 0.85f));     // floor
  quads->push_back(Quad(lo + Z, X, Y, tpm, 1.0f));  // ceiling
  quads->push_back(Quad(lo, X, Z, tpm, 0.95f));     // y = lo wall
  quads->push_back(Quad(lo + Y, X, Z, tpm, 0.9f));  // y = hi wall
  quads->push_back(Quad(lo, Y, Z, tpm, 1.05f));     // x = lo wall
  quads->push_back(Quad(lo + X, Y, Z, tpm, 0.8f));  // x = hi wall
}

// Four vertical sides and the top of an axis-aligned box seen from outside (furniture, pillar).
void AddBox(const Vector3d& lo, const Vector3d& hi, double tpm, std::vector<SceneQuad>* quads) {
  const Vector3d d = hi - lo;
  const Vector3d X(d.x(), 0, 0), Y(0, d.y(), 0), Z(0, 0, d.z());
  quads->push_back(Quad(lo, X, Z, tpm, 0.9f));
  quads->push_back(Quad(lo + Y, X, Z, tpm, 1.0f));
  quads->push_back(Quad(lo, Y, Z, tpm, 0.8f));
  quads->push_back(Quad(lo + X, Y, Z, tpm, 1.1f));
  quads->push_back(Quad(lo + Z, X, Y, tpm, 1.15f));
}

// A row of building facades from a to b (ground level), each a vertical quad of random
// width and height; the street side is whichever side the camera is on (quads are two-sided).
void AddFacadeRow(const Vector2d& a, const Vector2d& b, double tpm, std::mt19937_64* rng,
                  std::vector<SceneQuad>* quads) {
  std::uniform_real_distribution<double> width(7.0, 16.0), height(5.0, 16.0), light(0.8, 1.15);
  const double length = (b - a).norm();
  const Vector2d dir = (b - a) / length;
  double s = 0;
  while (s < length - 1e-6) {
    double w = std::min(width(*rng), length - s);
    if (length - s - w < 4.0) w = length - s;  // no sliver at the end of the row
    const Vector2d p = a + s * dir;
    quads->push_back(Quad(Vector3d(p.x(), p.y(), 0), Vector3d(dir.x() * w, dir.y() * w, 0),
                          Vector3d(0, 0, height(*rng)), tpm, static_cast<float>(light(*rng))));
    s += w;
  }
}

// Facades around a rectangle [lo, hi] (a city block, or the inside of a ring of buildings).
void AddFacadeRect(const Vector2d& lo, const Vector2d& hi, double tpm, std::mt19937_64* rng,
                   std::vector<SceneQuad>* quads) {
  const Vector2d c1(hi.x(), lo.y()), c3(lo.x(), hi.y());
  AddFacadeRow(lo, c1, tpm, rng, quads);
  AddFacadeRow(c1, hi, tpm, rng, quads);
  AddFacadeRow(hi, c3, tpm, rng, quads);
  AddFacadeRow(c3, lo, tpm, rng, quads);
}

// Control points of a rectangle with rounded corners at height z, counter-clockwise, evenly
// spaced along the curve (about every spacing metres) so the Catmull-Rom spline through them has no kinks.
std::vector<Vector3d> RoundedRect(const Vector2d& lo, const Vector2d& hi, double radius, double z,
                                  double spacing = 0.5) {
  const double w = hi.x() - lo.x() - 2 * radius, h = hi.y() - lo.y() - 2 * radius;
  const double arc = kPi / 2 * radius;
  // Pieces in order: bottom side (+x), corner, right side (+y), corner, top (-x), corner, left (-y), corner.
  const double piece[8] = {w, arc, h, arc, w, arc, h, arc};
  double perimeter = 0;
  for (double p : piece) perimeter += p;
  const int n = std::max(16, static_cast<int>(perimeter / spacing));
  const Vector2d centres[4] = {{hi.x() - radius, lo.y() + radius},
                               {hi.x() - radius, hi.y() - radius},
                               {lo.x() + radius, hi.y() - radius},
                               {lo.x() + radius, lo.y() + radius}};
  const Vector2d side_start[4] = {
      {lo.x() + radius, lo.y()}, {hi.x(), lo.y() + radius}, {hi.x() - radius, hi.y()}, {lo.x(), hi.y() - radius}};
  const Vector2d side_dir[4] = {{1, 0}, {0, 1}, {-1, 0}, {0, -1}};
  std::vector<Vector3d> pts;
  for (int k = 0; k < n; ++k) {
    double s = perimeter * k / n;
    int i = 0;
    while (i < 7 && s > piece[i]) s -= piece[i++];
    const int side = i / 2;
    Vector2d p;
    if (i % 2 == 0) {
      p = side_start[side] + s * side_dir[side];
    } else {
      const double a = -kPi / 2 + side * kPi / 2 + s / radius;
      p = centres[side] + radius * Vector2d(std::cos(a), std::sin(a));
    }
    pts.emplace_back(p.x(), p.y(), z);
  }
  return pts;
}

std::vector<Vector3d> Ellipse(const Vector2d& centre, double rx, double ry, double z, int n) {
  std::vector<Vector3d> pts;
  for (int k = 0; k < n; ++k) {
    const double a = 2 * kPi * k / n;
    pts.emplace_back(centre.x() + rx * std::cos(a), centre.y() + ry * std::sin(a), z);
  }
  return pts;
}

SceneDescription Room() {
  SceneDescription s;
  s.name = "room";
  s.world_seed = 101;
  const double tpm = 128;
  AddRoom({0, 0, 0}, {10, 8, 3}, tpm, &s.quads);
  AddBox({4.6, 3.6, 0}, {5.4, 4.4, 3}, tpm, &s.quads);    // pillar in the middle
  AddBox({0.3, 0.3, 0}, {1.5, 1.0, 1.1}, tpm, &s.quads);  // furniture along the walls
  AddBox({8.2, 0.4, 0}, {9.6, 1.2, 0.8}, tpm, &s.quads);
  AddBox({8.8, 5.5, 0}, {9.7, 7.6, 1.8}, tpm, &s.quads);
  AddBox({0.3, 6.2, 0}, {2.2, 7.7, 0.9}, tpm, &s.quads);
  AddBox({3.5, 7.3, 0}, {6.0, 7.8, 2.0}, tpm, &s.quads);
  CameraPath path;
  path.control_points = Ellipse({5, 4}, 2.9, 2.2, 1.4, 16);
  path.speed_mps = 0.6;
  path.yaw_wobble_rad = 0.12;
  path.pitch_wobble_rad = 0.05;
  path.height_wobble_m = 0.15;
  s.agents.push_back(path);
  s.default_duration_s = 60;
  return s;
}

SceneDescription Corridor() {
  SceneDescription s;
  s.name = "corridor";
  s.world_seed = 202;
  const double tpm = 96, h = 2.8;
  // A ring corridor 4 m wide around a 22 m x 8 m core, like one floor of a building.
  AddRoom({0, 0, 0}, {30, 16, h}, tpm, &s.quads);
  AddBox({4, 4, 0}, {26, 12, h}, tpm, &s.quads);
  std::mt19937_64 rng(s.world_seed);
  std::uniform_real_distribution<double> depth(0.25, 0.6), width(0.6, 1.6), height(0.8, h);
  // Cabinets and door frames against the outer wall give depth variation.
  for (double x = 3; x < 27; x += 5.5) {
    const double d = depth(rng), w = width(rng), z = height(rng);
    AddBox({x, 0, 0}, {x + w, d, z}, tpm, &s.quads);
    AddBox({x + 2, 16 - d, 0}, {x + 2 + w, 16, height(rng)}, tpm, &s.quads);
  }
  CameraPath path;
  path.control_points = RoundedRect({2, 2}, {28, 14}, 1.5, 1.5);
  path.speed_mps = 1.2;
  path.yaw_wobble_rad = 0.15;
  path.pitch_wobble_rad = 0.04;
  path.height_wobble_m = 0.1;
  s.agents.push_back(path);
  s.default_duration_s = 70;
  return s;
}

CameraPath StreetPath(const Vector2d& lo, const Vector2d& hi, double start_s) {
  CameraPath path;
  path.control_points = RoundedRect(lo, hi, 6, 1.6);
  path.speed_mps = 5.0;
  path.start_s = start_s;
  path.yaw_wobble_rad = 0.05;
  path.pitch_wobble_rad = 0.02;
  path.height_wobble_m = 0.05;
  return path;
}

SceneDescription Street() {
  SceneDescription s;
  s.name = "street";
  s.world_seed = 303;
  const double tpm = 40;
  std::mt19937_64 rng(s.world_seed);
  // A block 60 m x 40 m inside a ring road 12 m wide lined with buildings on both sides.
  s.quads.push_back(Quad({-20, -20, 0}, {100, 0, 0}, {0, 80, 0}, tpm * 0.5, 0.7f));  // ground
  AddFacadeRect({6, 6}, {54, 34}, tpm, &rng, &s.quads);
  AddFacadeRect({-6, -6}, {66, 46}, tpm, &rng, &s.quads);
  s.agents.push_back(StreetPath({0, 0}, {60, 40}, 0));
  s.default_duration_s = 60;
  s.default_baseline_m = 0.5;
  return s;
}

SceneDescription Town() {
  SceneDescription s;
  s.name = "town";
  s.world_seed = 404;
  const double tpm = 40;
  std::mt19937_64 rng(s.world_seed);
  // 3 x 2 blocks of 40 m x 30 m on a grid of 10 m roads; centrelines at x = 0,50,100,150
  // and y = 0,40,80. Three agents each loop around two blocks; their loops share roads.
  s.quads.push_back(Quad({-15, -15, 0}, {180, 0, 0}, {0, 110, 0}, tpm * 0.5, 0.7f));
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 2; ++j)
      AddFacadeRect({50.0 * i + 6, 40.0 * j + 6}, {50.0 * i + 44, 40.0 * j + 34}, tpm, &rng, &s.quads);
  AddFacadeRect({-6, -6}, {156, 86}, tpm, &rng, &s.quads);
  s.agents.push_back(StreetPath({0, 0}, {100, 40}, 0));    // blocks (0,0),(1,0)
  s.agents.push_back(StreetPath({50, 0}, {150, 40}, 60));  // blocks (1,0),(2,0)
  // Blocks (0,1),(1,1), driven clockwise: the road it shares with agents 0 and 1 (y = 40) is then
  // driven in their direction, as a forward camera recognizes a place only when seen the same way.
  CameraPath third = StreetPath({0, 40}, {100, 80}, 120);
  std::reverse(third.control_points.begin(), third.control_points.end());
  s.agents.push_back(third);
  s.default_duration_s = 90;
  s.default_baseline_m = 0.5;
  return s;
}

Vector3d Lift(const Vector2d& p, double z) {
  return {p.x(), p.y(), z};
}

// Sides of a box standing at ground position centre, turned by yaw, from z0 to z0 + height; its
// top and bottom faces only when asked (the ones a camera can see).
void AddTurnedBox(const Vector2d& centre, double yaw, double length, double width, double z0, double height, double tpm,
                  float brightness, bool top, bool bottom, std::vector<SceneQuad>* quads) {
  const Vector2d x(std::cos(yaw), std::sin(yaw)), y(-x.y(), x.x());
  const Vector3d o = Lift(centre - 0.5 * length * x - 0.5 * width * y, z0);
  const Vector3d L = Lift(length * x, 0), W = Lift(width * y, 0), Z(0, 0, height);
  quads->push_back(Quad(o, L, Z, tpm, 0.9f * brightness));
  quads->push_back(Quad(o + W, L, Z, tpm, brightness));
  quads->push_back(Quad(o, W, Z, tpm, 0.8f * brightness));
  quads->push_back(Quad(o + L, W, Z, tpm, 1.1f * brightness));
  if (top) quads->push_back(Quad(o + Z, L, W, tpm, 1.15f * brightness));
  if (bottom) quads->push_back(Quad(o, L, W, tpm, 0.6f * brightness));
}

// A closed polyline with arc length: where the road, its markings and its surroundings go.
class Centreline {
 public:
  explicit Centreline(const std::vector<Vector3d>& points) {
    for (const Vector3d& p : points) points_.push_back(p.head<2>());
    points_.push_back(points_.front());
    arc_.assign(points_.size(), 0.0);
    for (size_t i = 1; i < points_.size(); ++i) arc_[i] = arc_[i - 1] + (points_[i] - points_[i - 1]).norm();
  }
  [[nodiscard]] double length() const { return arc_.back(); }
  [[nodiscard]] Vector2d At(double s) const {
    s = std::fmod(s, length());
    if (s < 0) s += length();
    const size_t i = std::min<size_t>(std::upper_bound(arc_.begin(), arc_.end(), s) - arc_.begin(), arc_.size() - 1);
    const size_t j = i == 0 ? 0 : i - 1;
    const double span = arc_[i] - arc_[j];
    return points_[j] + (span > 0 ? (s - arc_[j]) / span : 0.0) * (points_[i] - points_[j]);
  }
  [[nodiscard]] Vector2d Tangent(double s) const { return (At(s + 1) - At(s - 1)).normalized(); }
  [[nodiscard]] Vector2d Left(double s) const {
    const Vector2d t = Tangent(s);
    return {-t.y(), t.x()};
  }
  [[nodiscard]] double Heading(double s) const {
    const Vector2d t = Tangent(s);
    return std::atan2(t.y(), t.x());
  }
  // The point at lateral offset (positive to the left of the direction of travel).
  [[nodiscard]] Vector2d Offset(double s, double lateral) const { return At(s) + lateral * Left(s); }

 private:
  std::vector<Vector2d> points_;
  std::vector<double> arc_;
};

// A quad along the road from s0 to s1 between lateral offsets lo and hi: flat at height z, or
// (height > 0) a vertical wall at lateral offset lo. Lengthened where the road turns so that
// neighbouring pieces overlap instead of leaving wedges.
SceneQuad RoadPiece(const Centreline& road, double s0, double s1, double lo, double hi, double z, double height,
                    double tpm, float brightness, TextureStyle style) {
  const double mid = 0.5 * (s0 + s1);
  const Vector2d t = road.Tangent(mid), n = road.Left(mid);
  const double turn = std::abs(std::remainder(road.Heading(s1) - road.Heading(s0), 2 * kPi));
  const double half = 0.5 * (s1 - s0) + 0.05 + 0.5 * turn * std::max(std::abs(lo), std::abs(hi));
  const Vector3d origin = Lift(road.At(mid) - half * t + lo * n, z);
  SceneQuad q = height > 0 ? Quad(origin, Lift(2 * half * t, 0), Vector3d(0, 0, height), tpm, brightness)
                           : Quad(origin, Lift(2 * half * t, 0), Lift((hi - lo) * n, 0), tpm, brightness);
  q.style = style;
  return q;
}

// A tree-like box: a trunk under a crown whose underside the camera sees.
void AddTree(const Vector2d& at, double height, double crown, double tpm, float brightness, double yaw,
             std::vector<SceneQuad>* quads) {
  AddTurnedBox(at, yaw, 0.2 + 0.04 * height, 0.2 + 0.04 * height, 0, 0.35 * height, tpm, 0.55f, false, false, quads);
  AddTurnedBox(at, yaw, crown, crown * 0.85, 0.3 * height, 0.7 * height, tpm, brightness, true, true, quads);
}

// A moving vehicle: its body in the vehicle frame, keyed along a lane of the road at speed_mps
// (negative: against the direction of travel), repeating once per lap.
SceneMover Vehicle(const Centreline& road, double lateral, double speed_mps, double start_s, int kind,
                   float brightness) {
  SceneMover v;
  constexpr double kTpm = 48;
  if (kind == 0) {  // car
    AddTurnedBox({0, 0}, 0, 4.4, 1.8, 0.25, 0.8, kTpm, brightness, true, false, &v.quads);
    AddTurnedBox({-0.3, 0}, 0, 2.4, 1.6, 1.05, 0.5, kTpm, 0.8f * brightness, true, false, &v.quads);
  } else if (kind == 1) {  // van
    AddTurnedBox({0, 0}, 0, 5.2, 2.0, 0.3, 2.1, kTpm, brightness, true, false, &v.quads);
  } else {  // truck: cab and trailer
    AddTurnedBox({5.4, 0}, 0, 2.2, 2.5, 0.4, 2.8, kTpm, brightness, true, false, &v.quads);
    AddTurnedBox({-1.5, 0}, 0, 10.5, 2.55, 1.0, 3.0, kTpm, 0.9f * brightness, true, true, &v.quads);
  }
  v.period_s = road.length() / std::abs(speed_mps);
  const int keys = static_cast<int>(std::ceil(v.period_s / 0.25));
  for (int k = 0; k < keys; ++k) {
    const double t = v.period_s * k / keys, s = start_s + speed_mps * t;
    v.keys.push_back({t, Lift(road.Offset(s, lateral), 0), road.Heading(s) + (speed_mps < 0 ? kPi : 0.0)});
  }
  return v;
}

SceneDescription Highway() {
  SceneDescription s;
  s.name = "highway";
  s.world_seed = 505;
  s.default_width = 1241;  // KITTI's image size and focal length
  s.default_height = 376;
  s.default_fx = 718;
  s.default_frame_rate_hz = 10;
  s.default_baseline_m = 0.54;
  s.default_duration_s = 60;
  s.dynamic_distance_m = 10;
  std::mt19937_64 rng(s.world_seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  auto uniform = [&](double a, double b) { return a + (b - a) * unit(rng); };

  // A 3.8 km loop: 750 m straights and 350 m radius curves, driven counter-clockwise at 25 m/s
  // (60 s covers 40% of it). Lateral offsets are from the camera's lane, positive to the left:
  // our carriageway has lanes at -3.75, 0, 3.75; the median barrier is at 7.2; oncoming
  // traffic uses lanes at 10.675, 14.425, 18.175.
  CameraPath path;
  path.control_points = RoundedRect({0, 0}, {1450, 750}, 350, 1.65, 2.0);
  path.speed_mps = 25;
  path.yaw_wobble_rad = 0.01;
  path.pitch_wobble_rad = 0.006;
  path.height_wobble_m = 0.02;
  const Centreline road(path.control_points);
  const double length = road.length();
  s.agents.push_back(path);

  // Road surface in 20 m pieces at alternating heights (overlaps resolve without z-fighting);
  // ground beneath so that no gap shows the sky.
  const int pieces = static_cast<int>(std::ceil(length / 20));
  for (int k = 0; k < pieces; ++k) {
    const double s0 = length * k / pieces, s1 = length * (k + 1) / pieces, lift = 0.004 * (k % 2);
    s.quads.push_back(RoadPiece(road, s0, s1, -8.8, 7.5, lift, 0, 16, 1.0f, TextureStyle::kAsphalt));
    s.quads.push_back(RoadPiece(road, s0, s1, 7.0, 23.0, 0.002 + lift, 0, 8, 1.0f, TextureStyle::kAsphalt));
    s.quads.push_back(RoadPiece(road, s0, s1, 7.2, 7.2, 0, 0.9, 24, 0.85f, TextureStyle::kShapes));  // median
  }
  for (int k = 0, n = static_cast<int>(std::ceil(length / 40)); k < n; ++k) {
    const double s0 = length * k / n, s1 = length * (k + 1) / n;
    s.quads.push_back(RoadPiece(road, s0, s1, -45, -8.0, -0.02, 0, 4, 0.7f, TextureStyle::kShapes));  // verges
    s.quads.push_back(RoadPiece(road, s0, s1, 22.0, 60, -0.02, 0, 4, 0.7f, TextureStyle::kShapes));
  }
  for (double x = -700; x < 2150; x += 285)  // fields
    for (double y = -700; y < 1450; y += 269)
      s.quads.push_back(Quad({x, y, -0.06}, {285, 0, 0}, {0, 269, 0}, 1.0, static_cast<float>(uniform(0.5, 0.75))));

  // Markings: 6 m dashes every 18 m between lanes, solid lines at the carriageway edges.
  for (double lateral : {-1.875, 1.875, 12.55, 16.3})
    for (double s0 = 0; s0 + 6 < length; s0 += 18)
      s.quads.push_back(
          RoadPiece(road, s0, s0 + 6, lateral - 0.075, lateral + 0.075, 0.012, 0, 24, 1.0f, TextureStyle::kPaint));
  for (int k = 0, n = static_cast<int>(std::ceil(length / 10)); k < n; ++k) {
    const double s0 = length * k / n, s1 = length * (k + 1) / n;
    for (double lateral : {-5.625, 5.625, 8.8, 20.05})
      s.quads.push_back(
          RoadPiece(road, s0, s1, lateral - 0.12, lateral + 0.12, 0.012, 0, 24, 1.0f, TextureStyle::kPaint));
  }

  // Noise barriers: a few stretches of 3.5 m walls close to the road.
  for (int side : {-1, 1}) {
    for (double s0 = uniform(300, 900); s0 < length - 300; s0 += uniform(900, 1600)) {
      const double stretch = uniform(100, 250), lateral = side < 0 ? -12.5 : 25.0;
      const float light = static_cast<float>(uniform(0.75, 1.0));
      for (double a = s0; a < s0 + stretch; a += 25)
        s.quads.push_back(RoadPiece(road, a, a + 25, lateral, lateral, 0, 3.5, 20, light, TextureStyle::kShapes));
    }
  }

  // Roadside objects in three bands, sparse near the road and denser far away; hills behind.
  struct Band {
    double near, far, spacing;
  };
  enum class Thing { kTrees, kBillboard, kWall, kBuilding };
  auto pick = [&](int band) {  // near: trees and billboards; then buildings, more trees, walls
    const double x = unit(rng);
    if (band == 0) return x < 0.75 ? Thing::kTrees : Thing::kBillboard;
    if (band == 1)
      return x < 0.35 ? Thing::kTrees : x < 0.45 ? Thing::kBillboard : x < 0.55 ? Thing::kWall : Thing::kBuilding;
    return x < 0.45 ? Thing::kTrees : Thing::kBuilding;
  };
  for (int side : {-1, 1}) {
    const double edge = side < 0 ? 15.0 : 28.0;  // beyond the hard shoulder / the oncoming carriageway
    const Band bands[] = {{edge, 40, 140}, {40, 100, 20}, {100, 200, 14}};
    for (int b = 0; b < 3; ++b) {
      const Band& band = bands[b];
      for (double at = uniform(0, band.spacing); at < length; at += band.spacing * uniform(0.5, 1.5)) {
        const Thing thing = pick(b);
        const double heading = road.Heading(at);
        if (thing == Thing::kTrees) {
          // A group of trees.
          const int trees = 1 + static_cast<int>(unit(rng) * (b == 0 ? 3 : 6));
          const double lateral = side * uniform(band.near + 4, band.far);
          const double tpm = std::clamp(360 / std::abs(lateral), 2.5, 24.0);
          for (int k = 0; k < trees; ++k) {
            const double h = b == 0 ? uniform(4, 9) : uniform(7, 17);
            const double l = side * std::max(band.near + 3, std::abs(lateral) + uniform(-8, 8));
            const Vector2d where = road.Offset(at + uniform(-12, 12), l);
            const double crown = uniform(0.35, 0.6) * h;
            const float light = static_cast<float>(uniform(0.45, 0.7));
            AddTree(where, h, crown, tpm, light, uniform(0, kPi), &s.quads);
          }
        } else if (thing == Thing::kBillboard) {
          // A billboard on two poles, turned towards the traffic.
          const double w = uniform(6, 10), h = uniform(3, 4.5), z = uniform(4, 7);
          const double lateral = side * uniform(band.near + 2, std::min(band.far, band.near + 25));
          const double yaw = heading + side * uniform(1.0, 1.3);
          const Vector2d c = road.Offset(at, lateral), x(std::cos(yaw), std::sin(yaw));
          const double tpm = std::clamp(600 / std::abs(lateral), 4.0, 24.0);
          s.quads.push_back(
              Quad(Lift(c - 0.5 * w * x, z), Lift(w * x, 0), {0, 0, h}, tpm, static_cast<float>(uniform(0.9, 1.2))));
          for (double end : {-0.35, 0.35})
            AddTurnedBox(c + end * w * x, yaw, 0.35, 0.35, 0, z, tpm, 0.7f, false, false, &s.quads);
        } else if (thing == Thing::kWall) {
          // A long wall along the road.
          const double w = uniform(30, 80), h = uniform(2, 3.5);
          const double lateral = side * uniform(band.near + 2, band.far), yaw = heading + uniform(-0.1, 0.1);
          AddTurnedBox(road.Offset(at, lateral), yaw, w, 0.4, 0, h, std::clamp(360 / std::abs(lateral), 2.5, 16.0),
                       static_cast<float>(uniform(0.7, 1.0)), false, false, &s.quads);
        } else {
          // A building: blocks of flats, offices, warehouses.
          const double w = uniform(15, 50), d = uniform(10, 25), h = b == 1 ? uniform(8, 28) : uniform(10, 35);
          const double lateral = side * std::max(band.near + 0.5 * std::hypot(w, d), uniform(band.near, band.far));
          const double yaw = heading + uniform(-0.3, 0.3);
          AddTurnedBox(road.Offset(at, lateral), yaw, w, d, 0, h, std::clamp(360 / std::abs(lateral), 2.0, 20.0),
                       static_cast<float>(uniform(0.7, 1.15)), false, false, &s.quads);
        }
      }
    }
    // Hills: slopes rising away from the road behind everything else.
    for (double at = uniform(0, 200); at < length; at += uniform(150, 260)) {
      const Vector2d n = side * road.Left(at), t = road.Tangent(at);
      const double lateral = uniform(150, 230), w = uniform(200, 400), h = uniform(50, 110);
      const double run = side > 0 ? std::min(uniform(100, 200), 370 - lateral) : uniform(100, 200);  // inside the loop
      const Vector2d foot = road.Offset(at, side * lateral) - 0.5 * w * t;
      s.quads.push_back(
          Quad(Lift(foot, -0.03), Lift(w * t, 0), Lift(run * n, h), 2.0, static_cast<float>(uniform(0.55, 0.8))));
    }
  }

  // Traffic at 17-33 m/s both ways; vehicles sharing a lane share a speed so they never meet.
  struct Traffic {
    double lateral, speed, start_s;
    int kind;  // 0 car, 1 van, 2 truck
  };
  const Traffic traffic[] = {
      {-3.75, 20, 120, 2},    {-3.75, 20, 250, 1},   {-3.75, 20, 1900, 2},   {3.75, 31, -100, 0},
      {3.75, 31, -300, 0},    {3.75, 31, 1500, 1},   {10.675, -30, 300, 0},  {10.675, -30, 1500, 0},
      {10.675, -30, 2700, 1}, {14.425, -26, 900, 1}, {14.425, -26, 2100, 0}, {18.175, -21, 600, 2},
      {18.175, -21, 2400, 2},
  };
  for (const Traffic& v : traffic)
    s.movers.push_back(Vehicle(road, v.lateral, v.speed, v.start_s, v.kind, static_cast<float>(uniform(0.6, 1.2))));
  return s;
}

// An open shelf against a wall between lo and hi: side panels, boards and blocks of books or
// boxes on each board. The shallow horizontal axis is its depth.
void AddShelf(const Vector3d& lo, const Vector3d& hi, int boards, double tpm, std::mt19937_64* rng,
              std::vector<SceneQuad>* quads) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const bool along_x = hi.x() - lo.x() > hi.y() - lo.y();
  const int a = along_x ? 0 : 1, b = 1 - a;  // long axis, depth axis
  auto box = [&](double a0, double a1, double b0, double b1, double z0, double z1, float light) {
    Vector3d p = lo, q = hi;
    p[a] = a0, q[a] = a1, p[b] = b0, q[b] = b1, p.z() = z0, q.z() = z1;
    const size_t first = quads->size();
    AddBox(p, q, tpm, quads);
    for (size_t i = first; i < quads->size(); ++i) (*quads)[i].brightness *= light;
  };
  const double board = 0.025, panel = 0.03, pitch = (hi.z() - lo.z()) / boards;
  box(lo[a], lo[a] + panel, lo[b], hi[b], lo.z(), hi.z(), 0.9f);
  box(hi[a] - panel, hi[a], lo[b], hi[b], lo.z(), hi.z(), 0.9f);
  for (int k = 0; k < boards; ++k) {
    const double z = lo.z() + k * pitch + 0.05;
    box(lo[a] + panel, hi[a] - panel, lo[b], hi[b], z - board, z, 1.0f);
    for (double x = lo[a] + panel + 0.02; x < hi[a] - panel - 0.1;) {
      const double w = std::min(0.08 + 0.35 * unit(*rng), hi[a] - panel - x);
      const double h = (0.45 + 0.45 * unit(*rng)) * (pitch - board - 0.03);
      const double depth = (0.55 + 0.4 * unit(*rng)) * (hi[b] - lo[b]);
      const double back = hi[b] - lo[b] - depth;  // books stand at the front or the back of the board
      const double b0 = unit(*rng) < 0.5 ? lo[b] : lo[b] + back;
      box(x, x + w, b0, b0 + depth, z, z + h, static_cast<float>(0.6 + 0.6 * unit(*rng)));
      x += w + 0.1 * unit(*rng) * unit(*rng);
    }
  }
}

SceneDescription Handheld() {
  SceneDescription s;
  s.name = "handheld";
  s.world_seed = 606;
  s.default_frame_rate_hz = 30;
  s.default_duration_s = 60;
  s.default_baseline_m = 0.1;
  s.exposure.exposure_s = 0.003;  // 4 px of blur at 3 rad/s
  s.exposure.gain_wobble = 0.1;
  s.exposure.gain_step_every_s = 8;
  std::mt19937_64 rng(s.world_seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double wall_tpm = 220, tpm = 360;
  // An office 6 m x 4.8 m x 2.6 m; everything the camera passes is 0.5-3 m away.
  AddRoom({0, 0, 0}, {6, 4.8, 2.6}, wall_tpm, &s.quads);
  AddBox({2.25, 2.05, 0}, {3.75, 2.75, 0.75}, tpm, &s.quads);  // table in the middle, things on it
  AddBox({2.5, 2.2, 0.75}, {2.85, 2.45, 0.8}, tpm, &s.quads);
  AddBox({3.2, 2.25, 0.75}, {3.6, 2.5, 0.77}, tpm, &s.quads);
  AddBox({3.0, 2.5, 0.75}, {3.1, 2.6, 0.86}, tpm, &s.quads);
  AddBox({2.35, 2.55, 0.75}, {2.5, 2.7, 1.05}, tpm, &s.quads);
  AddBox({0.8, 0.0, 0}, {2.4, 0.7, 0.75}, tpm, &s.quads);  // desk, monitor, lamp, chair
  AddBox({1.3, 0.12, 0.75}, {1.9, 0.19, 1.2}, tpm, &s.quads);
  AddBox({2.15, 0.1, 0.75}, {2.25, 0.2, 1.15}, tpm, &s.quads);
  AddBox({1.2, 0.8, 0}, {1.65, 1.2, 0.5}, tpm, &s.quads);
  AddBox({1.2, 1.15, 0.5}, {1.65, 1.25, 0.95}, tpm, &s.quads);
  AddBox({3.4, 0.0, 0}, {4.8, 0.4, 0.9}, tpm, &s.quads);  // low cabinet, west cabinet
  AddBox({0.0, 3.0, 0}, {0.45, 4.4, 1.1}, tpm, &s.quads);
  AddBox({0.1, 3.2, 1.1}, {0.35, 3.55, 1.4}, tpm, &s.quads);
  AddBox({5.35, 4.3, 0}, {5.8, 4.75, 1.3}, tpm, &s.quads);  // plants in two corners
  AddBox({0.15, 0.15, 0}, {0.6, 0.6, 1.0}, tpm, &s.quads);
  AddShelf({5.65, 1.2, 0}, {6.0, 3.6, 2.1}, 5, tpm, &rng, &s.quads);  // bookcase, open shelf
  AddShelf({2.0, 4.45, 0}, {4.0, 4.8, 1.8}, 4, tpm, &rng, &s.quads);
  s.quads.push_back(Quad({0.01, 0.9, 0.9}, {0, 1.6, 0}, {0, 0, 1.2}, tpm, 1.2f));  // whiteboard, posters
  s.quads.push_back(Quad({1.0, 0.01, 1.4}, {0.7, 0, 0}, {0, 0, 0.7}, tpm, 1.05f));
  s.quads.push_back(Quad({4.3, 4.79, 1.2}, {0.9, 0, 0}, {0, 0, 0.7}, tpm, 0.95f));

  // Walking round the table at 0.6 m/s (a lap every 14 s), with quick glances: turns of
  // 0.6-1.2 rad left/right or tilts up/down, every third at a peak rate of 2.5 rad/s, the others
  // at 1.4-2.4 rad/s, on top of the path's own turning (up to 0.75 rad/s).
  CameraPath path;
  path.control_points = Ellipse({3.0, 2.4}, 1.5, 1.1, 1.35, 24);
  path.speed_mps = 0.6;
  path.yaw_wobble_rad = 0.15;
  path.pitch_wobble_rad = 0.08;
  path.height_wobble_m = 0.04;
  path.roll_wobble_rad = 0.05;
  for (double t = 1.5; t < 600;) {
    CameraGlance g;
    g.start_s = t;
    const double peak = path.glances.size() % 3 == 0 ? 2.5 : 1.4 + 1.0 * unit(rng);
    if (unit(rng) < 0.6) {
      const double amplitude = 0.6 + 0.6 * unit(rng);
      g.yaw_rad = unit(rng) < 0.5 ? amplitude : -amplitude;
    } else {
      g.pitch_rad = unit(rng) < 0.65 ? -(0.35 + 0.35 * unit(rng)) : 0.25 + 0.25 * unit(rng);
    }
    g.turn_s = (std::abs(g.yaw_rad) + std::abs(g.pitch_rad)) * kPi / (2 * peak);
    g.hold_s = 0.3 + 0.9 * unit(rng);
    path.glances.push_back(g);
    t += 2 * g.turn_s + g.hold_s + 0.8 + 1.7 * unit(rng);
  }
  s.agents.push_back(path);
  return s;
}

}  // namespace

std::vector<std::string> SyntheticSceneNames() {
  return {"room", "corridor", "street", "town", "highway", "handheld"};
}

SceneDescription MakeScene(const std::string& name) {
  if (name == "room") return Room();
  if (name == "corridor") return Corridor();
  if (name == "street") return Street();
  if (name == "town") return Town();
  if (name == "highway") return Highway();
  if (name == "handheld") return Handheld();
  std::string known;
  for (const auto& n : SyntheticSceneNames()) known += (known.empty() ? "" : ", ") + n;
  Fail("unknown synthetic scene '", name, "' (known: ", known, ")");
}

}  // namespace flatslam
