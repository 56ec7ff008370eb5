// The occupancy grid's lookup (nerfexp.nerf.occupancy.OccupancyGrid.occupied_at) as one fused CPU loop: for each
// point, its cell in the box and whether that cell is occupied, in one pass over the points (parallel over them),
// where the torch path (``cell_indices``) runs a dozen operators over [N, 3] tensors, each a pass and a buffer.
//
// Inputs: points [N, 3], the box [2, 3] (lower corner, upper corner), both float32 and contiguous; the grid's
// occupied cells, bool [R^3] in flat order (i R + j) R + k; R the cells per side. Output bool [N]. The arithmetic is
// the torch path's, operation for operation in float32 (the build has no fused multiply-adds): u = (p - lower) /
// (upper - lower) per axis, inside where 0 <= u < 1 on every axis (false for NaN), the cell min(floor(u R), R - 1).
// A tensor on another device (the torch path runs there), not contiguous, of another dtype or shape is a one-line
// error (``check_inputs``), never a read through a pointer this loop cannot follow.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cstdint>

namespace {

// The largest cells per side: R^3 flat indices in int64 and each cell's index exactly in float32 (R <= 2^24).
const int64_t MAX_CELLS = int64_t{1} << 20;

void check_inputs(const torch::Tensor& points, const torch::Tensor& box, const torch::Tensor& occupied,
                  int64_t resolution) {
  for (const auto& [t, name] : {std::pair{&points, "points"}, std::pair{&box, "box"}, std::pair{&occupied, "occupied"}}) {
    TORCH_CHECK(t->device().is_cpu(), "occupancy_lookup: ", name, " is on ", t->device(), ", not the CPU");
    TORCH_CHECK(t->is_contiguous(), "occupancy_lookup: ", name, " is not contiguous");
  }
  TORCH_CHECK(points.scalar_type() == torch::kFloat && box.scalar_type() == torch::kFloat,
              "occupancy_lookup: points and box must be float32, got ", points.scalar_type(), " and ",
              box.scalar_type());
  TORCH_CHECK(occupied.scalar_type() == torch::kBool, "occupancy_lookup: occupied must be bool, got ",
              occupied.scalar_type());
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "occupancy_lookup: points must be [N, 3], got ",
              points.sizes());
  TORCH_CHECK(box.sizes() == torch::IntArrayRef({2, 3}), "occupancy_lookup: box must be [2, 3], got ", box.sizes());
  TORCH_CHECK(resolution >= 1 && resolution <= MAX_CELLS, "occupancy_lookup: ", resolution,
              " cells per side: expected 1 to 2^20");
  TORCH_CHECK(occupied.dim() == 1 && occupied.size(0) == resolution * resolution * resolution,
              "occupancy_lookup: occupied must be [", resolution * resolution * resolution, "], got ",
              occupied.sizes());
}

}  // namespace

torch::Tensor occupied_at(torch::Tensor points, torch::Tensor box, torch::Tensor occupied, int64_t resolution) {
  check_inputs(points, box, occupied, resolution);
  const int64_t N = points.size(0);
  auto out = torch::empty({N}, occupied.options());
  const float* p = points.data_ptr<float>();
  const float* b = box.data_ptr<float>();
  const bool* cells = occupied.data_ptr<bool>();
  bool* o = out.data_ptr<bool>();
  const float lower[3] = {b[0], b[1], b[2]};
  const float extent[3] = {b[3] - b[0], b[4] - b[1], b[5] - b[2]};
  const float side = static_cast<float>(resolution);
  at::parallel_for(0, N, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t n = begin; n < end; ++n) {
      bool inside = true;
      int64_t index = 0;
      for (int a = 0; a < 3; ++a) {
        const float u = (p[3 * n + a] - lower[a]) / extent[a];
        inside = inside && u >= 0 && u < 1;  // false for NaN
        // u R in [0, R] inside the box (u < 1 may round up to R): its floor, the integer conversion of a
        // non-negative float, clamped to the last cell; outside the box the index is never read
        const int64_t cell = inside ? static_cast<int64_t>(u * side) : 0;
        index = index * resolution + (cell < resolution ? cell : resolution - 1);
      }
      o[n] = inside && cells[index];
    }
  });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("occupied_at", &occupied_at, "whether each point lies in an occupied cell of the grid inside its box");
}
