// The hash encoding's forward and backward (nerfexp.nerf.hashgrid.HashGridEncoding) as fused CPU loops: each
// position's 8 corners per level found, weighted and summed in one pass (forward, parallel over positions), and
// each level's table gradient accumulated in one pass over the positions (backward, parallel over levels: a
// level's entries are its own, so no two threads add to one entry, without atomics or per-thread copies), into new
// zero tensors or (``backward_into``) into the sums of earlier calls of the same backward pass.
//
// Inputs: unit positions [N, 3] in [0, 1] (float32, contiguous); dense levels as [F, n+1, n+1, n+1] volumes
// (vertex (i, j, k) of feature f at f (n+1)^3 + (i (n+1) + j) (n+1) + k), the hashed levels' table [Lh, T, F];
// the levels' cells per side. Output features [N, (Ld + Lh) F], level-major, as the torch path's. A tensor on
// another device (a GPU's: the torch path runs there), not contiguous, not float32 or of another shape, and a size
// that would index outside the storage (cells per side, table rows, features) is a one-line error
// (``check_inputs``), never a read through a pointer these loops cannot follow.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

const uint32_t PRIME_X = 1, PRIME_Y = 2654435761u, PRIME_Z = 805459861u;  // HASH_PRIMES

const int64_t BLOCK = 64;  // positions whose corners are found together, in loops the compiler vectorizes

// One level's 8 corners of ``BLOCK`` positions (at most): their offsets into the level's storage and trilinear
// weights, corner-major.
struct Corners {
  int64_t offset[8][BLOCK];
  float weight[8][BLOCK];
};

// The cells of ``count`` positions ``u`` [count, 3] at ``n`` cells per side (the last cell for u = 1), as the torch
// path computes them: scaled = u n, lower = min(floor(scaled), n - 1), frac = scaled - lower; then each corner's
// row, hashed ((i p_x xor j p_y xor k p_z) mod T: T is a power of two at most 2^32, so the products' low 32 bits
// decide it and the arithmetic is in uint32) or indexed ((i (n+1) + j) (n+1) + k, below 2^32: ``check_inputs``),
// times ``stride``, and weight (w_x w_y w_z). A position outside [0, 1] (or NaN) is clamped, never read outside the
// storage. floor(x) for 0 <= x < 2^31 is x converted to an integer (rounded toward zero) and back: the baseline x86-64 (no SSE4.1 round) makes std::floor a call of the maths library.
inline void corners_of(const float* u, int64_t count, int64_t n, bool hashed, int64_t table_size, int64_t stride,
                       Corners& c) {
  uint32_t lower[3][BLOCK];
  float frac[3][BLOCK];
  const float cells = static_cast<float>(n), last = static_cast<float>(n - 1);
  for (int a = 0; a < 3; ++a)
    for (int64_t i = 0; i < count; ++i) {
      float scaled = u[3 * i + a] * cells;
      scaled = scaled > 0 ? scaled : 0;  // in [0, n] for u in [0, 1]; any other u (NaN too) clamped into the box
      scaled = scaled < cells ? scaled : cells;
      float floor = static_cast<float>(static_cast<int32_t>(scaled));
      if (floor > last) floor = last;
      lower[a][i] = static_cast<uint32_t>(static_cast<int32_t>(floor));
      frac[a][i] = scaled - floor;
    }
  const uint32_t mask = static_cast<uint32_t>(table_size - 1), side = static_cast<uint32_t>(n + 1);
  for (int k = 0; k < 8; ++k) {
    const uint32_t bx = (k >> 2) & 1, by = (k >> 1) & 1, bz = k & 1;
    int64_t* offset = c.offset[k];
    float* weight = c.weight[k];
    if (hashed)
      for (int64_t i = 0; i < count; ++i)
        offset[i] = static_cast<int64_t>(((lower[0][i] + bx) * PRIME_X ^ (lower[1][i] + by) * PRIME_Y ^
                                          (lower[2][i] + bz) * PRIME_Z) & mask) * stride;
    else
      for (int64_t i = 0; i < count; ++i)
        offset[i] = static_cast<int64_t>(((lower[0][i] + bx) * side + lower[1][i] + by) * side + lower[2][i] + bz) *
                    stride;
    for (int64_t i = 0; i < count; ++i) {
      const float wx = bx ? frac[0][i] : 1 - frac[0][i], wy = by ? frac[1][i] : 1 - frac[1][i];
      const float wz = bz ? frac[2][i] : 1 - frac[2][i];
      weight[i] = wx * wy * wz;
    }
  }
}

