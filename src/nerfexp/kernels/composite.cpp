// Volume rendering of sampled rays in one pass per ray (nerfexp.nerf.compositing): the interval weights
// w_i = T_i (1 - exp(-tau_i)), T_i = exp(-sum_{j<i} tau_j), tau_i = sigma_i (end_i - start_i), and from them the
// ray's colour, opacity and depth, as nerfexp.nerf.quadrature's render_weights and composite compute them (the
// torch path, the reference this kernel is tested against), with their gradients with respect to the densities
// and the colours. Parallel over rays; each ray's sums run in double, as ATen's CPU cumsum accumulates floats.
//
// The same arithmetic, operation for operation, as the torch path:
// - tau_i is 0 where sigma_i or the interval's length is 0 (never 0 * inf), inf where the length is infinite
//   (and sigma_i > 0), else sigma_i * length; a NaN density stays NaN;
// - alpha_i = -expm1(-tau_i), T_i = exp(-(exclusive cumulative sum of tau)), w_i = T_i alpha_i;
// - opacity = sum w_i; rgb = sum w_i c_i + (1 - opacity) background; depth = sum (w_i / opacity) t_i where the
//   opacity is positive, else far.
// Backward, with g the gradients of the outputs (any of them may be absent: zeros):
//   G_i = g_w_i + g_rgb . c_i + g_opacity - g_rgb . background + (opacity > 0 ? g_depth (t_i - depth) / opacity : 0)
//   dL/dc_i = g_rgb w_i;   dL/dtau_j = G_j T_j exp(-tau_j) - sum_{i>j} G_i w_i, where T_j exp(-tau_j) = T_{j+1},
//   the transmittance after interval j, which the forward keeps for it (no exponential in the backward)
//   dL/dsigma_j = dL/dtau_j * length_j where tau_j depended on sigma_j (sigma_j != 0, a finite non-zero length), else 0
//
// Inputs: sigmas, starts, ends, t [B, S]; rgbs [B, S, 3]; background [3]; all contiguous, on the CPU, of one
// floating dtype (float32 or float64). A wrong call is a one-line error, checked before anything is read.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <limits>
#include <optional>
#include <vector>

