// Ray marching through the occupancy grid (nerfexp.nerf.marching.GridMarchSampler) as a CPU loop per ray: the
// intervals [t, t + dt] of a ray's march whose midpoints lie in occupied cells, packed ray after ray, at most
// ``max_samples`` per ray. The same intervals as the torch path (``marching.march_torch``), bit for bit: a step's
// midpoint is looked up exactly as ``nerfexp.nerf.occupancy.cell_indices`` computes its cell, and an empty cell is
// crossed by jumping over the steps whose midpoints the cell holds, never over one it might not (the lookup decides).
//
// The march of ray b (origin o, direction d, both float32; t in units of d):
// - without a cone angle and without a contraction, from t0 = max(near, where the ray enters the box) to
//   t1 = min(far, where it leaves), steps of one length dt (``base``, in units of t), the k-th interval
//   [t0 + (k + offset) dt, t0 + (k + 1 + offset) dt] (cut at t1), offset in [0, 1) the ray's jitter;
// - with a cone angle c each step max(dt, c t) from the last, the first starting at t0 + offset max(dt, c t0); with
//   a contraction too, the positions looked up contracted, and t0, t1 are near and far (every point lies in the box).
// Inputs: origins, directions, [B, 3], near, far, offsets, base [B] float32 (base: the step's length in units of t,
// worked out by the caller, whose |d| the torch path shares); occupied [R^3] bool (uint8); the box [2, 3]
// float32; contraction: centre [3], radius and the norm (0: none, 1: l2, 2: l-infinity). Contiguous CPU tensors of
// those types and sizes, or a one-line error (``check_inputs``).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace {

struct Grid {
  const uint8_t* occupied;
  int64_t resolution;
  float lower[3], upper[3];
};

struct Contraction {
  int norm;  // 0: none, 1: l2 (mip-NeRF 360's ball), 2: l-infinity (nerfacto's box)
  float centre[3];
  float radius;
};

// nerfexp.nerf.contraction.contract of (p - centre) / radius, in float32: inside the inner region unchanged, beyond
// it (2 - 1 / |x|) x / |x|, the direction taken after dividing by the largest coordinate (as the torch path does).
inline void contract(const Contraction& c, const float p[3], float out[3]) {
  float x[3];
  for (int a = 0; a < 3; ++a) x[a] = (p[a] - c.centre[a]) / c.radius;
  float m = std::max(std::fabs(x[0]), std::max(std::fabs(x[1]), std::fabs(x[2])));
  if (!(m > 0)) {
    for (int a = 0; a < 3; ++a) out[a] = x[a];
    return;
  }
  float scaled[3] = {x[0] / m, x[1] / m, x[2] / m};
  float scaled_norm = c.norm == 1 ? std::sqrt(scaled[0] * scaled[0] + scaled[1] * scaled[1] + scaled[2] * scaled[2])
                                  : std::max(std::fabs(scaled[0]), std::max(std::fabs(scaled[1]), std::fabs(scaled[2])));
  float length = m * scaled_norm;
  if (length <= 1.0f) {
    for (int a = 0; a < 3; ++a) out[a] = x[a];
    return;
  }
  float shrink = 2.0f - 1.0f / length;
  for (int a = 0; a < 3; ++a) out[a] = shrink * (scaled[a] / scaled_norm);
}

// The cell (i, j, k) holding the point p, as cell_indices finds it (unit = (p - lower) / (upper - lower), the cell
// floor(unit R) clamped to [0, R - 1]); false where p lies outside the box (a unit coordinate outside [0, 1), NaN).
inline bool cell_of(const Grid& g, const float p[3], int64_t ijk[3]) {
  for (int a = 0; a < 3; ++a) {
    float unit = (p[a] - g.lower[a]) / (g.upper[a] - g.lower[a]);
    if (!(unit >= 0.0f && unit < 1.0f)) return false;
    int64_t i = static_cast<int64_t>(std::floor(unit * static_cast<float>(g.resolution)));
    ijk[a] = std::min(std::max(i, int64_t(0)), g.resolution - 1);
  }
  return true;
}

inline bool occupied(const Grid& g, const int64_t ijk[3]) {
  return g.occupied[(ijk[0] * g.resolution + ijk[1]) * g.resolution + ijk[2]] != 0;
}

inline bool occupied_at(const Grid& g, const float p[3]) {
  int64_t ijk[3];
  return cell_of(g, p, ijk) && occupied(g, ijk);
}