// A level's storage: its first value, the distance between two rows' values and between two features'.
struct Level {
  float* data;
  int64_t n;
  bool hashed;
  int64_t row_stride;      // F for the hashed table, 1 for a dense volume
  int64_t feature_stride;  // 1 for the hashed table, (n+1)^3 for a dense volume
};

// The largest cells per side of a dense level: its (n+1)^3 vertices indexed in uint32 (``corners_of``).
const int64_t DENSE_MAX_CELLS = 1624;  // 1625^3 < 2^32 <= 1626^3
// The largest cells per side of a hashed level: float32 holds every cell's index exactly (``corners_of``).
const int64_t HASHED_MAX_CELLS = int64_t{1} << 24;
// The largest hashed table: its rows masked in uint32 (``corners_of``).
const int64_t MAX_TABLE_SIZE = int64_t{1} << 32;

// A float32 tensor on the CPU, contiguous: what data_ptr<float> and the loops' flat indices read.
void check_cpu_contiguous(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), "hash_encoding: ", name, " is on ", t.device(), ", not the CPU");
  TORCH_CHECK(t.is_contiguous(), "hash_encoding: ", name, " is not contiguous");
  TORCH_CHECK(t.scalar_type() == torch::kFloat, "hash_encoding: ", name, " is ", t.scalar_type(), ", not float32");
}

// The inputs every entry point reads: unit [N, 3]; one [F, n+1, n+1, n+1] volume per dense level (n in
// [1, DENSE_MAX_CELLS]); the hashed table [Lh, T, F] (T a power of two at most MAX_TABLE_SIZE, each level's n in
// [1, HASHED_MAX_CELLS]); F >= 1; where given, the features' gradient [N, L F]; all float32.
void check_inputs(const torch::Tensor& unit, const std::vector<torch::Tensor>& dense, const torch::Tensor& hashed,
                  const std::vector<int64_t>& dense_res, const std::vector<int64_t>& hashed_res, int64_t features,
                  const torch::Tensor* grad) {
  check_cpu_contiguous(unit, "unit");
  check_cpu_contiguous(hashed, "hashed");
  TORCH_CHECK(unit.dim() == 2 && unit.size(1) == 3, "hash_encoding: unit must be [N, 3], got ", unit.sizes());
  TORCH_CHECK(features >= 1, "hash_encoding: features per level must be >= 1, got ", features);
  TORCH_CHECK(dense.size() == dense_res.size(), "hash_encoding: ", dense.size(), " dense volumes for ",
              dense_res.size(), " dense resolutions");
  TORCH_CHECK(hashed.dim() == 3 && hashed.size(0) == static_cast<int64_t>(hashed_res.size()) &&
                  hashed.size(2) == features,
              "hash_encoding: hashed must be [", hashed_res.size(), ", T, ", features, "], got ", hashed.sizes());
  const int64_t T = hashed.size(1);
  TORCH_CHECK(hashed_res.empty() || (T >= 1 && T <= MAX_TABLE_SIZE && (T & (T - 1)) == 0),
              "hash_encoding: the hashed table's T = ", T, " rows must be a power of two in [1, 2^32]");
  for (size_t h = 0; h < hashed_res.size(); ++h)
    TORCH_CHECK(hashed_res[h] >= 1 && hashed_res[h] <= HASHED_MAX_CELLS, "hash_encoding: hashed level ", h, " has ",
                hashed_res[h], " cells per side: expected 1 to 2^24");
  for (size_t d = 0; d < dense.size(); ++d) {
    check_cpu_contiguous(dense[d], "a dense volume");
    TORCH_CHECK(dense_res[d] >= 1 && dense_res[d] <= DENSE_MAX_CELLS, "hash_encoding: dense level ", d, " has ",
                dense_res[d], " cells per side: expected 1 to ", DENSE_MAX_CELLS);
    const int64_t side = dense_res[d] + 1;
    TORCH_CHECK(dense[d].sizes() == torch::IntArrayRef({features, side, side, side}), "hash_encoding: dense level ",
                d, " must be [", features, ", ", side, ", ", side, ", ", side, "], got ", dense[d].sizes());
  }
  if (grad != nullptr) {
    check_cpu_contiguous(*grad, "grad");
    const int64_t L = static_cast<int64_t>(dense.size() + hashed_res.size());
    TORCH_CHECK(grad->dim() == 2 && grad->size(0) == unit.size(0) && grad->size(1) == L * features,
                "hash_encoding: grad must be [", unit.size(0), ", ", L * features, "], got ", grad->sizes());
  }
}