namespace {

constexpr int64_t GRAIN = 16;  // rays per task of at::parallel_for

void check_input(const torch::Tensor& x, const char* name, const torch::Tensor& like, int64_t dim) {
  TORCH_CHECK(x.device().is_cpu(), "composite: ", name, " is on ", x.device(), ", not the CPU");
  TORCH_CHECK(x.is_contiguous(), "composite: ", name, " is not contiguous");
  TORCH_CHECK(x.scalar_type() == like.scalar_type(), "composite: ", name, " is ", x.scalar_type(), ", not ",
              like.scalar_type(), " as sigmas");
  TORCH_CHECK(x.dim() == dim, "composite: ", name, " has ", x.dim(), " dimensions, not ", dim);
}

void check_rays(const torch::Tensor& sigmas, const torch::Tensor& rgbs, const torch::Tensor& starts,
                const torch::Tensor& ends, const torch::Tensor& t, const torch::Tensor& background) {
  TORCH_CHECK(sigmas.scalar_type() == torch::kFloat || sigmas.scalar_type() == torch::kDouble,
              "composite: sigmas is ", sigmas.scalar_type(), ", not float32 or float64");
  check_input(sigmas, "sigmas", sigmas, 2);
  check_input(rgbs, "rgbs", sigmas, 3);
  check_input(starts, "starts", sigmas, 2);
  check_input(ends, "ends", sigmas, 2);
  check_input(t, "t", sigmas, 2);
  check_input(background, "background", sigmas, 1);
  TORCH_CHECK(starts.sizes() == sigmas.sizes() && ends.sizes() == sigmas.sizes() && t.sizes() == sigmas.sizes(),
              "composite: sigmas, starts, ends and t must be [B, S] alike, got ", sigmas.sizes(), ", ",
              starts.sizes(), ", ", ends.sizes(), ", ", t.sizes());
  TORCH_CHECK(rgbs.size(0) == sigmas.size(0) && rgbs.size(1) == sigmas.size(1) && rgbs.size(2) == 3,
              "composite: rgbs must be [B, S, 3] of sigmas' [B, S] = ", sigmas.sizes(), ", got ", rgbs.sizes());
  TORCH_CHECK(background.size(0) == 3, "composite: background must be [3], got ", background.sizes());
}

// The optical depth of one interval, as nerfexp.nerf.quadrature.optical_depths computes it.
template <typename scalar_t>
inline scalar_t optical_depth(scalar_t sigma, scalar_t length) {
  if (sigma == 0 || length == 0) return 0;
  if (std::isinf(length)) return std::numeric_limits<scalar_t>::infinity();
  return sigma * length;
}

// Whether an interval's optical depth varies with its density (its gradient reaches sigma).
template <typename scalar_t>
inline bool depends_on_sigma(scalar_t sigma, scalar_t length) {
  return !(sigma == 0 || length == 0) && !std::isinf(length);
}

template <typename scalar_t>
void forward_rays(const torch::Tensor& sigmas, const torch::Tensor& rgbs, const torch::Tensor& starts,
                  const torch::Tensor& ends, const torch::Tensor& t, const torch::Tensor& background, double far,
                  torch::Tensor& weights, torch::Tensor& after, torch::Tensor& rgb, torch::Tensor& opacity,
                  torch::Tensor& depth) {
  const int64_t B = sigmas.size(0), S = sigmas.size(1);
  const scalar_t* sg = sigmas.data_ptr<scalar_t>();
  const scalar_t* c = rgbs.data_ptr<scalar_t>();
  const scalar_t* s0 = starts.data_ptr<scalar_t>();
  const scalar_t* s1 = ends.data_ptr<scalar_t>();
  const scalar_t* tt = t.data_ptr<scalar_t>();
  const scalar_t* bg = background.data_ptr<scalar_t>();
  scalar_t* w = weights.data_ptr<scalar_t>();
  scalar_t* ta = after.data_ptr<scalar_t>();
  scalar_t* out_rgb = rgb.data_ptr<scalar_t>();
  scalar_t* out_opacity = opacity.data_ptr<scalar_t>();
  scalar_t* out_depth = depth.data_ptr<scalar_t>();
  at::parallel_for(0, B, GRAIN, [&](int64_t begin, int64_t end) {
    for (int64_t b = begin; b < end; ++b) {
      const int64_t row = b * S;
      double tau_before = 0;  // exclusive cumulative sum of tau, in double as ATen's cumsum of floats
      scalar_t transmittance = 1;  // T_i = exp(-tau_before)
      double sum_w = 0, sum_r = 0, sum_g = 0, sum_b = 0;
      for (int64_t i = 0; i < S; ++i) {
        const scalar_t tau = optical_depth(sg[row + i], static_cast<scalar_t>(s1[row + i] - s0[row + i]));
        // an interval that absorbs nothing (an empty cell's samples: most of them) weighs exactly 0 and leaves
        // the transmittance as it was, bit for bit: no exponential for it
        const scalar_t weight = tau == 0 ? scalar_t(0) : transmittance * -std::expm1(-tau);
        w[row + i] = weight;
        if (tau != 0) {
          tau_before += tau;
          transmittance = std::exp(-static_cast<scalar_t>(tau_before));
        }
        ta[row + i] = transmittance;  // T_{i+1}: the backward's d w_i / d tau_i
        sum_w += weight;
        sum_r += static_cast<double>(weight) * c[(row + i) * 3];
        sum_g += static_cast<double>(weight) * c[(row + i) * 3 + 1];
        sum_b += static_cast<double>(weight) * c[(row + i) * 3 + 2];
      }
      const scalar_t o = static_cast<scalar_t>(sum_w);
      out_opacity[b] = o;
      out_rgb[b * 3] = static_cast<scalar_t>(sum_r) + (1 - o) * bg[0];
      out_rgb[b * 3 + 1] = static_cast<scalar_t>(sum_g) + (1 - o) * bg[1];
      out_rgb[b * 3 + 2] = static_cast<scalar_t>(sum_b) + (1 - o) * bg[2];
      if (o > 0) {  // each weight's share of the opacity before it meets t (quadrature.composite's reason)
        double d = 0;
        for (int64_t i = 0; i < S; ++i) d += static_cast<double>(w[row + i] / o) * tt[row + i];
        out_depth[b] = static_cast<scalar_t>(d);
      } else {
        out_depth[b] = static_cast<scalar_t>(far);
      }
    }
  });
}

template <typename scalar_t>
void backward_rays(const torch::Tensor& sigmas, const torch::Tensor& rgbs, const torch::Tensor& starts,
                   const torch::Tensor& ends, const torch::Tensor& t, const torch::Tensor& background,
                   const torch::Tensor& weights, const torch::Tensor& after, const torch::Tensor& opacity,
                   const torch::Tensor& depth,
                   const scalar_t* g_w, const scalar_t* g_rgb, const scalar_t* g_opacity, const scalar_t* g_depth,
                   torch::Tensor& grad_sigmas, torch::Tensor& grad_rgbs) {
  const int64_t B = sigmas.size(0), S = sigmas.size(1);
  const scalar_t* sg = sigmas.data_ptr<scalar_t>();
  const scalar_t* c = rgbs.data_ptr<scalar_t>();
  const scalar_t* s0 = starts.data_ptr<scalar_t>();
  const scalar_t* s1 = ends.data_ptr<scalar_t>();
  const scalar_t* tt = t.data_ptr<scalar_t>();
  const scalar_t* bg = background.data_ptr<scalar_t>();
  const scalar_t* w = weights.data_ptr<scalar_t>();
  const scalar_t* ta = after.data_ptr<scalar_t>();
  const scalar_t* op = opacity.data_ptr<scalar_t>();
  const scalar_t* dp = depth.data_ptr<scalar_t>();
  scalar_t* gs = grad_sigmas.data_ptr<scalar_t>();
  scalar_t* gc = grad_rgbs.data_ptr<scalar_t>();
  at::parallel_for(0, B, GRAIN, [&](int64_t begin, int64_t end) {
    for (int64_t b = begin; b < end; ++b) {
      const int64_t row = b * S;
      const scalar_t r0 = g_rgb ? g_rgb[b * 3] : 0, r1 = g_rgb ? g_rgb[b * 3 + 1] : 0, r2 = g_rgb ? g_rgb[b * 3 + 2] : 0;
      const scalar_t o = op[b];
      // the gradient every weight gets alike: the opacity's, and the background's share of the colour
      const scalar_t common = (g_opacity ? g_opacity[b] : 0) - (r0 * bg[0] + r1 * bg[1] + r2 * bg[2]);
      const scalar_t per_depth = (g_depth && o > 0) ? g_depth[b] / o : 0;
      double behind = 0;  // sum over i > j of G_i w_i
      for (int64_t j = S - 1; j >= 0; --j) {
        const int64_t at = row + j;
        const scalar_t g = (g_w ? g_w[at] : 0) + (r0 * c[at * 3] + r1 * c[at * 3 + 1] + r2 * c[at * 3 + 2]) +
                           common + per_depth * (tt[at] - dp[b]);
        gc[at * 3] = r0 * w[at];
        gc[at * 3 + 1] = r1 * w[at];
        gc[at * 3 + 2] = r2 * w[at];
        const scalar_t g_tau = g * ta[at] - static_cast<scalar_t>(behind);  // T_j exp(-tau_j) = T_{j+1}
        const scalar_t length = s1[at] - s0[at];
        gs[at] = depends_on_sigma(sg[at], length) ? g_tau * length : 0;
        behind += static_cast<double>(g) * w[at];
      }
    }
  });
}

template <typename scalar_t>
const scalar_t* gradient_or_null(const std::optional<torch::Tensor>& g, const char* name,
                                 at::IntArrayRef sizes) {
  if (!g.has_value() || !g->defined()) return nullptr;
  TORCH_CHECK(g->device().is_cpu() && g->is_contiguous() && g->sizes() == sizes,
              "composite: the gradient of ", name, " must be a contiguous CPU tensor of ", sizes, ", got ",
              g->sizes());
  TORCH_CHECK(g->scalar_type() == c10::CppTypeToScalarType<scalar_t>::value, "composite: the gradient of ", name,
              " is ", g->scalar_type(), ", not the rays' dtype");
  return g->data_ptr<scalar_t>();
}

}  // namespace