// Where along o + t d (t in [lo, hi]) the ray is inside the box, as [enter, leave]; enter > leave where it misses.
inline void box_span(const Grid& g, const float o[3], const float d[3], float& enter, float& leave) {
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0f) {
      if (o[a] < g.lower[a] || o[a] >= g.upper[a]) {
        enter = 1.0f;
        leave = 0.0f;
        return;
      }
      continue;
    }
    float t_a = (g.lower[a] - o[a]) / d[a], t_b = (g.upper[a] - o[a]) / d[a];
    enter = std::max(enter, std::min(t_a, t_b));
    leave = std::min(leave, std::max(t_a, t_b));
  }
}

// About where o + t d leaves the cell (i, j, k): the nearest of its far faces along d (rounded: only a jump's target,
// which the lookups then check).
inline float cell_exit(const Grid& g, const float o[3], const float d[3], const int64_t ijk[3]) {
  float exit = std::numeric_limits<float>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0f) continue;
    float size = (g.upper[a] - g.lower[a]) / static_cast<float>(g.resolution);
    float face = g.lower[a] + static_cast<float>(d[a] > 0 ? ijk[a] + 1 : ijk[a]) * size;
    exit = std::min(exit, (face - o[a]) / d[a]);
  }
  return exit;
}

struct March {
  Grid grid;
  Contraction contraction;
  float cone_angle;  // 0: every step the same length
  int64_t max_samples;
};

// The intervals of ray (o, d) between near and far with jitter ``offset`` whose midpoints are occupied, written to
// starts / ends where they are not null; how many (at most max_samples).
int64_t march_ray(const March& m, const float o[3], const float d[3], float near, float far, float offset,
                  float base, float* starts, float* ends) {
  if (!(base > 0) || !std::isfinite(base) || !(near < far)) return 0;
  int64_t count = 0;
  auto emit = [&](float a, float b) {
    if (starts != nullptr) {
      starts[count] = a;
      ends[count] = b;
    }
    ++count;
  };
  float lo = near, hi = far;
  if (m.contraction.norm == 0) {  // the box bounds the march (a contracted scene's box holds every point)
    box_span(m.grid, o, d, lo, hi);
    if (!(lo < hi)) return 0;
  }
  if (m.cone_angle == 0.0f && m.contraction.norm == 0) {  // fixed steps through the box, empty cells jumped over
    for (int64_t k = 0; count < m.max_samples;) {
      float a = lo + (static_cast<float>(k) + offset) * base;
      if (!(a < hi)) break;
      float b = std::min(lo + (static_cast<float>(k + 1) + offset) * base, hi);
      float mid = 0.5f * (a + b);
      float p[3] = {o[0] + d[0] * mid, o[1] + d[1] * mid, o[2] + d[2] * mid};
      int64_t ijk[3];
      bool inside = cell_of(m.grid, p, ijk);
      if (inside && occupied(m.grid, ijk)) {
        emit(a, b);
        ++k;
        continue;
      }
      int64_t next = k + 1;
      if (inside) {  // jump to about the last step whose midpoint the empty cell holds, one step short of it, so
                     // that rounding never jumps over a step the lookups would keep
        float last = std::floor((cell_exit(m.grid, o, d, ijk) - lo) / base - offset - 0.5f) - 1.0f;
        if (last > static_cast<float>(next) && last < 9.0e15f) next = static_cast<int64_t>(last);
      }
      k = next;
    }
    return count;
  }
  float a = lo + offset * std::max(base, m.cone_angle * lo);
  while (a < hi && count < m.max_samples) {
    float b = std::min(a + std::max(base, m.cone_angle * a), hi);
    float mid = 0.5f * (a + b);
    float p[3] = {o[0] + d[0] * mid, o[1] + d[1] * mid, o[2] + d[2] * mid};
    bool hit;
    if (m.contraction.norm == 0) {
      hit = occupied_at(m.grid, p);
    } else {
      float c[3];
      contract(m.contraction, p, c);
      hit = occupied_at(m.grid, c);
    }
    if (hit) emit(a, b);
    if (!(b > a)) break;  // a step too small to move t (t beyond float32's resolution): the march ends
    a = b;
  }
  return count;
}

