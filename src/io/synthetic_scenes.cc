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

SceneQuad Quad(const Vector3d& origin, const Vector3d& u, const Vector3d& v, double texels_per_m,
               float brightness) {
  SceneQuad q;
  q.origin = origin;
  q.size_u = u.norm();
  q.size_v = v.norm();
  q.axis_u = u / q.size_u;
  q.axis_v = v / q.size_v;
  q.texels_per_m = texels_per_m;
  q.brightness = brightness;
  return q;
}

// Six faces of an axis-aligned box seen from inside (a room).
void AddRoom(const Vector3d& lo, const Vector3d& hi, double tpm, std::vector<SceneQuad>* quads) {
  const Vector3d d = hi - lo;
  const Vector3d X(d.x(), 0, 0), Y(0, d.y(), 0), Z(0, 0, d.z());
  quads->push_back(Quad(lo, X, Y, tpm, 0.85f));                // floor
  quads->push_back(Quad(lo + Z, X, Y, tpm, 1.0f));             // ceiling
  quads->push_back(Quad(lo, X, Z, tpm, 0.95f));                // y = lo wall
  quads->push_back(Quad(lo + Y, X, Z, tpm, 0.9f));             // y = hi wall
  quads->push_back(Quad(lo, Y, Z, tpm, 1.05f));                // x = lo wall
  quads->push_back(Quad(lo + X, Y, Z, tpm, 0.8f));             // x = hi wall
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
// spaced along the curve (about every 0.5 m) so the Catmull-Rom spline through them has no kinks.
std::vector<Vector3d> RoundedRect(const Vector2d& lo, const Vector2d& hi, double radius, double z) {
  const double w = hi.x() - lo.x() - 2 * radius, h = hi.y() - lo.y() - 2 * radius;
  const double arc = kPi / 2 * radius;
  // Pieces in order: bottom side (+x), corner, right side (+y), corner, top (-x), corner, left (-y), corner.
  const double piece[8] = {w, arc, h, arc, w, arc, h, arc};
  double perimeter = 0;
  for (double p : piece) perimeter += p;
  const int n = std::max(16, static_cast<int>(perimeter / 0.5));
  const Vector2d centres[4] = {{hi.x() - radius, lo.y() + radius},
                               {hi.x() - radius, hi.y() - radius},
                               {lo.x() + radius, hi.y() - radius},
                               {lo.x() + radius, lo.y() + radius}};
  const Vector2d side_start[4] = {{lo.x() + radius, lo.y()}, {hi.x(), lo.y() + radius},
                                  {hi.x() - radius, hi.y()}, {lo.x(), hi.y() - radius}};
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
  s.agents.push_back(StreetPath({0, 0}, {100, 40}, 0));     // blocks (0,0),(1,0)
  s.agents.push_back(StreetPath({50, 0}, {150, 40}, 60));   // blocks (1,0),(2,0)
  s.agents.push_back(StreetPath({0, 40}, {100, 80}, 120));  // blocks (0,1),(1,1)
  s.default_duration_s = 90;
  s.default_baseline_m = 0.5;
  return s;
}

}  // namespace

std::vector<std::string> SyntheticSceneNames() { return {"room", "corridor", "street", "town"}; }

SceneDescription MakeScene(const std::string& name) {
  if (name == "room") return Room();
  if (name == "corridor") return Corridor();
  if (name == "street") return Street();
  if (name == "town") return Town();
  std::string known;
  for (const auto& n : SyntheticSceneNames()) known += (known.empty() ? "" : ", ") + n;
  Fail("unknown synthetic scene '", name, "' (known: ", known, ")");
}

}  // namespace flatslam