// (weights [B, S], rgb [B, 3], opacity [B], depth [B], and for the backward the transmittance after each interval
// [B, S]) of the rays' samples.
std::vector<torch::Tensor> composite_forward(torch::Tensor sigmas, torch::Tensor rgbs, torch::Tensor starts,
                                             torch::Tensor ends, torch::Tensor t, torch::Tensor background,
                                             double far) {
  check_rays(sigmas, rgbs, starts, ends, t, background);
  const int64_t B = sigmas.size(0);
  auto weights = torch::empty_like(sigmas);
  auto after = torch::empty_like(sigmas);
  auto rgb = torch::empty({B, 3}, sigmas.options());
  auto opacity = torch::empty({B}, sigmas.options());
  auto depth = torch::empty({B}, sigmas.options());
  AT_DISPATCH_FLOATING_TYPES(sigmas.scalar_type(), "composite_forward", [&] {
    forward_rays<scalar_t>(sigmas, rgbs, starts, ends, t, background, far, weights, after, rgb, opacity, depth);
  });
  return {weights, rgb, opacity, depth, after};
}

// (grad sigmas [B, S], grad rgbs [B, S, 3]) from the gradients of the forward's outputs (None: zeros).
std::vector<torch::Tensor> composite_backward(torch::Tensor sigmas, torch::Tensor rgbs, torch::Tensor starts,
                                              torch::Tensor ends, torch::Tensor t, torch::Tensor background,
                                              torch::Tensor weights, torch::Tensor after, torch::Tensor opacity,
                                              torch::Tensor depth,
                                              std::optional<torch::Tensor> grad_weights,
                                              std::optional<torch::Tensor> grad_rgb,
                                              std::optional<torch::Tensor> grad_opacity,
                                              std::optional<torch::Tensor> grad_depth) {
  check_rays(sigmas, rgbs, starts, ends, t, background);
  check_input(weights, "weights", sigmas, 2);
  check_input(after, "after", sigmas, 2);
  check_input(opacity, "opacity", sigmas, 1);
  check_input(depth, "depth", sigmas, 1);
  const int64_t B = sigmas.size(0);
  TORCH_CHECK(weights.sizes() == sigmas.sizes() && after.sizes() == sigmas.sizes() && opacity.size(0) == B &&
                  depth.size(0) == B,
              "composite: weights and after [B, S], opacity and depth [B] of sigmas' ", sigmas.sizes(), " expected");
  auto grad_sigmas = torch::empty_like(sigmas);
  auto grad_rgbs = torch::empty_like(rgbs);
  AT_DISPATCH_FLOATING_TYPES(sigmas.scalar_type(), "composite_backward", [&] {
    backward_rays<scalar_t>(sigmas, rgbs, starts, ends, t, background, weights, after, opacity, depth,
                            gradient_or_null<scalar_t>(grad_weights, "weights", sigmas.sizes()),
                            gradient_or_null<scalar_t>(grad_rgb, "rgb", {B, 3}),
                            gradient_or_null<scalar_t>(grad_opacity, "opacity", {B}),
                            gradient_or_null<scalar_t>(grad_depth, "depth", {B}), grad_sigmas, grad_rgbs);
  });
  return {grad_sigmas, grad_rgbs};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &composite_forward, "weights, colour, opacity and depth of sampled rays");
  m.def("backward", &composite_backward, "the gradients of the densities and the colours");
}