void check_inputs(const at::Tensor& origins, const at::Tensor& directions, const at::Tensor& near,
                  const at::Tensor& far, const at::Tensor& offsets, const at::Tensor& base,
                  const at::Tensor& occupied,
                  const at::Tensor& box, const at::Tensor& centre, int64_t resolution, int64_t norm,
                  int64_t max_samples) {
  for (const at::Tensor* t : {&origins, &directions, &near, &far, &offsets, &base, &box, &centre}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kFloat && t->is_contiguous(),
                "grid_march: expected contiguous float32 CPU tensors");
  }
  int64_t rays = origins.size(0);
  TORCH_CHECK(origins.dim() == 2 && origins.size(1) == 3 && directions.sizes() == origins.sizes(),
              "grid_march: origins and directions must be [B, 3]");
  TORCH_CHECK(near.dim() == 1 && near.size(0) == rays && far.sizes() == near.sizes() && offsets.sizes() == near.sizes() &&
                  base.sizes() == near.sizes(),
              "grid_march: near, far, offsets and base must be [B]");
  TORCH_CHECK(box.dim() == 2 && box.size(0) == 2 && box.size(1) == 3, "grid_march: the box must be [2, 3]");
  TORCH_CHECK(centre.dim() == 1 && centre.size(0) == 3, "grid_march: the contraction's centre must be [3]");
  TORCH_CHECK(resolution >= 1 && resolution <= 4096, "grid_march: resolution must be in [1, 4096]");
  TORCH_CHECK(occupied.device().is_cpu() && occupied.scalar_type() == at::kBool && occupied.is_contiguous() &&
                  occupied.dim() == 1 && occupied.size(0) == resolution * resolution * resolution,
              "grid_march: occupied must be a contiguous bool CPU tensor of resolution^3 cells");
  TORCH_CHECK(norm >= 0 && norm <= 2, "grid_march: norm must be 0 (none), 1 (l2) or 2 (l-infinity)");
  TORCH_CHECK(max_samples >= 1, "grid_march: max_samples must be >= 1");
}

// (t_starts [N], t_ends [N] float32, counts [B] int64): every ray's occupied intervals, ray
// after ray, each ray's in order along it.
std::vector<at::Tensor> march(const at::Tensor& origins, const at::Tensor& directions, const at::Tensor& near,
                              const at::Tensor& far, const at::Tensor& offsets, const at::Tensor& base,
                              const at::Tensor& occupied, int64_t resolution, const at::Tensor& box,
                              double cone_angle,
                              int64_t max_samples, const at::Tensor& centre, double radius, int64_t norm) {
  check_inputs(origins, directions, near, far, offsets, base, occupied, box, centre, resolution, norm, max_samples);
  TORCH_CHECK(cone_angle >= 0 && std::isfinite(cone_angle), "grid_march: cone_angle must be finite and >= 0");
  TORCH_CHECK(norm == 0 || (radius > 0 && std::isfinite(radius)), "grid_march: radius must be finite and > 0");
  March m;
  m.grid.occupied = reinterpret_cast<const uint8_t*>(occupied.data_ptr<bool>());
  m.grid.resolution = resolution;
  const float* b = box.data_ptr<float>();
  for (int a = 0; a < 3; ++a) {
    m.grid.lower[a] = b[a];
    m.grid.upper[a] = b[3 + a];
  }
  const float* c = centre.data_ptr<float>();
  m.contraction.norm = static_cast<int>(norm);
  for (int a = 0; a < 3; ++a) m.contraction.centre[a] = c[a];
  m.contraction.radius = static_cast<float>(radius);
  m.cone_angle = static_cast<float>(cone_angle);
  m.max_samples = max_samples;

  int64_t rays = origins.size(0);
  const float* o = origins.data_ptr<float>();
  const float* d = directions.data_ptr<float>();
  const float* n = near.data_ptr<float>();
  const float* f = far.data_ptr<float>();
  const float* u = offsets.data_ptr<float>();
  const float* w = base.data_ptr<float>();
  at::Tensor counts = at::zeros({rays}, origins.options().dtype(at::kLong));
  int64_t* count = counts.data_ptr<int64_t>();
  at::parallel_for(0, rays, 256, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r)
      count[r] = march_ray(m, o + 3 * r, d + 3 * r, n[r], f[r], u[r], w[r], nullptr, nullptr);
  });
  at::Tensor first = counts.cumsum(0) - counts;  // each ray's first place in the packed arrays
  int64_t total = rays == 0 ? 0 : (first[rays - 1].item<int64_t>() + count[rays - 1]);
  at::Tensor starts = at::empty({total}, origins.options());
  at::Tensor ends = at::empty({total}, origins.options());
  const int64_t* place = first.data_ptr<int64_t>();
  float* s = starts.data_ptr<float>();
  float* e = ends.data_ptr<float>();
  at::parallel_for(0, rays, 256, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r)
      march_ray(m, o + 3 * r, d + 3 * r, n[r], f[r], u[r], w[r], s + place[r], e + place[r]);
  });
  return {starts, ends, counts};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, module) {
  module.def("march", &march, "the occupied intervals of rays marched through an occupancy grid");
}