std::vector<Level> levels_of(std::vector<torch::Tensor>& dense, torch::Tensor& hashed,
                             const std::vector<int64_t>& dense_res, const std::vector<int64_t>& hashed_res) {
  std::vector<Level> levels;
  for (size_t d = 0; d < dense.size(); ++d) {
    const int64_t n = dense_res[d];
    levels.push_back({dense[d].data_ptr<float>(), n, false, 1, (n + 1) * (n + 1) * (n + 1)});
  }
  const int64_t T = hashed.size(1), F = hashed.size(2);
  for (size_t h = 0; h < hashed_res.size(); ++h)
    levels.push_back({hashed.data_ptr<float>() + static_cast<int64_t>(h) * T * F, hashed_res[h], true, F, 1});
  return levels;
}

}  // namespace

torch::Tensor hash_encoding_forward(torch::Tensor unit, std::vector<torch::Tensor> dense, torch::Tensor hashed,
                                    std::vector<int64_t> dense_res, std::vector<int64_t> hashed_res,
                                    int64_t features) {
  check_inputs(unit, dense, hashed, dense_res, hashed_res, features, nullptr);
  const int64_t N = unit.size(0), T = hashed.size(1);
  std::vector<Level> levels = levels_of(dense, hashed, dense_res, hashed_res);
  const int64_t L = static_cast<int64_t>(levels.size()), F = features;
  auto out = torch::empty({N, L * F}, unit.options());
  const float* u = unit.data_ptr<float>();
  float* o = out.data_ptr<float>();
  // level by level within a thread's positions: one level's storage (a hashed level's T F floats) stays in the
  // core's cache while its positions read it, where all the levels' would not
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    Corners c;
    for (int64_t l = 0; l < L; ++l) {
      const Level& level = levels[l];
      for (int64_t first = begin; first < end; first += BLOCK) {
        const int64_t count = std::min(BLOCK, end - first);
        corners_of(u + 3 * first, count, level.n, level.hashed, T, level.row_stride, c);
        for (int64_t i = 0; i < count; ++i)
          for (int64_t f = 0; f < F; ++f) {
            const float* values = level.data + f * level.feature_stride;
            float sum = 0;
            for (int k = 0; k < 8; ++k) sum += c.weight[k][i] * values[c.offset[k][i]];
            o[((first + i) * L + l) * F + f] = sum;
          }
      }
    }
  });
  return out;
}

namespace {

// Sums each level's gradient from the features' gradient ``g`` [N, L F] into ``levels`` (zeroed storage of the
// gradients' layout), parallel over levels; with ``touched`` [Lh, T] (or null), marks each hashed row summed into.
void accumulate(const float* u, const float* g, int64_t N, int64_t T, int64_t F, const std::vector<Level>& levels,
                int64_t n_dense, uint8_t* touched) {
  const int64_t L = static_cast<int64_t>(levels.size());
  at::parallel_for(0, L, 1, [&](int64_t begin, int64_t end) {
    Corners c;
    for (int64_t l = begin; l < end; ++l) {
      const Level& level = levels[l];
      uint8_t* marks = (touched != nullptr && level.hashed) ? touched + (l - n_dense) * T : nullptr;
      for (int64_t first = 0; first < N; first += BLOCK) {
        const int64_t count = std::min(BLOCK, N - first);
        corners_of(u + 3 * first, count, level.n, level.hashed, T, level.row_stride, c);
        for (int64_t i = 0; i < count; ++i)
          for (int64_t f = 0; f < F; ++f) {
            const float gradient = g[((first + i) * L + l) * F + f];
            float* values = level.data + f * level.feature_stride;
            for (int k = 0; k < 8; ++k) values[c.offset[k][i]] += c.weight[k][i] * gradient;
          }
        if (marks != nullptr)
          for (int k = 0; k < 8; ++k)
            for (int64_t i = 0; i < count; ++i) marks[c.offset[k][i] / F] = 1;
      }
    }
  });
}

}  // namespace

// The gradients of the dense volumes and of the hashed table (new zero tensors, then summed into), from the
// gradient of the features [N, L F].
std::vector<torch::Tensor> hash_encoding_backward(torch::Tensor unit, torch::Tensor grad,
                                                  std::vector<torch::Tensor> dense, torch::Tensor hashed,
                                                  std::vector<int64_t> dense_res, std::vector<int64_t> hashed_res,
                                                  int64_t features) {
  check_inputs(unit, dense, hashed, dense_res, hashed_res, features, &grad);
  std::vector<torch::Tensor> grads;
  for (auto& volume : dense) grads.push_back(torch::zeros_like(volume));
  auto hashed_grad = torch::zeros_like(hashed);
  std::vector<torch::Tensor> dense_grads(grads.begin(), grads.end());
  const std::vector<Level> levels = levels_of(dense_grads, hashed_grad, dense_res, hashed_res);
  accumulate(unit.data_ptr<float>(), grad.data_ptr<float>(), unit.size(0), hashed.size(1), features, levels,
             static_cast<int64_t>(dense.size()), nullptr);
  grads.push_back(hashed_grad);
  return grads;
}

// As ``hash_encoding_backward``, but summed into the given gradients (of the dense volumes' and the hashed table's
// shapes, contiguous float32, zeros or the sums of earlier calls), in place: the gradients of several calls of one
// backward pass accumulated in one set of tensors, none allocated or zero-filled per call.
void hash_encoding_backward_into(torch::Tensor unit, torch::Tensor grad, std::vector<torch::Tensor> dense_grads,
                                 torch::Tensor hashed_grad, std::vector<int64_t> dense_res,
                                 std::vector<int64_t> hashed_res, int64_t features) {
  check_inputs(unit, dense_grads, hashed_grad, dense_res, hashed_res, features, &grad);
  const std::vector<Level> levels = levels_of(dense_grads, hashed_grad, dense_res, hashed_res);
  accumulate(unit.data_ptr<float>(), grad.data_ptr<float>(), unit.size(0), hashed_grad.size(1), features, levels,
             static_cast<int64_t>(dense_grads.size()), nullptr);
}

// As ``hash_encoding_backward``, but the hashed table's gradient as the rows the positions read, each once:
// their indices [2, U] (level, row; ascending, level first) and summed values [U, F], the parts of a coalesced
// sparse COO tensor of the table's shape. Returns the dense volumes' gradients, then indices, then values.
std::vector<torch::Tensor> hash_encoding_backward_rows(torch::Tensor unit, torch::Tensor grad,
                                                       std::vector<torch::Tensor> dense, torch::Tensor hashed,
                                                       std::vector<int64_t> dense_res,
                                                       std::vector<int64_t> hashed_res, int64_t features) {
  check_inputs(unit, dense, hashed, dense_res, hashed_res, features, &grad);
  const int64_t Lh = hashed.size(0), T = hashed.size(1), F = features;
  std::vector<torch::Tensor> grads;
  for (auto& volume : dense) grads.push_back(torch::zeros_like(volume));
  auto sums = torch::zeros_like(hashed);  // [Lh, T, F]
  auto touched = torch::zeros({Lh, T}, hashed.options().dtype(torch::kUInt8));
  std::vector<torch::Tensor> dense_grads(grads.begin(), grads.end());
  const std::vector<Level> levels = levels_of(dense_grads, sums, dense_res, hashed_res);
  uint8_t* marks = touched.data_ptr<uint8_t>();
  accumulate(unit.data_ptr<float>(), grad.data_ptr<float>(), unit.size(0), T, F, levels,
             static_cast<int64_t>(dense.size()), marks);
  std::vector<int64_t> first(Lh + 1, 0);  // each level's first slot in the output
  at::parallel_for(0, Lh, 1, [&](int64_t begin, int64_t end) {
    for (int64_t h = begin; h < end; ++h) {
      int64_t count = 0;
      for (int64_t r = 0; r < T; ++r) count += marks[h * T + r];
      first[h + 1] = count;
    }
  });
  for (int64_t h = 0; h < Lh; ++h) first[h + 1] += first[h];
  auto indices = torch::empty({2, first[Lh]}, hashed.options().dtype(torch::kInt64));
  auto values = torch::empty({first[Lh], F}, hashed.options());
  int64_t* level_index = indices.data_ptr<int64_t>();
  int64_t* row_index = level_index + first[Lh];
  float* out = values.data_ptr<float>();
  const float* summed = sums.data_ptr<float>();
  at::parallel_for(0, Lh, 1, [&](int64_t begin, int64_t end) {
    for (int64_t h = begin; h < end; ++h) {
      int64_t slot = first[h];
      for (int64_t r = 0; r < T; ++r) {
        if (!marks[h * T + r]) continue;
        level_index[slot] = h;
        row_index[slot] = r;
        for (int64_t f = 0; f < F; ++f) out[slot * F + f] = summed[(h * T + r) * F + f];
        ++slot;
      }
    }
  });
  grads.push_back(indices);
  grads.push_back(values);
  return grads;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &hash_encoding_forward, "the hash encoding's features of unit positions");
  m.def("backward", &hash_encoding_backward, "the gradients of the dense volumes and the hashed table");
  m.def("backward_into", &hash_encoding_backward_into,
        "the gradients of the dense volumes and the hashed table summed into the given ones, in place");
  m.def("backward_rows", &hash_encoding_backward_rows,
        "the dense volumes' gradients, and the hashed table's as the rows read: indices [2, U] and values [U, F]");
}
